"""Verification that a few spurious classic matches cannot steer a pair."""

from __future__ import annotations

import numpy as np
import pycolmap
import pytest
from scipy.spatial.transform import Rotation

from colmap_vc.evaluation import pose_disagreement_deg
from colmap_vc.verification import (
    VerificationOptions,
    cycle_inconsistent_pairs,
    inverted,
    verify_pair,
    verify_pair_with_classic,
)

CAM = pycolmap.Camera(
    model="PINHOLE", width=640, height=480, params=[500, 500, 320, 240]
)


def _project(points_world: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    return np.asarray(CAM.img_from_cam(points_world @ R.T + t))


def _pair(rng: np.random.Generator, angle_deg: float) -> tuple:
    """Points around the origin seen by camera 1 at (0, 0, -4) and camera 2 turned
    ``angle_deg`` around them; returns (xy1, xy2, cam2_from_cam1)."""
    X = rng.normal(0, 0.4, (300, 3))
    R1, t1 = np.eye(3), np.array([0.0, 0.0, 4.0])
    R2 = Rotation.from_euler("y", angle_deg, degrees=True).as_matrix()
    t2 = np.array([0.0, 0.0, 4.0])
    xy1 = _project(X, R1, t1) + rng.normal(0, 1.0, (300, 2))
    xy2 = _project(X, R2, t2) + rng.normal(0, 1.0, (300, 2))
    R = R2 @ R1.T
    return xy1, xy2, np.c_[R, t2 - R @ t1]


@pytest.mark.parametrize("classic", ["spurious", "agreeing"])
def test_classic_matches_join_only_when_they_agree(rng, classic) -> None:
    xy1, xy2, truth = _pair(rng, 70.0)
    vc1, vc2 = xy1[:200], xy2[:200]
    if classic == "agreeing":
        c1, c2 = xy1[200:], xy2[200:]
    else:  # 40 matches of another scene geometry (another relative pose)
        other1, other2, _ = _pair(np.random.default_rng(9), -40.0)
        c1, c2 = other1[:40], other2[:40]
    options = VerificationOptions()
    result = verify_pair_with_classic(CAM, CAM, vc1, vc2, c1, c2, options, 20.0)
    vc_only = verify_pair(CAM, CAM, vc1, vc2, options=options)
    assert result.geometry is not None and vc_only.geometry is not None
    assert pose_disagreement_deg(result.geometry.cam2_from_cam1, truth) < 5.0
    if classic == "agreeing":
        assert result.classic_is_inlier.mean() > 0.8
    else:
        assert not result.classic_is_inlier.any()


def test_inverted_swaps_the_images(rng) -> None:
    xy1, xy2, _ = _pair(rng, 50.0)
    forward = verify_pair(CAM, CAM, xy1, xy2)
    backward = verify_pair(CAM, CAM, xy2, xy1)
    flipped = inverted(forward)
    assert forward.geometry is not None and backward.geometry is not None
    assert (
        pose_disagreement_deg(
            flipped.geometry.cam2_from_cam1, backward.geometry.cam2_from_cam1
        )
        < 1.0
    )
    assert np.array_equal(flipped.vc_is_inlier, forward.vc_is_inlier)


def test_the_pair_that_breaks_the_cycles_is_dropped() -> None:
    yaw = {
        n: Rotation.from_euler("y", 40 * k, degrees=True).as_matrix()
        for k, n in enumerate("abcd")
    }
    rel = {(m, n): yaw[n] @ yaw[m].T for m in "abcd" for n in "abcd" if m < n}
    assert cycle_inconsistent_pairs(rel, 35.0) == {}
    rel[("b", "d")] = (
        Rotation.from_euler("x", 90, degrees=True).as_matrix() @ rel[("b", "d")]
    )
    assert list(cycle_inconsistent_pairs(rel, 35.0)) == [("b", "d")]
