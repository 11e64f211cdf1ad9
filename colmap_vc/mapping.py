"""`colmap-vc map`: pycolmap mapping of an (augmented) database, with progress and a
summary that says which images were registered and why the others were not.

The defaults suit virtual correspondences: VC pairs are wide-baseline by nature and
their pixels carry a few pixels of prior error, so the mapper's reprojection filters
are looser than COLMAP's, while the inlier counts stay COLMAP's.
"""

from __future__ import annotations

import dataclasses
import enum
import logging
import shutil
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap

from . import canonical, database, outputs
from .estimators.body import anny_keypoint_mirror
from .evaluation import relative_pose, rotation_angle_deg
from .keypoint_ba import KeypointBaOptions, keypoint_bundle_adjustment
from .keypoint_tracks import bundle_adjust_inplace, person_identities
from .meshalign import mesh_alignment_poses
from .priors import read_priors
from .static_cameras import StaticCameras, merge_priors, parse_static_cameras
from .structs import ScenePriors

logger = logging.getLogger(__name__)


class Mapper(enum.StrEnum):
    """Which pycolmap mapper."""

    AUTO = (
        "auto"  # incremental, checked against the mesh prior, mesh-initialised if not
    )
    INCREMENTAL = "incremental"
    GLOBAL = "global"
    MESH = "mesh"  # cameras from mesh alignment, then triangulation + bundle adjustment


@dataclass(frozen=True, kw_only=True, slots=True)
class MappingOptions:
    """Options of the mapper (the ones that matter for VC pairs)."""

    mapper: Mapper = Mapper.AUTO
    """auto: pycolmap's incremental mapper, whose result is checked against the coarse
    camera poses the predicted meshes give (mesh alignment); when it contradicts them
    (a mirrored two-view start, typical with one person) or registers fewer images
    than the meshes can place, the mesh-initialised mapper replaces it (if it does
    better). incremental / global (GLOMAP) / mesh force one mapper."""
    max_prior_deviation_deg: float = 35.0
    """auto: largest median rotation difference to the mesh prior that is accepted."""
    max_image_prior_deviation_deg: float = 90.0
    """An image whose relative rotations to the other registered images differ from
    the meshes' by more than this (median over its pairs) is left out: its evidence
    contradicts its own people. The meshes' relative rotations are off by up to 77
    deg for correctly posed cameras on pose2sim_multi (10-25 deg median), so only a
    contradiction beyond any mesh error counts (0: no check)."""
    refine_intrinsics: bool = False
    """Refine focal length and distortion (off: the intrinsics are known)."""
    num_threads: int = -1
    """Threads (-1: all cores)."""
    static_cameras: str | None = None
    """Images from static cameras (the regular expression of `augment
    --static-cameras`; default: what augment recorded): one pose per physical
    camera, given to every image of that camera."""
    seed: int = 0
    """Seed of COLMAP's randomness (pycolmap.set_random_seed)."""
    min_num_matches: int = 15
    """Minimum verified matches for a pair to enter the scene graph."""
    init_min_num_inliers: int = 50
    """Minimum inliers of the initial pair (COLMAP: 100)."""
    init_min_tri_angle_deg: float = 4.0
    """Minimum triangulation angle of the initial pair, degrees (COLMAP: 16)."""
    abs_pose_min_num_inliers: int = 30
    """Minimum 2D-3D inliers to register an image."""
    abs_pose_max_error_px: float = 12.0
    """RANSAC threshold of image registration, pixels."""
    filter_max_reproj_error_px: float = 8.0
    """Observations reprojecting worse are filtered, pixels (COLMAP: 4)."""
    multiple_models: bool = True
    """Allow several models (the largest one is returned)."""
    min_model_size: int = 2
    """Smallest model kept, in images (COLMAP: 10, which silently drops a two-view or
    small extreme-view model)."""
    bundle_adjustment: bool = True
    """Run COLMAP's local and global bundle adjustment (off: initialisation only, i.e.
    registration and triangulation with one global BA iteration, COLMAP's minimum)."""
    keypoint_ba: bool = True
    """Finish with the keypoint bundle adjustment (colmap_vc/keypoint_ba.py): the
    people's keypoints as multi-view tracks by identity, robust loss, a budget of
    surface-VC points. A database without keypoint VCs is left as mapped."""
    keypoint_ba_options: KeypointBaOptions = field(default_factory=KeypointBaOptions)
    """Options of that pass."""
    show_progress: bool = True
    """Log each registered image."""


