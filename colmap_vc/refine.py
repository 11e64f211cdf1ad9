"""The post-mapping pass of `colmap-vc map`: generalized bundle adjustment (GBA).

Reads the VC tuples `augment` stored in the database, refines a copy of the mapper's
model with :mod:`colmap_vc.gba`, and writes it as a COLMAP model (.bin and .txt) plus
PLY files of the VC tuples and the scene points.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap

from . import database
from .gba import GbaOptions, GbaResult, export_ply, refine_reconstruction

logger = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True, slots=True)
class RefineSummary:
    """What the GBA pass did."""

    reconstruction: pycolmap.Reconstruction
    result: GbaResult | None  # None: the database has no VCs (nothing to refine)
    output_dir: Path | None
    elapsed_s: float


def _vc_budget(
    rec: pycolmap.Reconstruction,
    pairs: list,
    num_classic: dict[int, int],
    variance_ratio: float,
) -> int | None:
    """VC tuples per pair for GBA: None (all) unless the model has classic points."""
    num_classic_obs = 0
    for image in rec.images.values():  # loop over images, vectorized over points
        if image.has_pose:
            idx = np.asarray(image.get_observation_point2D_idxs(), dtype=np.int64)
            num_classic_obs += int((idx < num_classic.get(image.image_id, 0)).sum())
    if num_classic_obs == 0 or not pairs:
        return None
    median = float(np.median([int(p.is_inlier.sum()) for p in pairs]))
    return max(5, math.ceil(median / variance_ratio))


def refine_model(
    database_path: Path,
    rec: pycolmap.Reconstruction,
    output_dir: Path | None,
    options: GbaOptions | None = None,
    vc_to_classic_variance: float = 36.0,
    max_classic_inliers: int = 100,
) -> RefineSummary:
    """GBA of ``rec`` with the database's VCs; writes the refined model to output_dir.

    A database that was never augmented has no VCs: the model is returned unchanged
    and the pass says so. When the model also holds classic (SIFT) observations, VCs
    count as noisier: a VC pixel carries a few pixels of prior error against a
    fraction of a pixel for SIFT (variance ratio ``vc_to_classic_variance``, about
    (3 px / 0.5 px)^2). The solver weighs all residuals alike, so the VC tuples of
    each pair are thinned by that ratio instead (an even subsample), which keeps
    classic matches from being drowned out on overlapping views. Pairs that already
    have ``max_classic_inliers`` classic inliers or more (overlapping views, where
    SIFT is far more precise than any human prior) contribute no VC tuples at all.
    """
    t0 = time.perf_counter()
    keypoints, pairs = database.read_virtual_correspondences(database_path)
    if not pairs:
        logger.info(
            "GBA: %s has no virtual correspondences: nothing to refine", database_path
        )
        return RefineSummary(
            reconstruction=rec, result=None, output_dir=None, elapsed_s=0.0
        )
    classic = database.read_two_view_geometries(database_path, include_vc=False)
    strong = {
        p
        for p, row in classic.items()
        if len(row.inlier_matches) >= max_classic_inliers
    }
    pairs = [p for p in pairs if (p.image_id1, p.image_id2) not in strong]
    if not pairs:
        logger.info(
            "GBA: every VC pair has strong classic geometry: plain BA is enough"
        )
        return RefineSummary(
            reconstruction=rec, result=None, output_dir=None, elapsed_s=0.0
        )
    views = database.read_views(database_path)
    num_classic = dict(
        zip(views.image_ids.tolist(), views.num_keypoints.tolist(), strict=True)
    )
    cap = _vc_budget(rec, pairs, num_classic, vc_to_classic_variance)
    refined, result = refine_reconstruction(
        rec,
        keypoints,
        pairs,
        options,
        image_id_to_num_classic=num_classic,
        max_vcs_per_pair=cap,
    )
    if output_dir is not None:
        output_dir.mkdir(parents=True, exist_ok=True)
        refined.write_binary(str(output_dir))
        refined.write_text(str(output_dir))
        export_ply(result, output_dir / "vc_tuples.ply", output_dir / "points.ply")
    elapsed = time.perf_counter() - t0
    s = result.summary
    logger.info(
        "GBA: cost %.4g -> %.4g in %d iterations (%.1f s); model written to %s",
        s.initial_cost,
        s.final_cost,
        s.num_iterations,
        elapsed,
        output_dir,
    )
    return RefineSummary(
        reconstruction=refined, result=result, output_dir=output_dir, elapsed_s=elapsed
    )
