"""Options of `colmap-vc map` and their translation into pycolmap's pipelines.

The defaults suit virtual correspondences: VC pairs are wide-baseline by nature and
their pixels carry a few pixels of prior error, so the mapper's reprojection filters
are looser than COLMAP's, while the inlier counts stay COLMAP's.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field
from pathlib import Path

import pycolmap

from ..gravity import GravityOptions
from ..keypoint_ba import KeypointBaOptions
from ..metric_scale import MetricScale


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
    better); two images start from their verified two-view geometry instead.
    incremental (COLMAP's, also for two images) / global (GLOMAP) / mesh force
    one mapper."""
    max_prior_deviation_deg: float = 35.0
    """auto: largest median rotation difference to the mesh prior that is accepted."""
    max_image_prior_deviation_deg: float = 90.0
    """An image whose relative rotations to the other registered images differ from
    the meshes' by more than this (median over its pairs, each pair aligned by its
    own meshes) is left out: its evidence contradicts its own people. The meshes'
    relative rotations are off by up to 45 deg for the calibrated cameras of
    pose2sim_multi (17 deg median; an image's median over its pairs up to 42), so
    only a contradiction beyond any mesh error counts (0: no check). Judged
    through one reference image instead, a camera posed within 1.5 deg was left
    out of the 16-view speed dome, its alignment to the reference 110 deg off
    (docs/real-data.md, "Mesh check")."""
    max_people_up_deg: float = 30.0
    """An image whose pose tilts its people more than this from the up the other
    images give the same people, and more than ``people_up_ratio`` times the
    other images' median, is left out, while 4 or more images remain (0: no
    check). A person's up is the long axis of its 3D keypoints off the arms,
    turned into the world by the model; an image's tilt is the median over its
    people that two or more other images see. No vertical lines needed.
    30 deg: a camera tilted that far is wrong, not noisy (the benches call a
    camera wrong beyond a median pair error of 30 deg); below it the check does
    not judge (docs/real-data.md, "People's up check")."""
    people_up_ratio: float = 4.5
    """The scene's own noise, for the people's up check: the meshes' tilt errors
    depend on the pose estimator (a right camera's median deviation: 4-5 deg with
    the synthetic fitted priors, 9 with the realistic ones, 6.5 on pose2sim). Of
    503 right cameras in 53 scenes, the one above 30 deg was 3.5 times its
    scene's median; the four wrong cameras the check leaves out, 5.6-7.8 times
    (docs/real-data.md, "People's up check")."""
    refine_intrinsics: bool = False
    """Refine focal length and distortion (off: the intrinsics are known)."""
    num_threads: int = 1
    """Threads of COLMAP's mapper (-1: all cores). One: with several, the mapper is
    not deterministic (thread timing changes its floating-point sums, then which
    image comes next): one 128-image database gave all 128 cameras on one run and
    a camera left out on the next. One thread gave identical models, on 2 cores
    only 10% slower (that dome: 53 s against 59 s, docs/scaling.md)."""
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
    light_ba_from_images: int | None = 32
    """From this many images to map, COLMAP's bundle-adjustment schedule is
    lightened: one round of BA, observation filtering and retriangulation per local
    or global BA (COLMAP: up to 2 local, 5 global, repeated while more than 0.1% /
    0.05% of the observations change), and a global BA when the model grew by 1.3x
    (COLMAP: 1.1x). VC observations carry pixels of correlated prior error, so each
    round's filter moves observations across its threshold and the rounds run to
    the cap without moving the cameras: on the 64- and 128-image domes the light
    schedule gives the same AUC in a third of the mapper time. Below, COLMAP's
    schedule costs seconds and its extra rounds help the 11-12-image one-person
    domes (AUC@15 1.6-4 points lower with the light one). Measured in
    docs/scaling.md. None: COLMAP's schedule always."""
    bundle_adjustment: bool = True
    """Run COLMAP's local and global bundle adjustment (off: initialisation only, i.e.
    registration and triangulation with one global BA iteration, COLMAP's minimum)."""
    keypoint_ba: bool = True
    """Finish with the keypoint bundle adjustment (colmap_vc/keypoint_ba.py): the
    people's keypoints as multi-view tracks by identity, robust loss, the mapper's
    surface-VC points weighted to a fixed total per image. A database without
    keypoint VCs is left as mapped."""
    keypoint_ba_options: KeypointBaOptions = field(default_factory=KeypointBaOptions)
    """Options of that pass."""
    gravity: bool = True
    """After the refinement, measure each camera's up from the scene's vertical
    lines (door and window frames, pillars; colmap_vc/gravity.py: a static camera
    pools all its images) and bundle-adjust once more with every camera's up
    tied to one world up, weighed against the keypoints' noise: the turn of all
    cameras about the people that the keypoints barely see (docs/real-data.md,
    "Why people alone stop at 2-3 degrees"). pose2sim, AUC@15: static cameras
    82.6 -> 92.6 (one person) and 80.3 -> 84.0 (two), one instant at a time 59.9
    -> 77.6 and 65.0 -> 71.7. A camera without 20 agreeing vertical lines, or
    with two vanishing points, gets no up; with fewer than two, or without
    priors (the people's up picks the vertical; their boxes are masked), the
    model is left as it is. What was measured goes to gravity.json beside the
    model."""
    gravity_options: GravityOptions = field(default_factory=GravityOptions)
    """Options of the vertical vanishing point."""
    metric_scale: bool = True
    """Scale the model to metres from the people's keypoints (colmap_vc/
    metric_scale.py; the scale, its spread and its uncertainty go to
    metric_scale.json beside the model). Needs keypoint VCs and the priors;
    otherwise the model keeps COLMAP's arbitrary scale."""
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
    metric_scale: MetricScale | None = None  # None: the model's scale is arbitrary
    no_scale: str = ""  # why it is arbitrary ("": metric, or not asked for)
    timings_s: dict[str, float] = field(default_factory=dict)  # seconds per stage
    re_posed: dict[str, str] = field(default_factory=dict)  # name -> how the
    # camera check moved it

    @property
    def num_registered(self) -> int:
        """Images in the largest model."""
        return len(self.registered)


def incremental_options(
    options: MappingOptions, num_images: int = 0
) -> pycolmap.IncrementalPipelineOptions:
    """pycolmap incremental pipeline options from ours, for ``num_images`` to map."""
    light_ba = (
        options.light_ba_from_images is not None
        and num_images >= options.light_ba_from_images
    )
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
    if light_ba:
        pipeline.ba_local_max_refinements = 1
        pipeline.ba_global_max_refinements = 1
        pipeline.ba_global_frames_ratio = 1.3
        pipeline.ba_global_points_ratio = 1.3
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
