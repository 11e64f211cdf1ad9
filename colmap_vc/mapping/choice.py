"""Which mapping strategy runs, decided in one place.

- Two images (``auto``): the two-view start from their verified geometry, checked
  against the meshes (:func:`strategies.two_view_initialised`).
- ``mesh``: the mesh-initialised mapper; ``global``: pycolmap's global mapper;
  ``incremental``: pycolmap's incremental mapper, as COLMAP runs it.
- ``auto`` with more images: the incremental mapper, whose model is checked against
  the coarse camera poses the meshes give (mesh alignment). When it contradicts
  them (a mirrored two-view start, typical with one person) or registers fewer
  images than the meshes can place, the mesh-initialised mapper replaces it if it
  does better. Two images that classic (SIFT) matches place are not checked
  against each other: the meshes err more than SIFT does (a prior turned front
  to back is 180 deg off), so they judge only the cameras people place.
"""

from __future__ import annotations

import logging
import shutil
from pathlib import Path

import pycolmap

from ..camera_check import classic_placed
from ..meshalign import mesh_alignment_poses
from . import strategies
from .inputs import MapInputs
from .options import Mapper, MappingOptions
from .priors import prior_deviation_deg

logger = logging.getLogger(__name__)

Models = dict[int | str, pycolmap.Reconstruction]


def map_images(
    inputs: MapInputs, image_dir: Path, output_dir: Path, options: MappingOptions
) -> tuple[Models, int | str | None]:
    """Run the chosen strategy -> (models by output folder name, the largest's)."""
    db, priors = inputs.database_path, inputs.priors
    if len(inputs.mapped) == 2 and options.mapper is Mapper.AUTO:
        rec = strategies.two_view_initialised(
            db,
            inputs.views,
            inputs.geometries,
            image_dir,
            output_dir / "0",
            options,
            priors,
            inputs.mapped,
        )
        models: Models = {} if rec is None else {0: rec}
    elif options.mapper is Mapper.MESH:
        if priors is None:
            raise ValueError("the mesh mapper needs the priors (--priors)")
        rec = strategies.mesh_initialised(
            db, inputs.views, image_dir, output_dir / "0", priors, options
        )
        models = {} if rec is None else {0: rec}
    elif options.mapper is Mapper.GLOBAL:
        models = {
            k: r
            for k, r in strategies.global_(db, image_dir, output_dir, options).items()
        }
    else:
        incremental = strategies.incremental(
            db,
            image_dir,
            output_dir,
            options,
            inputs.mapped,
            only_these=inputs.static is not None,
        )
        models = {k: r for k, r in incremental.items()}
        if options.mapper is Mapper.AUTO and priors is not None:
            models = _mesh_fallback(models, inputs, image_dir, output_dir, options)
    best = max(models, key=lambda k: models[k].num_reg_images(), default=None)
    return models, best


def _mesh_fallback(
    models: Models,
    inputs: MapInputs,
    image_dir: Path,
    output_dir: Path,
    options: MappingOptions,
) -> Models:
    """The incremental models, or the mesh-initialised one where it does better."""
    priors = inputs.priors
    assert priors is not None
    if len(inputs.mapped) <= 2:
        return models
    key = max(models, key=lambda k: models[k].num_reg_images(), default=None)
    best = None if key is None else models[key]
    # Two images that classic matches place are not judged against each other by
    # the meshes: a prior's error (a mesh turned front to back) is not theirs.
    pinned = (
        frozenset()
        if best is None
        else frozenset(
            best.image(i).name
            for i in classic_placed(
                best,
                inputs.num_classic,
                options.keypoint_ba_options.min_classic_support,
            )
        )
    )
    deviation = 180.0 if best is None else prior_deviation_deg(best, priors, pinned)
    placeable = len(
        mesh_alignment_poses(priors, image_names=set(inputs.views.image_names))
    )
    num_best = 0 if best is None else best.num_reg_images()
    contradicts = deviation > options.max_prior_deviation_deg
    if not contradicts and num_best >= placeable:
        if num_best and len(pinned) >= num_best:
            logger.info(
                "classic matches place every image of the incremental model: the "
                "meshes do not judge it"
            )
        else:
            logger.info(
                "the incremental model agrees with the mesh prior (median %.0f deg)",
                deviation,
            )
        return models
    if best is None:
        why = "the incremental mapper found no model"
    elif contradicts:
        why = (
            f"the incremental model contradicts the mesh prior (median "
            f"{deviation:.0f} deg > {options.max_prior_deviation_deg:.0f})"
        )
    else:
        why = (
            f"the incremental model registers {num_best} images, the meshes "
            f"place {placeable}"
        )
    logger.info("%s: mesh-initialised mapping instead", why)
    rec = strategies.mesh_initialised(
        inputs.database_path,
        inputs.views,
        image_dir,
        output_dir / "mesh",
        priors,
        options,
    )
    if rec is not None and (
        best is None
        or rec.num_reg_images() > num_best
        or (contradicts and rec.num_reg_images() >= 0.8 * num_best)
    ):
        for k in models:  # superseded: keep one answer on disk
            shutil.rmtree(output_dir / str(k), ignore_errors=True)
        return {"mesh": rec}
    shutil.rmtree(output_dir / "mesh", ignore_errors=True)  # not adopted
    return models
