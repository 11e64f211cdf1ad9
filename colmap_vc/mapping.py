"""`colmap-vc map`: pycolmap mapping of an (augmented) database, with progress and a
summary that says which images were registered and why the others were not.

Options: :mod:`colmap_vc.mapping_options`; starts from the meshes:
:mod:`colmap_vc.mapping_init`; checks against the meshes and the priors used:
:mod:`colmap_vc.mapping_priors`.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import shutil
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

import pycolmap

from . import __version__, canonical, database, outputs
from .camera_check import classic_support
from .gba.ceres import bundle_adjust_inplace
from .keypoint_ba import keypoint_bundle_adjustment, with_loss_scale
from .mapping_init import mesh_initialised, two_view_initialised
from .mapping_options import (
    Mapper,
    MappingOptions,
    MappingSummary,
    global_options,
    incremental_options,
)
from .mapping_priors import (
    keypoint_mirror,
    leave_out_prior_outliers_inplace,
    load_priors,
    prior_deviation_deg,
    with_associated_ids,
)
from .meshalign import mesh_alignment_poses
from .metric_scale import (
    apply_metric_scale_inplace,
    estimate_metric_scale,
    write_metric_scale,
)
from .static_cameras import StaticCameras, parse_static_cameras

__all__ = [
    "OPTIONS_FILE",
    "OUTPUT_MARKER",
    "Mapper",
    "MappingOptions",
    "MappingSummary",
    "leave_out_prior_outliers_inplace",
    "run",
    "run_incremental",
    "with_associated_ids",
]

logger = logging.getLogger(__name__)


def _why_unregistered(
    database_path: Path, best: pycolmap.Reconstruction | None
) -> dict[str, str]:
    """A reason per image of the database missing from the model."""
    views = database.read_views(database_path)
    geometries = database.read_two_view_geometries(database_path, include_vc=True)
    registered = (
        set()
        if best is None
        else {im.name for im in best.images.values() if im.has_pose}
    )
    id_of_name = dict(zip(views.image_names, views.image_ids.tolist(), strict=True))
    reg_ids = {id_of_name[n] for n in registered if n in id_of_name}
    reasons = {}
    for name, image_id in id_of_name.items():
        if name in registered:
            continue
        pairs = [
            p
            for p, row in geometries.items()
            if image_id in p and len(row.inlier_matches) > 0
        ]
        with_registered = [p for p in pairs if (set(p) - {image_id}) & reg_ids]
        if not pairs:
            reasons[name] = (
                "no verified image pair: no classic matches survived verification "
                "and no virtual correspondences (no priors, or no person shared "
                "with other images)"
            )
        elif not with_registered:
            reasons[name] = (
                f"{len(pairs)} verified pair(s), none with a registered image "
                "(a separate component of the scene graph)"
            )
        else:
            reasons[name] = (
                f"{len(with_registered)} verified pair(s) with registered images, but "
                "registration failed (too few 2D-3D inliers)"
            )
    return reasons


def run(
    database_path: Path,
    image_dir: Path,
    output_dir: Path,
    options: MappingOptions | None = None,
    *,
    overwrite: bool = False,
    priors_path: Path | None = None,
) -> tuple[pycolmap.Reconstruction, MappingSummary]:
    """Map a database; the final model goes to ``output_dir/0`` (with the options it
    was made with, :data:`OPTIONS_FILE`) and is returned; smaller models of image
    groups it could not join follow at ``output_dir/1``, ....

    Raises:
        FileNotFoundError: the database or image folder is missing.
        FileExistsError: ``output_dir`` is not empty and ``overwrite`` is False.
        RuntimeError: the mapper found no model (the reason is in the message).
    """
    options = options or MappingOptions()
    database_path, image_dir, output_dir = (
        Path(database_path),
        Path(image_dir),
        Path(output_dir),
    )
    if not database_path.is_file():
        raise FileNotFoundError(f"database not found: {database_path}")
    if not image_dir.is_dir():
        raise FileNotFoundError(f"image folder not found: {image_dir}")
    outputs.prepare_output_dir(
        output_dir,
        "map",
        overwrite=overwrite,
        inputs=[database_path, image_dir, *([priors_path] if priors_path else [])],
    )
    # pycolmap's mappers open their database read-write and migrate its schema:
    # they get a copy, the user's database is only read (docs/database.md).
    # Same input, same output: the copy is numbered by image name (the mappers
    # break ties by ids, which follow the order extraction wrote the images).
    with tempfile.TemporaryDirectory(prefix=".work-", dir=output_dir) as work:
        copy = database.snapshot(database_path, Path(work) / "copy.db")
        ordered = Path(work) / "database.db"
        ids = canonical.canonical_copy(copy, ordered)
        rec, summary = _map_copy(
            ordered if ids else copy, image_dir, output_dir, options, priors_path
        )
    if ids is not None:  # the models get the user's ids back
        for folder in sorted(output_dir.iterdir()):
            if (folder / "images.bin").is_file():
                canonical.relabel(pycolmap.Reconstruction(folder), *ids).write(folder)
        rec = canonical.relabel(rec, *ids)
    model_dir = _number_models(output_dir, summary.model_dir)
    _write_run_options(
        model_dir, options, database_path, image_dir, priors_path, summary
    )
    summary = dataclasses.replace(summary, model_dir=model_dir)
    logger.info(
        "mapping: %d model(s); the largest registers %d/%d images (%.1f s)",
        summary.num_models,
        summary.num_registered,
        summary.num_images,
        summary.elapsed_s,
    )
    for name, reason in summary.unregistered.items():
        logger.info("not registered: %s: %s", name, reason)
    return rec, summary


def _map_copy(
    database_path: Path,
    image_dir: Path,
    output_dir: Path,
    options: MappingOptions,
    priors_path: Path | None,
) -> tuple[pycolmap.Reconstruction, MappingSummary]:
    """:func:`run` on a copy of the user's database (pycolmap may write to it)."""
    views = database.read_views(database_path)
    num_images = len(views.image_names)
    static = _static_cameras(options, database_path, views.image_names)
    mapped = (
        list(views.image_names)
        if static is None
        else sorted({*static.representative.values(), *static.unmatched})
    )
    pycolmap.set_random_seed(options.seed)
    t0 = time.perf_counter()
    priors = load_priors(database_path, priors_path, views.image_names, static)
    timings = {"read": time.perf_counter() - t0}
    lap = time.perf_counter()
    if len(mapped) == 2 and options.mapper is Mapper.AUTO:
        rec = two_view_initialised(
            database_path, image_dir, output_dir / "0", options, priors
        )
        models = {} if rec is None else {0: rec}
    elif options.mapper is Mapper.MESH:
        if priors is None:
            raise ValueError("the mesh mapper needs the priors (--priors)")
        rec = mesh_initialised(
            database_path, image_dir, output_dir / "0", priors, options
        )
        models = {} if rec is None else {0: rec}
    elif options.mapper is Mapper.GLOBAL:
        models = pycolmap.global_mapping(
            database_path, image_dir, output_dir, options=global_options(options)
        )
    else:
        registered = [0]

        def on_init() -> None:
            logger.info("initial pair chosen")

        def on_next() -> None:
            registered[0] += 1
            if options.show_progress:
                logger.info("registered image %d/%d", registered[0] + 2, len(mapped))

        pipeline = incremental_options(options, len(mapped))
        if static is not None:
            pipeline.image_names = mapped  # one view per static camera
        models = pycolmap.incremental_mapping(
            database_path,
            image_dir,
            output_dir,
            options=pipeline,
            initial_image_pair_callback=on_init,
            next_image_callback=on_next,
        )
    best_key = max(models, key=lambda k: models[k].num_reg_images(), default=None)
    best = None if best_key is None else models[best_key]
    timings["mapper"] = time.perf_counter() - lap
    lap = time.perf_counter()
    if options.mapper is Mapper.AUTO and priors is not None and len(mapped) > 2:
        deviation = 180.0 if best is None else prior_deviation_deg(best, priors)
        placeable = len(
            mesh_alignment_poses(priors, image_names=set(views.image_names))
        )
        num_best = 0 if best is None else best.num_reg_images()
        if deviation > options.max_prior_deviation_deg or num_best < placeable:
            logger.info(
                "the incremental model %s: mesh-initialised mapping instead",
                f"contradicts the mesh prior (median {deviation:.0f} deg > "
                f"{options.max_prior_deviation_deg:.0f})"
                if deviation > options.max_prior_deviation_deg
                else f"registers {num_best} images, the meshes place {placeable}",
            )
            rec = mesh_initialised(
                database_path, image_dir, output_dir / "mesh", priors, options
            )
            if rec is not None and (
                best is None
                or rec.num_reg_images() > num_best
                or (
                    deviation > options.max_prior_deviation_deg
                    and rec.num_reg_images() >= 0.8 * num_best
                )
            ):
                for key in models:  # superseded: keep one answer on disk
                    shutil.rmtree(output_dir / str(key), ignore_errors=True)
                models, best_key, best = {"mesh": rec}, "mesh", rec
        else:
            logger.info(
                "the incremental model agrees with the mesh prior (median %.0f deg)",
                deviation,
            )
    timings["mesh_fallback"] = time.perf_counter() - lap
    lap = time.perf_counter()
    left_out: dict[str, str] = {}
    mirrored: tuple[str, ...] = ()
    people = None
    if best is not None and options.keypoint_ba:
        best, kba = keypoint_bundle_adjustment(
            database_path,
            best,
            options.keypoint_ba_options,
            mirror=keypoint_mirror(database_path, priors),
        )
        models[best_key] = best
        left_out.update(kba.left_out or {})
        mirrored = kba.mirrored
        people = kba.people
    timings["keypoint_ba"] = time.perf_counter() - lap
    lap = time.perf_counter()
    if best is not None and priors is not None:
        # On the final poses: the keypoint BA can carry a camera far from its start.
        # An image re-posed with left and right exchanged has a mesh turned front
        # to back: the meshes cannot judge it.
        # An image that classic keypoints place is not judged by its people either.
        num_classic = dict(
            zip(views.image_ids.tolist(), views.num_keypoints.tolist(), strict=True)
        )
        pinned = {
            best.image(i).name
            for i, n in classic_support(best, num_classic).items()
            if n >= options.keypoint_ba_options.min_classic_support
        }
        left_out.update(
            leave_out_prior_outliers_inplace(
                best,
                priors,
                options.max_image_prior_deviation_deg,
                exempt=frozenset(mirrored) | frozenset(pinned),
            )
        )
        if left_out:
            kba_options = with_loss_scale(options.keypoint_ba_options, best)
            bundle_adjust_inplace(best, kba_options.loss_scale_px, people)
    timings["checks"] = time.perf_counter() - lap
    lap = time.perf_counter()
    scale = None
    if best is not None and priors is not None and options.metric_scale:
        scale = estimate_metric_scale(database_path, best, priors)
        if scale is None:
            logger.info("metric scale: no triangulated keypoints: scale arbitrary")
        else:
            apply_metric_scale_inplace(best, scale)
            logger.info(
                "metric scale: x%.4f to metres (spread %.1f%% over %d person views "
                "of %d people)",
                scale.scale,
                100 * scale.spread,
                scale.num_person_views,
                scale.num_people,
            )
    if best is not None and static is not None:
        add_static_members_inplace(best, static, views)
    if best is not None and (
        options.keypoint_ba or left_out or static is not None or scale is not None
    ):
        best.write(output_dir / str(best_key))
    if best is not None and scale is not None:
        write_metric_scale(output_dir / str(best_key), scale)
    timings["scale_write"] = time.perf_counter() - lap
    elapsed = time.perf_counter() - t0
    reasons = {**_why_unregistered(database_path, best), **left_out}
    if best is None:
        why = "; ".join(f"{n}: {r}" for n, r in list(reasons.items())[:5])
        raise RuntimeError(f"the mapper found no model ({num_images} images). {why}")
    summary = MappingSummary(
        num_models=len(models),
        num_images=num_images,
        registered=sorted(im.name for im in best.images.values() if im.has_pose),
        unregistered=reasons,
        model_dir=output_dir / str(best_key),
        elapsed_s=elapsed,
        metric_scale=scale,
        timings_s=timings,
    )
    return best, summary