@dataclass(frozen=True, kw_only=True, slots=True)
class MappingSummary:
    """What the mapper produced."""

    num_models: int
    num_images: int
    registered: list[str]
    unregistered: dict[str, str]  # image name -> why
    model_dir: Path | None
    elapsed_s: float

    @property
    def num_registered(self) -> int:
        """Images in the largest model."""
        return len(self.registered)


MIN_MESH_INIT_POINTS = 20  # fewer triangulated points: too few for a stable BA

# COLMAP's own defaults, for the classic baseline.
COLMAP_DEFAULTS = MappingOptions(
    mapper=Mapper.INCREMENTAL,
    min_model_size=10,
    init_min_num_inliers=100,
    init_min_tri_angle_deg=16.0,
    filter_max_reproj_error_px=4.0,
)


def incremental_options(options: MappingOptions) -> pycolmap.IncrementalPipelineOptions:
    """pycolmap incremental pipeline options from ours."""
    pipeline = pycolmap.IncrementalPipelineOptions(
        num_threads=options.num_threads,
        min_num_matches=options.min_num_matches,
        multiple_models=options.multiple_models,
        ba_refine_focal_length=options.refine_intrinsics,
        ba_refine_principal_point=False,
        ba_refine_extra_params=options.refine_intrinsics,
        random_seed=options.seed,
        min_model_size=options.min_model_size,
    )
    m = pipeline.mapper
    m.init_min_num_inliers = options.init_min_num_inliers
    m.init_min_tri_angle = options.init_min_tri_angle_deg
    m.abs_pose_min_num_inliers = options.abs_pose_min_num_inliers
    m.abs_pose_max_error = options.abs_pose_max_error_px
    m.filter_max_reproj_error = options.filter_max_reproj_error_px
    pipeline.triangulation.complete_max_reproj_error = (
        options.filter_max_reproj_error_px
    )
    pipeline.triangulation.merge_max_reproj_error = options.filter_max_reproj_error_px
    if not options.bundle_adjustment:
        # Initialisation only: no local BA; COLMAP insists on >= 1 global iteration.
        pipeline.ba_local_max_num_iterations = 0
        pipeline.ba_global_max_num_iterations = 1
        pipeline.ba_local_max_refinements = 1
        pipeline.ba_global_max_refinements = 1
    return pipeline


def global_options(options: MappingOptions) -> pycolmap.GlobalPipelineOptions:
    """pycolmap global pipeline options from ours."""
    pipeline = pycolmap.GlobalPipelineOptions(
        num_threads=options.num_threads,
        min_num_matches=options.min_num_matches,
        multiple_models=options.multiple_models,
        random_seed=options.seed,
    )
    return pipeline


def mesh_initialised(
    database_path: Path,
    image_dir: Path,
    output_dir: Path,
    priors: ScenePriors,
    options: MappingOptions,
    num_rounds: int = 3,
) -> pycolmap.Reconstruction | None:
    """Cameras from mesh alignment, then COLMAP triangulation + BA, a few rounds.

    Robust where two-view geometry from one person is not: mesh alignment is off by
    10-20 degrees but never flipped, and bundle adjustment over all views then pulls
    the cameras to what the VC tracks say.
    """
    views = database.read_views(database_path)
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
    pipeline = incremental_options(options)
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
    image_dir: Path,
    output_dir: Path,
    options: MappingOptions,
    priors: ScenePriors | None = None,
) -> pycolmap.Reconstruction | None:
    """A two-image model from the pair's verified two-view geometry, triangulated.

    COLMAP's incremental mapper discards a model made of its initial pair only, so a
    two-image scene (the paper's two-frame task) is built here: camera 1 at the
    origin, camera 2 at the verified relative pose (unit baseline), the VC and
    classic inlier tracks triangulated. No Ceres BA (it cannot fix a two-camera
    gauge); the generalized BA refines it with an explicit gauge.
    """
    views = database.read_views(database_path)
    geometries = database.read_two_view_geometries(database_path, include_vc=True)
    posed = {p: row for p, row in geometries.items() if row.cam2_from_cam1 is not None}
    if not posed:
        return None
    (id1, id2), row = max(posed.items(), key=lambda kv: len(kv[1].inlier_matches))
    rel = row.cam2_from_cam1
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
                t = mesh_rel[:, 3] / max(np.linalg.norm(mesh_rel[:, 3]), 1e-12)
                rel = np.c_[mesh_rel[:, :3], t]
    kp1 = database.read_keypoints(database_path, int(id1), include_vc=True)
    kp2 = database.read_keypoints(database_path, int(id2), include_vc=True)
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
    cam1 = views.cameras[int(views.camera_ids[views.image_ids == id1][0])]
    cam2 = views.cameras[int(views.camera_ids[views.image_ids == id2][0])]
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


