"""Baselines run in the same harness as colmap-vc: classic COLMAP, mesh alignment
(the latter lives in :mod:`colmap_vc.meshalign`, re-exported here)."""

from __future__ import annotations

import logging
import shutil
from pathlib import Path

import pycolmap

from .evaluation import Metrics, evaluate_reconstruction
from .mapping import COLMAP_DEFAULTS, MappingOptions, run_incremental
from .meshalign import mesh_alignment, mesh_alignment_poses, procrustes

logger = logging.getLogger(__name__)

__all__ = ["mesh_alignment", "mesh_alignment_poses", "procrustes", "run_classic"]


def run_classic(
    scene_dir: Path, work_dir: Path, options: MappingOptions | None = None
) -> tuple[pycolmap.Reconstruction | None, Metrics]:
    """Classic COLMAP on a synthetic scene: its SIFT database, incremental mapping.

    The scene's database is copied first, so the scene stays untouched.
    """
    work_dir.mkdir(parents=True, exist_ok=True)
    db = work_dir / "classic.db"
    shutil.copyfile(scene_dir / "database.db", db)
    gt = pycolmap.Reconstruction(scene_dir / "gt" / "sparse")
    rec, _ = run_incremental(
        db,
        scene_dir / "images",
        work_dir / "classic",
        options or COLMAP_DEFAULTS,
        num_images=gt.num_images(),
    )
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
