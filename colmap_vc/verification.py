"""Geometric verification of virtual correspondences (pycolmap's 5-point RANSAC).

VCs satisfy the epipolar constraint like any match, so the pair's essential matrix is
estimated with COLMAP's own calibrated two-view estimator, jointly over the VCs and
the pair's classic matches when there are any.
"""

from __future__ import annotations

import itertools
import logging
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import pycolmap

from .evaluation import pose_disagreement_deg, rotation_angle_deg
from .structs import BoolArray, FloatArray, PairGeometry, _check_shape

logger = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True, slots=True)
class VerificationOptions:
    """Options of the two-view verification."""

    max_error_px: float = 4.0
    """RANSAC inlier threshold (COLMAP's epipolar error), pixels, for images whose
    larger side is ``reference_image_size_px``; larger images scale it up (never
    down), as the priors' pixel errors grow with resolution (MediaPipe's landmarks are
    off by about 12 px median on 1920-px photos: 4 px there verifies almost nothing)."""
    reference_image_size_px: int = 640
    """Image side at which ``max_error_px`` applies (0: no scaling)."""
    min_num_inliers: int = 15
    """Fewer inliers: the pair gets no two-view geometry."""
    confidence: float = 0.999
    """RANSAC confidence."""
    max_num_trials: int = 10000
    """RANSAC iterations at most."""
    seed: int = 0
    """RANSAC seed (deterministic results)."""


@dataclass(frozen=True, kw_only=True, slots=True)
class Verification:
    """Result of verifying one pair."""

    geometry: PairGeometry | None  # None: not verified
    vc_is_inlier: BoolArray  # (M,)
    classic_is_inlier: BoolArray  # (C,)

    @property
    def num_inliers(self) -> int:
        """VC and classic inliers."""
        return int(self.vc_is_inlier.sum() + self.classic_is_inlier.sum())


def max_error_px(options: VerificationOptions, *cameras: pycolmap.Camera) -> float:
    """The RANSAC threshold for these cameras' images (``max_error_px``, scaled)."""
    if options.reference_image_size_px <= 0 or not cameras:
        return options.max_error_px
    side = max(max(c.width, c.height) for c in cameras)
    return options.max_error_px * max(1.0, side / options.reference_image_size_px)


def two_view_options(
    options: VerificationOptions, *cameras: pycolmap.Camera
) -> pycolmap.TwoViewGeometryOptions:
    """pycolmap options from ours (threshold scaled to the cameras' image size)."""
    opts = pycolmap.TwoViewGeometryOptions(
        min_num_inliers=options.min_num_inliers, compute_relative_pose=True
    )
    opts.ransac.max_error = max_error_px(options, *cameras)
    opts.ransac.confidence = options.confidence
    opts.ransac.max_num_trials = options.max_num_trials
    opts.ransac.random_seed = options.seed
    # VCs concentrate on a person: never call that a watermark.
    opts.detect_watermark = False
    # The intrinsics are known: COLMAP's "F explains more points than E, so the
    # cameras must be uncalibrated" test only rejects pairs whose VCs carry the
    # priors' (large, person-correlated) errors. E with enough inliers is kept.
    opts.min_E_F_inlier_ratio = 0.0
    return opts