def prior_deviation_deg(rec: pycolmap.Reconstruction, priors: ScenePriors) -> float:
    """Median rotation difference (deg) of a model's and the meshes' relative poses."""
    names = {im.name for im in rec.images.values() if im.has_pose}
    mesh = mesh_alignment_poses(priors, image_names=names)
    model = {
        im.name: im.cam_from_world().matrix()
        for im in rec.images.values()
        if im.has_pose
    }
    common = sorted(set(mesh) & set(model))
    diffs = [
        rotation_angle_deg(
            relative_pose(model[a], model[b])[:, :3]
            @ relative_pose(mesh[a], mesh[b])[:, :3].T
        )
        for i, a in enumerate(common)
        for b in common[i + 1 :]
    ]
    return float(np.median(diffs)) if diffs else 0.0


def _keypoint_mirror(
    database_path: Path, priors: ScenePriors | None
) -> dict[int, int] | None:
    """Template track id -> its left/right counterpart's, for the camera check."""
    if priors is None:
        return None
    persons = [p for ip in priors.images.values() for p in ip.persons]
    perm = anny_keypoint_mirror(persons)
    if perm is None:
        return None
    run = database.read_run_info(database_path).get("options", {})
    offset = int(run.get("matching", {}).get("num_samples", 0))
    if offset <= 0:
        return None
    return {offset + k: offset + int(j) for k, j in enumerate(perm.tolist())}


