"""`colmap-vc map` as one pipeline: inputs, mapping, refinement, checks, outputs.

1. The inputs are read once (:mod:`.inputs`) from a copy of the user's database.
2. The strategy is chosen in one place (:mod:`.choice`).
3. The refinement: the keypoint bundle adjustment, or the generalized one with
   ``--gba`` (:mod:`colmap_vc.keypoint_ba`, docs/gba.md), with its camera check.
4. The checks against the meshes: a camera that contradicts them is left out;
   when two images remain they are mapped again on their own and adjusted.
5. The cameras' up from the scene's vertical lines (:mod:`.up`; ``--no-gravity``
   skips it).
6. The metric scale from the people's size.
7. The outputs: the final model at ``OUTPUT/0`` with the options beside it, its
   points without the observations the refinement weighed as outliers.
"""

from __future__ import annotations

import dataclasses
import logging
import shutil
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import NoReturn

import pycolmap

from .. import canonical, database, outputs
from ..camera_check import classic_placed
from ..gba.ceres import PeopleNoise, bundle_adjust_inplace
from ..keypoint_ba import keypoint_bundle_adjustment, with_loss_scale
from ..metric_scale import (
    TWO_VIEW_POSE_SD_DEG,
    MetricScale,
    apply_metric_scale_inplace,
    estimate_metric_scale,
    write_metric_scale,
)
from ..static_cameras import merge_priors
from . import strategies
from .choice import map_images
from .inputs import MapInputs, read_inputs
from .options import MappingOptions, MappingSummary
from .outputs import (
    OUTLIER_LOSS_SCALES,
    add_static_members_inplace,
    drop_outlier_observations_inplace,
    leave_out_unobserved_inplace,
    number_models,
    static_members_left_out,
    why_unregistered,
    write_run_options,
)
from .priors import leave_out_prior_outliers_inplace, leave_out_tilted_inplace
from .up import refine_with_gravity_inplace, write_gravity