OPTIONS_FILE = "map_options.json"
"""Beside the final model: the options and inputs `map` ran with."""


def _number_models(output_dir: Path, best: Path | None) -> Path:
    """The final model at ``output_dir/0``, as COLMAP numbers its first; smaller
    models of other image groups (several components) follow at 1, 2, ... by size.

    The mappers name their folders by their own order ("0", "1", ...; "mesh" for
    the mesh-initialised one), and a superseded model is already removed.
    """
    folders = sorted(p for p in output_dir.iterdir() if (p / "images.bin").is_file())
    if best is None or best not in folders:
        return output_dir / "0"
    size = {p: pycolmap.Reconstruction(p).num_reg_images() for p in folders}
    others = sorted((p for p in folders if p != best), key=lambda p: (-size[p], p.name))
    order = [best, *others]
    staged = []
    for k, folder in enumerate(order):  # two steps: "1" may become "0" and back
        tmp = output_dir / f".model-{k}"
        folder.rename(tmp)
        staged.append(tmp)
    for k, tmp in enumerate(staged):
        tmp.rename(output_dir / str(k))
    return output_dir / "0"


def _write_run_options(
    model_dir: Path,
    options: MappingOptions,
    database_path: Path,
    image_dir: Path,
    priors_path: Path | None,
    summary: MappingSummary,
) -> None:
    """What this model was made from and with, beside it (:data:`OPTIONS_FILE`)."""
    record = {
        "colmap_vc_version": __version__,
        "pycolmap_version": pycolmap.__version__,
        "database": str(database_path.resolve()),
        "image_path": str(image_dir.resolve()),
        "priors": None if priors_path is None else str(Path(priors_path).resolve()),
        "options": outputs.jsonable(dataclasses.asdict(options)),
        "registered": summary.num_registered,
        "images": summary.num_images,
        "timings_s": summary.timings_s,
    }
    (model_dir / OPTIONS_FILE).write_text(json.dumps(record, indent=1) + "\n")