def verify_pair(
    camera1: pycolmap.Camera,
    camera2: pycolmap.Camera,
    vc_xy1: FloatArray,
    vc_xy2: FloatArray,
    classic_xy1: FloatArray | None = None,
    classic_xy2: FloatArray | None = None,
    options: VerificationOptions | None = None,
) -> Verification:
    """Estimate the pair's geometry from VCs (+ classic matches) and split inliers.

    Args:
        camera1, camera2: the two cameras (known intrinsics).
        vc_xy1, vc_xy2: (M, 2) VC pixels.
        classic_xy1, classic_xy2: (C, 2) pixels of the pair's classic matches.
        options: verification options.
    """
    options = options or VerificationOptions()
    _check_shape("vc_xy1", vc_xy1, (None, 2))
    _check_shape("vc_xy2", vc_xy2, (len(vc_xy1), 2))
    if classic_xy1 is None or classic_xy2 is None:
        classic_xy1 = classic_xy2 = np.zeros((0, 2))
    _check_shape("classic_xy2", classic_xy2, (len(classic_xy1), 2))
    m, c = len(vc_xy1), len(classic_xy1)
    none = Verification(
        geometry=None,
        vc_is_inlier=np.zeros(m, dtype=bool),
        classic_is_inlier=np.zeros(c, dtype=bool),
    )
    if m + c < max(5, options.min_num_inliers):
        return none
    xy1 = np.concatenate([vc_xy1, classic_xy1]).astype(np.float64)
    xy2 = np.concatenate([vc_xy2, classic_xy2]).astype(np.float64)
    matches = np.repeat(np.arange(m + c, dtype=np.uint32)[:, None], 2, axis=1)
    tvg = pycolmap.estimate_calibrated_two_view_geometry(
        camera1, xy1, camera2, xy2, matches, two_view_options(options, camera1, camera2)
    )
    config = int(tvg.config)
    inliers = np.asarray(tvg.inlier_matches, dtype=np.int64).reshape(-1, 2)[:, 0]
    if (
        config
        not in (
            int(pycolmap.TwoViewGeometryConfiguration.CALIBRATED),
            int(pycolmap.TwoViewGeometryConfiguration.PLANAR),
            int(pycolmap.TwoViewGeometryConfiguration.PLANAR_OR_PANORAMIC),
            int(pycolmap.TwoViewGeometryConfiguration.PANORAMIC),
        )
        or len(inliers) < options.min_num_inliers
        or tvg.cam2_from_cam1 is None
    ):
        # (a planar or panoramic configuration can come without a relative pose)
        return none
    is_inlier = np.zeros(m + c, dtype=bool)
    is_inlier[inliers] = True
    pose = tvg.cam2_from_cam1.matrix()
    return Verification(
        geometry=PairGeometry(
            config=config,
            E=np.asarray(tvg.E, dtype=np.float64),
            F=np.asarray(tvg.F, dtype=np.float64),
            H=np.asarray(tvg.H, dtype=np.float64),
            cam2_from_cam1=pose,
        ),
        vc_is_inlier=is_inlier[:m],
        classic_is_inlier=is_inlier[m:],
    )


