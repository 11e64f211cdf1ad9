"""The mapping strategies, one function each: pycolmap's incremental and global
mappers, and mapping started from the people's meshes (all views at once, or two
views from their verified geometry).

The meshes' starts exist where COLMAP's incremental start from two-view geometry
is fragile: one person's two-view geometry can be mirrored, and two images give
the incremental mapper nothing to check against. Which strategy runs is decided in
one place, :mod:`colmap_vc.mapping.choice`.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import pycolmap

from .. import database
from ..colmap_log import colmap_quiet
from ..evaluation import relative_pose, rotation_angle_deg
from ..gba.ceres import bundle_adjust_inplace
from ..meshalign import mesh_alignment_poses
from ..structs import FloatArray, ScenePriors
from .options import Mapper, MappingOptions, global_options, incremental_options

logger = logging.getLogger(__name__)

MIN_MESH_INIT_POINTS = 20  # fewer triangulated points: too few for a stable BA


def incremental(
    database_path: Path,
    image_dir: Path,
    output_dir: Path,
    options: MappingOptions,
    image_names: Sequence[str],
    *,
    only_these: bool = False,
) -> dict[int, pycolmap.Reconstruction]:
    """pycolmap's incremental mapper -> its models by folder number.

    ``only_these``: map only ``image_names`` (one view per static camera).
    """
    registered = [0]

    def on_init() -> None:
        logger.info("initial pair chosen")

    def on_next() -> None:
        registered[0] += 1
        if options.show_progress:
            logger.info("registered image %d/%d", registered[0] + 2, len(image_names))

    pipeline = incremental_options(options, len(image_names))
    if only_these:
        pipeline.image_names = list(image_names)
    with colmap_quiet(logger):
        return pycolmap.incremental_mapping(
            database_path,
            image_dir,
            output_dir,
            options=pipeline,
            initial_image_pair_callback=on_init,
            next_image_callback=on_next,
        )


def global_(
    database_path: Path, image_dir: Path, output_dir: Path, options: MappingOptions
) -> dict[int, pycolmap.Reconstruction]:
    """pycolmap's global mapper (GLOMAP) -> its models by folder number."""
    with colmap_quiet(logger):
        return pycolmap.global_mapping(
            database_path, image_dir, output_dir, options=global_options(options)
        )


def mesh_initialised(
    database_path: Path,
    views: database.DatabaseViews,
    image_dir: Path,
    output_dir: Path,
    priors: ScenePriors,
    options: MappingOptions,
    num_rounds: int = 3,
) -> pycolmap.Reconstruction | None:
    """Cameras from mesh alignment, then COLMAP triangulation + BA, a few rounds.

    Robust where two-view geometry from one person is not: mesh alignment is off by
    10-20 degrees but never flipped, and bundle adjustment over all views then pulls
    the cameras to what the VC tracks say. ``views``: the database's images.
    """
    poses = mesh_alignment_poses(priors, image_names=set(views.image_names))
    if len(poses) < 2:
        return None
    rec = pycolmap.Reconstruction()
    for camera in views.cameras.values():
        rec.add_camera_with_trivial_rig(camera)
    for image_id, name, camera_id in zip(
        views.image_ids, views.image_names, views.camera_ids, strict=True
    ):
        if name in poses:
            T = poses[name]
            rec.add_image_with_trivial_frame(
                pycolmap.Image(
                    name=name, camera_id=int(camera_id), image_id=int(image_id)
                ),
                pycolmap.Rigid3d(pycolmap.Rotation3d(T[:, :3]), T[:, 3]),
            )
    pipeline = incremental_options(options, len(poses))
    # The initial poses are coarse: triangulate generously, let BA tighten.
    pipeline.triangulation.complete_max_reproj_error = (
        4 * options.filter_max_reproj_error_px
    )
    pipeline.triangulation.merge_max_reproj_error = (
        4 * options.filter_max_reproj_error_px
    )
    pipeline.triangulation.create_max_angle_error = 10.0
    output_dir.mkdir(parents=True, exist_ok=True)
    for _ in range(num_rounds):
        rec = pycolmap.triangulate_points(
            rec,
            database_path,
            image_dir,
            output_dir,
            clear_points=True,
            options=pipeline,
        )
        if rec.num_points3D() < MIN_MESH_INIT_POINTS:
            break
        bundle_adjust_inplace(rec, options.filter_max_reproj_error_px / 2)
    if rec.num_points3D() < MIN_MESH_INIT_POINTS:
        if not options.keypoint_ba:
            return None
        # Too few verified matches to triangulate (one person, failed RANSAC): the
        # keypoint BA needs none, its tracks come from identities.
        logger.info(
            "mesh-initialised mapping: %d points triangulated; keeping the "
            "mesh-alignment cameras for the keypoint bundle adjustment",
            rec.num_points3D(),
        )
        for point_id in list(rec.point3D_ids()):
            rec.delete_point3D(point_id)
        for image in rec.images.values():  # back to the meshes' cameras
            T = poses[image.name]
            rec.frame(image.frame_id).rig_from_world = pycolmap.Rigid3d(
                pycolmap.Rotation3d(T[:, :3]), T[:, 3]
            )
    rec.write(output_dir)
    return rec