logger = logging.getLogger(__name__)


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
        try:
            ids = canonical.canonical_copy(copy, ordered)
            rec, summary = _map_copy(
                ordered if ids else copy, image_dir, output_dir, options, priors_path
            )
        except (ValueError, RuntimeError) as exc:
            named = _naming(exc, (ordered, copy), database_path)
            if named is exc:
                raise
            raise named from exc
    if ids is not None:  # the models get the user's ids back
        for folder in sorted(output_dir.iterdir()):
            if (folder / "images.bin").is_file():
                canonical.relabel(pycolmap.Reconstruction(folder), *ids).write(folder)
        rec = canonical.relabel(rec, *ids)
    model_dir = number_models(output_dir, summary.model_dir)
    write_run_options(
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


def _check_image_folder(image_dir: Path, names: Sequence[str]) -> None:
    """Refuse a folder that holds none of the database's images (a wrong
    --image-path: the gravity step and the report read them); warn when some
    are missing."""
    missing = [n for n in names if not (image_dir / n).is_file()]
    if names and len(missing) == len(names):
        raise FileNotFoundError(
            f"none of the database's {len(names)} images is in {image_dir} (e.g. "
            f"{missing[0]}): --image-path must be the folder the features were "
            "extracted from"
        )
    if missing:
        logger.warning(
            "%d of the database's %d images are not in %s (e.g. %s): no up from "
            "their vertical lines",
            len(missing),
            len(names),
            image_dir,
            missing[0],
        )


def _naming(exc: Exception, copies: tuple[Path, ...], database_path: Path) -> Exception:
    """``exc`` with the working copies' paths replaced by the user's database."""
    message = str(exc)
    for path in copies:
        message = message.replace(str(path), str(database_path))
    if message == str(exc):
        return exc
    try:
        return type(exc)(message)
    except TypeError:  # an exception type with other arguments: as it was
        return exc


def _map_copy(
    database_path: Path,
    image_dir: Path,
    output_dir: Path,
    options: MappingOptions,
    priors_path: Path | None,
) -> tuple[pycolmap.Reconstruction, MappingSummary]:
    """:func:`run` on a copy of the user's database (pycolmap may write to it)."""
    pycolmap.set_random_seed(options.seed)
    t0 = time.perf_counter()
    inputs = read_inputs(database_path, options, priors_path)
    _check_image_folder(image_dir, inputs.views.image_names)
    if inputs.focal_guessed and inputs.priors is not None:
        logger.warning(
            "%d of %d images have no known focal length (%s; COLMAP guessed it, "
            "1.2 times the larger side when neither the user nor EXIF gives one): "
            "their people's depth is proportional to it and a person's size "
            "against the cameras' distances follows it, so the model stays at "
            "COLMAP's arbitrary scale, and their poses follow it too "
            "(pose2sim_single, each instant on its own: 12.7 deg median pair "
            "error with the guess, 2.3 with the calibration). Give the "
            "intrinsics when you extract features "
            '(docs/real-data.md, "Photos and a COLMAP database")',
            len(inputs.focal_guessed),
            len(inputs.views.image_names),
            _names(inputs.focal_guessed),
        )
    timings = {"read": time.perf_counter() - t0}
    lap = time.perf_counter()
    models, best_key = map_images(inputs, image_dir, output_dir, options)
    best = None if best_key is None else models[best_key]
    timings["mapper"] = time.perf_counter() - lap
    lap = time.perf_counter()
    left_out: dict[str, str] = {}
    mirrored: tuple[str, ...] = ()
    re_posed: dict[str, str] = {}
    people = None
    tracks = None
    if best is not None and best_key is not None and options.keypoint_ba:
        best, kba = keypoint_bundle_adjustment(
            inputs.records,
            best,
            options.keypoint_ba_options,
            mirror=inputs.mirror,
            instant_of=inputs.instant_of,
        )
        models[best_key] = best
        left_out.update(kba.left_out or {})
        mirrored, people, tracks = kba.mirrored, kba.people, kba.tracks
        re_posed = {
            name: (
                "re-posed with its people's left and right exchanged (a pose "
                "estimator saw them from the back as if from the front)"
                if name in mirrored
                else "re-posed by PnP on the keypoints the other cameras triangulate"
            )
            for name in kba.relocalised
        }
    timings["refinement"] = time.perf_counter() - lap
    lap = time.perf_counter()
    if best is not None and inputs.priors is not None:
        meshes_left = _check_against_meshes(best, inputs, options, mirrored, people)
        left_out.update(meshes_left)
        two_left = meshes_left and best.num_reg_images() == 2
        if two_left and best_key is not None and options.keypoint_ba:
            # Two images left: mapped again on their own, as two images mapped
            # from the start (the larger model's poses can hold their keypoint
            # tracks in a wrong basin), then adjusted.
            best = _map_two_again(best, inputs, image_dir, output_dir, options)
            best, kba = keypoint_bundle_adjustment(
                inputs.records,
                best,
                options.keypoint_ba_options,
                mirror=inputs.mirror,
                instant_of=inputs.instant_of,
            )
            models[best_key] = best
            people, tracks = kba.people, kba.tracks
    timings["checks"] = time.perf_counter() - lap
    lap = time.perf_counter()
    gravity = None
    if best is not None and options.gravity and inputs.priors is not None:
        kba_options = with_loss_scale(options.keypoint_ba_options, best)
        assert kba_options.loss_scale_px is not None
        gravity = refine_with_gravity_inplace(
            best,
            inputs,
            image_dir,
            people,
            tracks,
            options.gravity_options,
            loss_scale_px=kba_options.loss_scale_px,
            min_sigma_px=kba_options.min_sigma_px,
            robust_sigmas=kba_options.robust_sigmas,
        )
        left_out.update(gravity.cameras_left_out)
    elif options.gravity:
        logger.info("gravity: needs priors (the people's up): model unchanged")
    timings["gravity"] = time.perf_counter() - lap
    if best is not None and best.num_reg_images() < 2:
        _no_model_left(output_dir, best, left_out)
    lap = time.perf_counter()
    dropped = 0
    if best is not None:
        loss = with_loss_scale(options.keypoint_ba_options, best).loss_scale_px
        assert loss is not None
        dropped = drop_outlier_observations_inplace(best, loss)
        if dropped:
            logger.info(
                "outputs: %d observation(s) behind their camera or more than %.0f px "
                "from their point (the refinement's outliers) left the model",
                dropped,
                OUTLIER_LOSS_SCALES * loss,
            )
        left_out.update(leave_out_unobserved_inplace(best))
        if best.num_reg_images() < 2:
            _no_model_left(output_dir, best, left_out)
    scale, no_scale = _metric_scale(best, inputs, options)
    if best is not None and _people_only_pair(best, inputs, options):
        logger.warning(
            "two images placed by their people alone: expect a relative "
            "rotation several degrees off, and now and then far off "
            "(pose2sim, one instant, two cameras: median 5-8 deg, and 10 of "
            "58 models more than 30 deg off, 4 of them nearly reversed where "
            "a person's prior was turned front to back, which takes a third "
            'camera to detect; docs/results.md, "Real photos: fewer cameras, '
            'fewer instants"); more cameras or instants of static cameras '
            "pin it down"
        )
    if best is not None and inputs.static is not None:
        add_static_members_inplace(best, inputs.static, inputs.views)
    if best is not None and (
        options.keypoint_ba
        or dropped
        or left_out
        or inputs.static is not None
        or scale is not None
        or gravity is not None
    ):
        best.write(output_dir / str(best_key))
    if best is not None and scale is not None:
        write_metric_scale(output_dir / str(best_key), scale)
    if best is not None and gravity is not None:
        write_gravity(output_dir / str(best_key), gravity)
    timings["scale_write"] = time.perf_counter() - lap
    reasons = {**why_unregistered(inputs.views, inputs.geometries, best), **left_out}
    if inputs.static is not None:
        reasons.update(static_members_left_out(left_out, inputs.static))
    if best is None:
        why = "; ".join(f"{n}: {r}" for n, r in list(reasons.items())[:5])
        raise RuntimeError(
            f"the mapper found no model ({len(inputs.views.image_names)} images). {why}"
        )
    summary = MappingSummary(
        num_models=len(models),
        num_images=len(inputs.views.image_names),
        registered=sorted(im.name for im in best.images.values() if im.has_pose),
        unregistered=reasons,
        model_dir=output_dir / str(best_key),
        elapsed_s=time.perf_counter() - t0,
        metric_scale=scale,
        no_scale=no_scale,
        timings_s=timings,
        re_posed=re_posed,
    )
    return best, summary


def _map_two_again(
    rec: pycolmap.Reconstruction,
    inputs: MapInputs,
    image_dir: Path,
    output_dir: Path,
    options: MappingOptions,
) -> pycolmap.Reconstruction:
    """The two registered images of ``rec`` (what a check left of a larger model)
    mapped again on their own from their verified two-view geometry, as two
    images mapped from the start are; ``rec`` when they have none.

    Adjusted from the larger model's poses instead, pose2sim_single t070's
    cam01-cam03 (cam02 left: 93 deg from its meshes) ended 27 deg off under the
    surface weight every image has, held in a wrong basin by 17 keypoint tracks
    of two observations each; mapped on their own, 5.8 deg (docs/gba.md, "Not
    done"). The people's left/right exchanges the larger model's camera check
    made are not carried over: its tracks are rebuilt from the database, and two
    images cannot be checked."""
    names = sorted(im.name for im in rec.images.values() if im.has_pose)
    with tempfile.TemporaryDirectory(prefix=".two-", dir=output_dir) as work:
        fresh = strategies.two_view_initialised(
            inputs.database_path,
            inputs.views,
            inputs.geometries,
            image_dir,
            Path(work),
            options,
            inputs.priors,
            names,
        )
    if fresh is None or fresh.num_reg_images() != 2:
        logger.info(
            "the two images left (%s) have no verified geometry of their own: "
            "adjusted from the larger model's poses",
            ", ".join(names),
        )
        return rec
    logger.info("the two images left (%s): mapped again on their own", ", ".join(names))
    return fresh


def _names(names: Sequence[str], shown: int = 3) -> str:
    """The first ``shown`` names, and how many more."""
    more = len(names) - shown
    return ", ".join(names[:shown]) + (f" and {more} more" if more > 0 else "")


def _no_model_left(
    output_dir: Path, rec: pycolmap.Reconstruction, left_out: dict[str, str]
) -> NoReturn:
    """The checks left fewer than two images of the model: no model. The
    mappers' models leave ``output_dir`` (a failed run leaves only its marker;
    a model the checks contradicted is not one to pick up by mistake)."""
    for folder in sorted(output_dir.iterdir()):  # loop over the written models
        if folder.is_dir() and (folder / "images.bin").is_file():
            shutil.rmtree(folder)
    names = sorted(left_out)
    first = f" {names[0]}: {left_out[names[0]]}" if names else ""
    raise RuntimeError(
        f"no model left: the checks left out {len(names)} image(s) of the model "
        f"({', '.join(names)}) and {rec.num_reg_images()} remain(s); the "
        f"warnings above say why each left.{first}"
    )


def _check_against_meshes(
    rec: pycolmap.Reconstruction,
    inputs: MapInputs,
    options: MappingOptions,
    mirrored: tuple[str, ...],
    people: PeopleNoise | None,
) -> dict[str, str]:
    """Leave out the cameras that contradict the meshes, on the final poses (the
    refinement can carry a camera far from its start): their relative rotations
    (:func:`leave_out_prior_outliers_inplace`), then the up they give each person
    (:func:`leave_out_tilted_inplace`); re-adjust if any left.

    An image re-posed with left and right exchanged has a mesh turned front to
    back (and leaning the other way), and an image that classic keypoints place
    is not judged by its people: the meshes judge neither.
    """
    assert inputs.priors is not None
    pinned = {
        rec.image(i).name
        for i in classic_placed(
            rec,
            inputs.num_classic,
            options.keypoint_ba_options.min_classic_support,
        )
    }
    exempt = frozenset(mirrored) | frozenset(pinned)
    left_out = leave_out_prior_outliers_inplace(
        rec, inputs.priors, options.max_image_prior_deviation_deg, exempt=exempt
    )
    left_out |= leave_out_tilted_inplace(
        rec,
        inputs.priors,
        options.max_people_up_deg,
        options.people_up_ratio,
        exempt=exempt,
    )
    if left_out:
        scale_px = with_loss_scale(options.keypoint_ba_options, rec).loss_scale_px
        assert scale_px is not None
        bundle_adjust_inplace(rec, scale_px, people)
    return left_out


def people_scale(
    rec: pycolmap.Reconstruction, inputs: MapInputs, options: MappingOptions
) -> MetricScale | None:
    """The metric scale of ``rec`` from its people (not applied; None without
    priors or triangulated keypoints). Static cameras: the instant of each merged
    person goes with it (the people of different instants may be one person,
    whose size error repeats). Two images that only their people place: the
    relative pose's part joins the uncertainty."""
    if inputs.priors is None:
        return None
    instant_of = None
    if inputs.static is not None and inputs.image_priors is not None:
        _, groups = merge_priors(inputs.image_priors, inputs.static)
        instant_of = dict(groups)
    return estimate_metric_scale(
        inputs.records,
        rec,
        inputs.priors,
        instant_of=instant_of,
        relative_pose_sd_deg=(
            TWO_VIEW_POSE_SD_DEG if _people_only_pair(rec, inputs, options) else None
        ),
    )


def _people_only_pair(
    rec: pycolmap.Reconstruction, inputs: MapInputs, options: MappingOptions
) -> bool:
    """Two images, one instant, and classic matches do not place both: their
    relative pose is the people's alone (pose2sim: 5-8 deg median)."""
    return (
        rec.num_reg_images() == 2
        and inputs.static is None
        and len(
            classic_placed(
                rec,
                inputs.num_classic,
                options.keypoint_ba_options.min_classic_support,
            )
        )
        < 2
    )


def _metric_scale(
    rec: pycolmap.Reconstruction | None, inputs: MapInputs, options: MappingOptions
) -> tuple[MetricScale | None, str]:
    """Scale ``rec`` to metres from the people's size (in place) -> the estimate,
    or None and why not. Not where a registered image's focal length is a
    guess: a person's size against the cameras' distances follows it (the
    warning at the start says so)."""
    if rec is None or not options.metric_scale:
        return None, ""
    registered = {im.name for im in rec.images.values() if im.has_pose}
    guessed = sorted(registered & set(inputs.focal_guessed))
    if guessed:
        why = (
            f"{len(guessed)} registered image(s) without a known focal length "
            f"({_names(guessed)}): give the intrinsics for metres"
        )
        logger.info("metric scale: %s; scale arbitrary", why)
        return None, why
    scale = people_scale(rec, inputs, options)
    if scale is None:
        why = "no keypoint of a person with priors triangulated"
        logger.info("metric scale: %s; scale arbitrary", why)
        return None, why
    apply_metric_scale_inplace(rec, scale)
    logger.info(
        "metric scale: x%.4f to metres, +-%.1f%% (the people's size, %s; their "
        "%d views spread %.1f%%%s)",
        scale.scale,
        100 * scale.uncertainty,
        scale.basis(),
        scale.num_person_views,
        100 * scale.spread,
        f"; the two images' relative pose +-{100 * scale.relative_pose:.1f}%"
        if scale.relative_pose
        else "",
    )
    return scale, ""


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