def skew(v: FloatArray) -> FloatArray:
    """(3, 3) cross-product matrix of v (3,)."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def epipolar_line_distances(
    p1: FloatArray, p2: FloatArray, M: FloatArray
) -> FloatArray:
    """(N, 2) distances of homogeneous points (N, 3) to their epipolar lines.

    ``M`` is E (normalized coordinates) or F (pixels), with p2' M p1 = 0; column 0
    is the distance in image 1, column 1 in image 2; NaN/inf where a line is
    undefined (at the epipole).
    """
    lines2 = p1 @ M.T  # epipolar lines in image 2
    lines1 = p2 @ M  # epipolar lines in image 1
    residual = np.abs(np.sum(p2 * lines2, axis=1))
    with np.errstate(divide="ignore", invalid="ignore"):
        d2 = residual / np.hypot(lines2[:, 0], lines2[:, 1])
        d1 = residual / np.hypot(lines1[:, 0], lines1[:, 1])
    return np.column_stack([d1, d2])


def epipolar_errors_px(
    camera1: pycolmap.Camera,
    camera2: pycolmap.Camera,
    cam2_from_cam1: FloatArray,
    xy1: FloatArray,
    xy2: FloatArray,
) -> FloatArray:
    """Symmetric point-to-epipolar-line distance (M,), in pixels.

    Computed on undistorted normalized coordinates (so any camera model works) and
    scaled by each camera's mean focal length; the larger of the two sides.
    """
    _check_shape("xy1", xy1, (None, 2))
    _check_shape("xy2", xy2, (len(xy1), 2))
    if len(xy1) == 0:
        return np.zeros(0)
    x1 = np.c_[camera1.cam_from_img(xy1), np.ones(len(xy1))]
    x2 = np.c_[camera2.cam_from_img(xy2), np.ones(len(xy2))]
    E = skew(cam2_from_cam1[:, 3]) @ cam2_from_cam1[:, :3]
    d = epipolar_line_distances(x1, x2, E)
    focal = np.array([camera1.mean_focal_length(), camera2.mean_focal_length()])
    # 0/0 (a point at the epipole on its own line) is no error.
    return np.nan_to_num(d * focal, nan=0.0).max(axis=1)


def verify_pair_with_classic(
    cam1: pycolmap.Camera,
    cam2: pycolmap.Camera,
    vc_xy1: FloatArray,
    vc_xy2: FloatArray,
    classic_xy1: FloatArray | None,
    classic_xy2: FloatArray | None,
    options: VerificationOptions,
    max_classic_disagreement_deg: float,
) -> Verification:
    """Verification that a few spurious classic matches cannot steer.

    The VCs are verified on their own. Classic matches join only when they verify
    on their own too *and* their relative pose agrees with the VCs' (within
    ``max_classic_disagreement_deg``); the joint estimate is then kept if it still
    agrees. Otherwise the pair's geometry is the VCs' alone, without classic inliers.
    """
    vc = verify_pair(cam1, cam2, vc_xy1, vc_xy2, options=options)
    if classic_xy1 is None or classic_xy2 is None or len(classic_xy1) == 0:
        return vc
    none_classic = np.zeros(len(classic_xy1), dtype=bool)
    classic = verify_pair(
        cam1,
        cam2,
        np.zeros((0, 2)),
        np.zeros((0, 2)),
        classic_xy1,
        classic_xy2,
        options,
    )
    if vc.geometry is None:
        return Verification(
            geometry=None, vc_is_inlier=vc.vc_is_inlier, classic_is_inlier=none_classic
        )
    limit = max_classic_disagreement_deg
    if classic.geometry is not None and (
        pose_disagreement_deg(
            classic.geometry.cam2_from_cam1, vc.geometry.cam2_from_cam1
        )
        <= limit
    ):
        joint = verify_pair(
            cam1,
            cam2,
            vc_xy1,
            vc_xy2,
            classic_xy1,
            classic_xy2,
            options,
        )
        if joint.geometry is not None and (
            pose_disagreement_deg(
                joint.geometry.cam2_from_cam1, vc.geometry.cam2_from_cam1
            )
            <= limit
        ):
            return joint
    return Verification(
        geometry=vc.geometry,
        vc_is_inlier=vc.vc_is_inlier,
        classic_is_inlier=none_classic,
    )


def inverted(result: Verification) -> Verification:
    """The same verification seen from image 2 (cam1_from_cam2, transposed E/F)."""
    g = result.geometry
    if g is None:
        return result
    R, t = g.cam2_from_cam1[:, :3], g.cam2_from_cam1[:, 3]
    return Verification(
        geometry=PairGeometry(
            config=g.config,
            E=g.E.T.copy(),
            F=g.F.T.copy(),
            H=(
                np.asarray(np.linalg.inv(g.H), dtype=np.float64)
                if abs(np.linalg.det(g.H)) > 1e-12
                else g.H.copy()
            ),
            cam2_from_cam1=np.c_[R.T, -R.T @ t],
        ),
        vc_is_inlier=result.vc_is_inlier,
        classic_is_inlier=result.classic_is_inlier,
    )


def cycle_inconsistent_pairs(
    rotations: Mapping[tuple[str, str], FloatArray], max_error_deg: float
) -> dict[tuple[str, str], str]:
    """Pairs (name order) whose rotation breaks most of the triplets they close.

    For images a < b < c with all three pairs verified, R_ac should equal R_bc R_ab.
    The pair in the most inconsistent (and more inconsistent than consistent)
    triplets is dropped, then the next, until none is left; when several pairs tie
    the cycles cannot tell which one is wrong, and none is dropped.
    """
    pairs = dict(rotations)
    dropped: dict[tuple[str, str], str] = {}
    names = sorted({n for p in pairs for n in p})
    while True:
        bad: dict[tuple[str, str], int] = {}
        good: dict[tuple[str, str], int] = {}
        worst: dict[tuple[str, str], float] = {}
        for a, b, c in itertools.combinations(names, 3):
            if not ((a, b) in pairs and (b, c) in pairs and (a, c) in pairs):
                continue
            R = pairs[(b, c)] @ pairs[(a, b)] @ pairs[(a, c)].T
            err = rotation_angle_deg(R)
            for p in ((a, b), (b, c), (a, c)):
                if err > max_error_deg:
                    bad[p] = bad.get(p, 0) + 1
                    worst[p] = max(worst.get(p, 0.0), err)
                else:
                    good[p] = good.get(p, 0) + 1
        candidates = [p for p in bad if bad[p] > good.get(p, 0)]
        if not candidates:
            return dropped
        most = max(bad[p] for p in candidates)
        worst_pairs = [p for p in candidates if bad[p] == most]
        if len(worst_pairs) > 1:
            # Several pairs break as many cycles: the cycles cannot tell which is
            # wrong (e.g. 4 views, every triplet broken); keep them all.
            return dropped
        p = worst_pairs[0]
        dropped[p] = (
            f"its rotation breaks {bad[p]} of {bad[p] + good.get(p, 0)} view "
            f"triplets (cycle error up to {worst[p]:.0f} deg > {max_error_deg:g})"
        )
        del pairs[p]
