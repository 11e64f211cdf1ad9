"""The post-mapping pass of `colmap-vc map`: generalized bundle adjustment (GBA).

Reads the VC tuples `augment` stored in the database, refines a copy of the mapper's
model with :mod:`colmap_vc.gba`, and writes it as a COLMAP model (.bin and .txt) plus
PLY files of the VC tuples and the scene points.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path

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


def refine_model(
    database_path: Path,
    rec: pycolmap.Reconstruction,
    output_dir: Path | None,
    options: GbaOptions | None = None,
) -> RefineSummary:
    """GBA of ``rec`` with the database's VCs; writes the refined model to output_dir.

    A database that was never augmented has no VCs: the model is returned unchanged
    and the pass says so.
    """
    t0 = time.perf_counter()
    keypoints, pairs = database.read_virtual_correspondences(database_path)
    if not pairs:
        logger.info("GBA: %s has no virtual correspondences: nothing to refine", database_path)
        return RefineSummary(reconstruction=rec, result=None, output_dir=None, elapsed_s=0.0)
    views = database.read_views(database_path)
    num_classic = dict(zip(views.image_ids.tolist(), views.num_keypoints.tolist(), strict=True))
    refined, result = refine_reconstruction(
        rec, keypoints, pairs, options, image_id_to_num_classic=num_classic
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
        s.initial_cost, s.final_cost, s.num_iterations, elapsed, output_dir,
    )
    return RefineSummary(reconstruction=refined, result=result, output_dir=output_dir, elapsed_s=elapsed)
