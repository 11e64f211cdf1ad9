"""Baselines run in the same harness as colmap-vc: classic COLMAP, mesh alignment
(the latter lives in :mod:`colmap_vc.meshalign`, re-exported here)."""

from __future__ import annotations

import logging
import shutil
from pathlib import Path

import pycolmap

from .evaluation import Metrics, evaluate_reconstruction
from .meshalign import mesh_alignment, mesh_alignment_poses, procrustes

logger = logging.getLogger(__name__)

__all__ = [
    "colmap_incremental",
    "mesh_alignment",
    "mesh_alignment_poses",
    "procrustes",
    "run_classic",
]


def colmap_incremental(
    database_path: Path, image_dir: Path, output_dir: Path, seed: int = 0
) -> pycolmap.Reconstruction | None:
    """COLMAP itself: pycolmap's incremental mapper with COLMAP's default options,
    run as with calibrated cameras: the database's intrinsics held fixed (COLMAP
    refines focal length and distortion by default; on the dense synthetic scene,
    whose intrinsics are exact, that gave AUC@15 12.0 instead of 98.9). One thread
    and a fixed seed, so that a run repeats. On a copy of the database.

    No colmap-vc step runs: not its two-view start for two images, not its checks,
    not its image renumbering. Returns the model with the most registered images,
    or None when COLMAP finds none.
    """
    output_dir.mkdir(parents=True, exist_ok=True)
    copy = output_dir / "database.db"  # the mapper may migrate the schema
    shutil.copyfile(database_path, copy)
    pycolmap.set_random_seed(seed)
    options = pycolmap.IncrementalPipelineOptions(
        num_threads=1,
        random_seed=seed,
        ba_refine_focal_length=False,
        ba_refine_principal_point=False,
        ba_refine_extra_params=False,
    )
    models = pycolmap.incremental_mapping(copy, image_dir, output_dir, options=options)
    copy.unlink()
    if not models:
        return None
    return models[max(models, key=lambda k: (models[k].num_reg_images(), -k))]


def run_classic(
    scene_dir: Path, work_dir: Path
) -> tuple[pycolmap.Reconstruction | None, Metrics]:
    """Classic COLMAP on a synthetic scene: its SIFT database, COLMAP's incremental
    mapping (:func:`colmap_incremental`). The scene stays untouched."""
    gt = pycolmap.Reconstruction(scene_dir / "gt" / "sparse")
    out = work_dir / "classic"
    shutil.rmtree(out, ignore_errors=True)
    rec = colmap_incremental(scene_dir / "database.db", scene_dir / "images", out)
    metrics = evaluate_reconstruction(rec, gt)
    logger.info(
        "classic COLMAP: %d/%d registered, AUC@15/30/45 = %.1f / %.1f / %.1f",
        metrics.num_registered,
        metrics.num_images,
        metrics.auc["15"],
        metrics.auc["30"],
        metrics.auc["45"],
    )
    return rec, metrics