def two_view_initialised(
    database_path: Path,
    views: database.DatabaseViews,
    geometries: Mapping[database.Pair, database.TwoViewGeometryRow],
    image_dir: Path,
    output_dir: Path,
    options: MappingOptions,
    priors: ScenePriors | None = None,
    image_names: Sequence[str] | None = None,
) -> pycolmap.Reconstruction | None:
    """A two-image model from the pair's verified two-view geometry, triangulated.

    ``image_names``: the two images to map, when the database holds more (static
    cameras: one view per camera; the other instants' images of the same camera
    share its background, and their SIFT pair would win on inliers with no
    baseline at all).

    COLMAP's incremental mapper discards a model made of its initial pair only, so a
    two-image scene (the paper's two-frame task) is built here: camera 1 at the
    origin, camera 2 at the verified relative pose (unit baseline), the VC and
    classic inlier tracks triangulated. No Ceres BA (it cannot fix a two-camera
    gauge); the generalized BA refines it with an explicit gauge. ``views`` and
    ``geometries``: the database's images and two-view geometries; the chosen
    pair's keypoints are read here.
    """
    wanted = set(
        views.image_ids.tolist()
        if image_names is None
        else views.image_ids[np.isin(views.image_names, list(image_names))].tolist()
    )
    usable = {
        p: row
        for p, row in geometries.items()
        if len(row.inlier_matches) >= 5 and {int(p[0]), int(p[1])} <= wanted
    }
    if not usable:
        return None
    (id1, id2), row = max(usable.items(), key=lambda kv: len(kv[1].inlier_matches))
    kp1 = database.read_keypoints(database_path, int(id1), include_vc=True)
    kp2 = database.read_keypoints(database_path, int(id2), include_vc=True)
    cam1 = views.cameras[int(views.camera_ids[views.image_ids == id1][0])]
    cam2 = views.cameras[int(views.camera_ids[views.image_ids == id2][0])]
    rel = row.cam2_from_cam1
    if rel is None:  # COLMAP's matchers store E or F without the relative pose
        rel = _pose_from_geometry(row, cam1, cam2, kp1, kp2)
        if rel is None:
            return None
    if priors is not None and options.mapper is Mapper.AUTO:
        names = {
            int(i): n for i, n in zip(views.image_ids, views.image_names, strict=True)
        }
        mesh = mesh_alignment_poses(priors, image_names={names[id1], names[id2]})
        if len(mesh) == 2:
            mesh_rel = relative_pose(mesh[names[id1]], mesh[names[id2]])
            deviation = rotation_angle_deg(rel[:, :3] @ mesh_rel[:, :3].T)
            if deviation > options.max_prior_deviation_deg:
                logger.info(
                    "the two-view geometry contradicts the mesh prior (%.0f deg): "
                    "starting from the meshes' relative pose",
                    deviation,
                )
                t = mesh_rel[:, 3] / max(float(np.linalg.norm(mesh_rel[:, 3])), 1e-12)
                rel = np.c_[mesh_rel[:, :3], t]
    rec = pycolmap.Reconstruction()
    for camera in views.cameras.values():
        rec.add_camera_with_trivial_rig(camera)
    for image_id, pose, kp in (
        (id1, np.c_[np.eye(3), np.zeros(3)], kp1),
        (id2, rel, kp2),
    ):
        i = int(np.flatnonzero(views.image_ids == image_id)[0])
        rec.add_image_with_trivial_frame(
            pycolmap.Image(
                name=views.image_names[i],
                keypoints=kp,
                camera_id=int(views.camera_ids[i]),
                image_id=int(image_id),
            ),
            pycolmap.Rigid3d(pycolmap.Rotation3d(pose[:, :3]), pose[:, 3]),
        )
    # Midpoint triangulation of the inlier matches (vectorized), cheirality-checked.
    m = row.inlier_matches
    d1 = np.c_[cam1.cam_from_img(kp1[m[:, 0]]), np.ones(len(m))]
    d2 = (
        np.c_[cam2.cam_from_img(kp2[m[:, 1]]), np.ones(len(m))] @ rel[:, :3]
    )  # in cam 1
    c2 = -rel[:, :3].T @ rel[:, 3]
    # Closest points of the rays o1 + s d1 and c2 + u d2.
    a, b, c = (d1 * d1).sum(1), (d1 * d2).sum(1), (d2 * d2).sum(1)
    w = -c2
    d, e = (d1 * w).sum(1), (d2 * w).sum(1)
    den = np.maximum(a * c - b * b, 1e-12)
    s_ = (b * e - c * d) / den
    u_ = (a * e - b * d) / den
    xyz = 0.5 * (s_[:, None] * d1 + (c2 + u_[:, None] * d2))
    ok = (s_ > 0) & (u_ > 0)
    for (i1, i2), x in zip(m[ok], xyz[ok], strict=True):  # one pycolmap call per point
        track = pycolmap.Track()
        track.add_element(int(id1), int(i1))
        track.add_element(int(id2), int(i2))
        rec.add_point3D(x, track)
    if rec.num_points3D() == 0:
        return None
    output_dir.mkdir(parents=True, exist_ok=True)
    rec.write(output_dir)
    return rec


def _pose_from_geometry(
    row: database.TwoViewGeometryRow,
    cam1: pycolmap.Camera,
    cam2: pycolmap.Camera,
    kp1: FloatArray,
    kp2: FloatArray,
) -> FloatArray | None:
    """cam2_from_cam1 (3, 4) of a stored geometry without a pose (E, F or H and
    its inliers, as COLMAP's matchers write them), by COLMAP's own decomposition
    with the cheirality check; None when it finds none."""
    geometry = pycolmap.TwoViewGeometry()
    geometry.config = pycolmap.TwoViewGeometryConfiguration(int(row.config))
    for name in ("E", "F", "H"):
        value = getattr(row, name)
        if value is not None:
            setattr(geometry, name, value)
    geometry.inlier_matches = row.inlier_matches.astype(np.uint32)
    if not pycolmap.estimate_two_view_geometry_pose(cam1, kp1, cam2, kp2, geometry):
        return None
    pose = geometry.cam2_from_cam1
    return None if pose is None else pose.matrix()