def leave_out_prior_outliers_inplace(
    rec: pycolmap.Reconstruction,
    priors: ScenePriors,
    max_deviation_deg: float,
    *,
    exempt: frozenset[str] = frozenset(),
) -> dict[str, str]:
    """Deregister images whose pose contradicts the meshes (image name -> why).

    Per registered image: the median over its pairs (with the other registered
    images the meshes can place) of the rotation difference between the model's
    and the meshes' relative poses. The worst image above ``max_deviation_deg`` is
    left out, then the next, while 3 or more remain (with 2 the images cannot tell
    which of the two is wrong). A wrong camera is worse than none.
    """
    if max_deviation_deg <= 0:
        return {}
    model = {
        im.name: (i, im.cam_from_world().matrix())
        for i, im in rec.images.items()
        if im.has_pose
    }
    mesh = mesh_alignment_poses(priors, image_names=set(model) - exempt)
    placed = sorted(set(mesh) & set(model))
    left: dict[str, str] = {}
    while len(placed) >= 3:
        medians = {
            a: float(
                np.median(
                    [
                        rotation_angle_deg(
                            relative_pose(model[a][1], model[b][1])[:, :3]
                            @ relative_pose(mesh[a], mesh[b])[:, :3].T
                        )
                        for b in placed
                        if b != a
                    ]
                )
            )
            for a in placed
        }
        logger.debug("deviation from the meshes: %s", medians)
        worst = max(placed, key=lambda a: (medians[a], a))
        if medians[worst] <= max_deviation_deg:
            break
        left[worst] = (
            f"left out: its pose contradicts the body meshes (relative rotations "
            f"{medians[worst]:.0f} deg from theirs, median over {len(placed) - 1} "
            f"images; more than any mesh error, {max_deviation_deg:g} deg)"
        )
        logger.warning("%s %s", worst, left[worst])
        rec.deregister_frame(rec.image(model[worst][0]).frame_id)
        placed.remove(worst)
    return left


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
    """Map a database; the models go to ``output_dir/<k>``, the largest is returned.

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
    priors = _load_priors(database_path, priors_path, views.image_names, static)
    if len(mapped) == 2 and options.mapper in (Mapper.AUTO, Mapper.INCREMENTAL):
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

        pipeline = incremental_options(options)
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
    left_out: dict[str, str] = {}
    mirrored: tuple[str, ...] = ()
    if best is not None and options.keypoint_ba:
        best, kba = keypoint_bundle_adjustment(
            database_path,
            best,
            options.keypoint_ba_options,
            mirror=_keypoint_mirror(database_path, priors),
        )
        models[best_key] = best
        left_out.update(kba.left_out or {})
        mirrored = kba.mirrored
    if best is not None and priors is not None:
        # On the final poses: the keypoint BA can carry a camera far from its start.
        # An image re-posed with left and right exchanged has a mesh turned front
        # to back: the meshes cannot judge it.
        left_out.update(
            leave_out_prior_outliers_inplace(
                best,
                priors,
                options.max_image_prior_deviation_deg,
                exempt=frozenset(mirrored),
            )
        )
        if left_out:
            bundle_adjust_inplace(best, options.keypoint_ba_options.loss_scale_px)
    if best is not None and static is not None:
        add_static_members_inplace(best, static, views)
    if best is not None and (options.keypoint_ba or left_out or static is not None):
        best.write(output_dir / str(best_key))
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
    )
    return best, summary


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


def _load_priors(
    database_path: Path,
    priors_path: Path | None,
    image_names: tuple[str, ...],
    static: StaticCameras | None = None,
) -> ScenePriors | None:
    """The priors given, else those `augment` recorded in the database, else None."""
    if priors_path is None:
        recorded = database.read_run_info(database_path).get("priors")
        if not recorded:
            return None
        try:
            if not Path(recorded).exists():
                return None
            priors = read_priors(Path(recorded), known_image_names=image_names)
        except OSError as error:
            raise OSError(
                f"the priors augment used, {recorded} (recorded in the database), "
                f"cannot be read ({error.strerror or error}): give --priors"
            ) from error
    else:
        priors = read_priors(priors_path, known_image_names=image_names)
    if static is not None:  # the views augment wrote: one per static camera
        priors, _ = merge_priors(priors, static)
    return with_associated_ids(priors, database_path)


def with_associated_ids(priors: ScenePriors, database_path: Path) -> ScenePriors:
    """Anonymous people get the identity `augment`'s association gave them.

    Mesh alignment (the auto mapper's check and the mesh-initialised mapper) pairs
    people by identity; with anonymous multi-person priors it could pair nobody.
    People the association left out stay anonymous.
    """
    associations = database.read_person_associations(database_path)
    if not associations:
        return priors
    identity = person_identities(associations)
    views = database.read_views(database_path)
    id_of = dict(zip(views.image_names, views.image_ids.tolist(), strict=True))
    offset = 1 + max(
        (
            p.person_id
            for ip in priors.images.values()
            for p in ip.persons
            if p.person_id is not None
        ),
        default=-1,
    )
    images = {}
    for name, ip in priors.images.items():
        persons = tuple(
            p
            if p.person_id is not None or (id_of.get(name), k) not in identity
            else dataclasses.replace(p, person_id=offset + identity[(id_of[name], k)])
            for k, p in enumerate(ip.persons)
        )
        images[name] = dataclasses.replace(ip, persons=persons)
    return dataclasses.replace(priors, images=images)


def run_incremental(
    database_path: Path,
    image_dir: Path,
    output_dir: Path,
    options: MappingOptions | None = None,
    num_images: int | None = None,
) -> tuple[pycolmap.Reconstruction | None, MappingSummary | None]:
    """Like :func:`run` but returns (None, None) instead of raising when no model.

    Used by baselines, where a failure is a result to report.
    """
    try:
        return run(database_path, image_dir, output_dir, options, overwrite=True)
    except RuntimeError as exc:
        logger.info("%s", exc)
        return None, None
