"""What `map` writes and reports: the models numbered as COLMAP numbers them, the
options beside the final one, the points as the refinement left them (none behind
its camera, no observation it weighed as an outlier, true errors), a reason for
every image left out, and the images of static cameras given their
representative's pose."""

from __future__ import annotations

import dataclasses
import json
import logging
from collections.abc import Mapping
from pathlib import Path

import pycolmap

from .. import __version__, database, outputs
from ..static_cameras import StaticCameras
from .options import MappingOptions, MappingSummary

logger = logging.getLogger(__name__)

OUTPUT_MARKER = outputs.marker_name("map")
"""File `map` writes into its output folder: `--overwrite` removes only such folders."""


OPTIONS_FILE = "map_options.json"
"""Beside the final model: the options and inputs `map` ran with."""

OUTLIER_LOSS_SCALES = 10.0
"""An observation farther than this many of the refinement's Cauchy scales from its
point's projection weighed less than 1 % of an inlier there (1 / (1 + 10^2)):
the refinement treated it as an outlier, and the written model leaves it out."""


def drop_outlier_observations_inplace(
    rec: pycolmap.Reconstruction, loss_scale_px: float
) -> int:
    """Leave out of ``rec`` the observations behind their camera and those more
    than :data:`OUTLIER_LOSS_SCALES` times ``loss_scale_px`` (the refinement's
    Cauchy scale) from their point's projection, with the points left with one
    view (COLMAP's filters), and store the points' errors as they are now.
    Returns how many observations were removed.

    The mapper filters its points at its own threshold, but the refinement and the
    checks after it move the cameras under a robust loss, and the people's points
    are never re-filtered: on pose2sim_multi's static cameras, keypoint
    observations of another person 400-1070 px from their point, on the 16-view
    speed dome two-view surface points behind a camera, whose error (6.7e153 px)
    made the model's mean reprojection error, as COLMAP's tools report it,
    1.7e151 px.
    """
    manager = pycolmap.ObservationManager(rec)
    behind = manager.filter_observations_with_negative_depth()
    far = manager.filter_points3D_with_large_reprojection_error(
        OUTLIER_LOSS_SCALES * loss_scale_px, set(rec.point3D_ids())
    )
    rec.update_point_3d_errors()
    return behind + far


def leave_out_unobserved_inplace(rec: pycolmap.Reconstruction) -> dict[str, str]:
    """Deregister the images of ``rec`` that hold no observation of a model point
    (after :func:`drop_outlier_observations_inplace`), each with its reason in the
    log -> name: reason.

    Nothing in the model places such an image any more: its pose is whatever the
    refinement left, and a wrong camera is worse than none. COLMAP's own frame
    filter deregisters a frame without points for the same reason. Before the
    refinement reflected models that had crossed behind their cameras
    (:func:`colmap_vc.gba.ceres.restore_cheirality_inplace`), pose2sim_single t050
    (seed 1) ended with three such cameras, 177-179 deg off, and no point.
    """
    left: dict[str, str] = {}
    for image_id in sorted(rec.reg_image_ids()):  # loop over the images
        image = rec.image(image_id)
        if image.num_points3D == 0:
            left[image.name] = (
                "left out: none of its observations is left in the model (behind "
                "the camera, or outliers of the refinement): nothing places it"
            )
            logger.warning("%s %s", image.name, left[image.name])
            rec.deregister_frame(image.frame_id)
    return left


def number_models(output_dir: Path, best: Path | None) -> Path:
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


def write_run_options(
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
        "re_posed": summary.re_posed,
        "unregistered": summary.unregistered,
    }
    (model_dir / OPTIONS_FILE).write_text(json.dumps(record, indent=1) + "\n")


def why_unregistered(
    views: database.DatabaseViews,
    geometries: Mapping[database.Pair, database.TwoViewGeometryRow],
    best: pycolmap.Reconstruction | None,
) -> dict[str, str]:
    """A reason per image of the database (``views``, with its ``geometries``)
    missing from the model."""
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
        elif not reg_ids:  # no model at all: nothing to be separate from
            reasons[name] = (
                f"{len(pairs)} verified pair(s), but no model could be started "
                "from them (no pair with the inliers and the triangulation angle "
                "an initial pair needs)"
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


def static_members_left_out(
    left_out: dict[str, str], static: StaticCameras
) -> dict[str, str]:
    """Why each image of a left-out static camera is missing: the reason its
    representative (the view that stands for every instant) was left out."""
    out = {}
    for rep, why in sorted(left_out.items()):
        if rep not in static.camera_of:
            continue  # an image of its own
        for name in static.members(rep):
            if name != rep:
                out[name] = f"as {rep} (the same static camera): {why}"
    return out


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