OUTPUT_MARKER = outputs.marker_name("map")
"""File `map` writes into its output folder: `--overwrite` removes only such folders."""


def _static_cameras(
    options: MappingOptions, database_path: Path, image_names: Sequence[str]
) -> StaticCameras | None:
    """The static cameras given, else those `augment` recorded, else None."""
    pattern = options.static_cameras
    if pattern is None:
        recorded = database.read_run_info(database_path).get("options", {})
        pattern = recorded.get("static_cameras") if isinstance(recorded, dict) else None
    return None if not pattern else parse_static_cameras(pattern, image_names)


def add_static_members_inplace(
    rec: pycolmap.Reconstruction, static: StaticCameras, views: database.DatabaseViews
) -> None:
    """Every image of a registered static camera gets its representative's pose."""
    camera_of = dict(zip(views.image_names, views.camera_ids.tolist(), strict=True))
    id_of = dict(zip(views.image_names, views.image_ids.tolist(), strict=True))
    for rep in sorted(static.representative.values()):
        image = rec.find_image_with_name(rep)
        if image is None or not image.has_pose:
            continue
        pose = image.cam_from_world()
        for name in static.members(rep):
            if name == rep or rec.find_image_with_name(name) is not None:
                continue
            camera_id = int(camera_of[name])
            if camera_id not in rec.cameras:
                rec.add_camera_with_trivial_rig(views.cameras[camera_id])
            rec.add_image_with_trivial_frame(
                pycolmap.Image(name=name, camera_id=camera_id, image_id=id_of[name]),
                pycolmap.Rigid3d(pose.rotation, pose.translation),
            )


def run_incremental(
    database_path: Path,
    image_dir: Path,
    output_dir: Path,
    options: MappingOptions | None = None,
) -> tuple[pycolmap.Reconstruction | None, MappingSummary | None]:
    """Like :func:`run` but returns (None, None) instead of raising when no model.

    Used by the benchmarks and the demo's variants, where a failure is a result to
    report.
    """
    try:
        return run(database_path, image_dir, output_dir, options, overwrite=True)
    except RuntimeError as exc:
        logger.info("%s", exc)
        return None, None
