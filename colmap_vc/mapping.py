"""pycolmap incremental mapping: options, progress, model selection."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path

import pycolmap

logger = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True, slots=True)
class MappingOptions:
    """Options of the incremental mapper."""

    refine_intrinsics: bool = False
    """Refine focal length, principal point and distortion (off: known intrinsics)."""
    num_threads: int = -1
    """Threads (-1: all cores)."""
    seed: int = 0
    """Seed of COLMAP's RANSAC (pycolmap.set_random_seed)."""
    min_num_matches: int = 15
    """Minimum verified matches for a pair to enter the scene graph."""
    init_min_num_inliers: int = 100
    """Minimum inliers of the initial pair."""
    init_min_tri_angle_deg: float = 16.0
    """Minimum triangulation angle of the initial pair, degrees."""
    abs_pose_min_num_inliers: int = 30
    """Minimum 2D-3D inliers to register an image."""
    multiple_models: bool = True
    """Allow several models (the largest one is returned)."""


@dataclass(frozen=True, kw_only=True, slots=True)
class MappingSummary:
    """What the mapper produced."""

    num_models: int
    num_registered: int
    num_images: int
    model_dir: Path | None
    elapsed_s: float


def pipeline_options(options: MappingOptions) -> pycolmap.IncrementalPipelineOptions:
    """pycolmap options from ours."""
    pipeline = pycolmap.IncrementalPipelineOptions(
        num_threads=options.num_threads,
        min_num_matches=options.min_num_matches,
        multiple_models=options.multiple_models,
        ba_refine_focal_length=options.refine_intrinsics,
        ba_refine_principal_point=False,
        ba_refine_extra_params=options.refine_intrinsics,
    )
    pipeline.mapper.init_min_num_inliers = options.init_min_num_inliers
    pipeline.mapper.init_min_tri_angle = options.init_min_tri_angle_deg
    pipeline.mapper.abs_pose_min_num_inliers = options.abs_pose_min_num_inliers
    return pipeline


def run_incremental(
    database_path: Path,
    image_dir: Path,
    output_dir: Path,
    options: MappingOptions | None = None,
    num_images: int | None = None,
) -> tuple[pycolmap.Reconstruction | None, MappingSummary]:
    """Run pycolmap's incremental mapper; return the largest model (or None).

    The models are written to ``output_dir/<k>``; the largest is also returned.
    """
    options = options or MappingOptions()
    output_dir.mkdir(parents=True, exist_ok=True)
    pycolmap.set_random_seed(options.seed)
    t0 = time.perf_counter()
    models = pycolmap.incremental_mapping(
        database_path, image_dir, output_dir, options=pipeline_options(options)
    )
    elapsed = time.perf_counter() - t0
    best_key = max(models, key=lambda k: models[k].num_reg_images(), default=None)
    best = None if best_key is None else models[best_key]
    summary = MappingSummary(
        num_models=len(models),
        num_registered=0 if best is None else best.num_reg_images(),
        num_images=num_images if num_images is not None else -1,
        model_dir=None if best_key is None else output_dir / str(best_key),
        elapsed_s=elapsed,
    )
    logger.info(
        "mapping: %d model(s), largest registers %d image(s), %.1f s",
        summary.num_models, summary.num_registered, elapsed,
    )
    return best, summary
