"""Pose errors and AUC against hand-computed values and SuperGlue's definition."""

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from colmap_vc import evaluation as ev


def test_auc_matches_a_hand_computed_example():
    # Errors 5, 10, 40 deg. Recall steps: (0,0) (5,1/3) (10,2/3) (40,1).
    # AUC@15 = [trapezoids 0-5: 5*(0+1/3)/2, 5-10: 5*(1/3+2/3)/2, 10-15: 5*2/3] / 15
    expected15 = (5 * (1 / 3) / 2 + 5 * (1 / 3 + 2 / 3) / 2 + 5 * (2 / 3)) / 15
    # AUC@45 adds 10-40 (30 * (2/3 + 1) / 2) and 40-45 (5 * 1).
    expected45 = (5 * (1 / 3) / 2 + 5 * 0.5 + 30 * (2 / 3 + 1) / 2 + 5) / 45
    auc15, auc45 = ev.pose_auc([40.0, 5.0, 10.0], [15, 45])
    assert auc15 == pytest.approx(expected15)
    assert auc45 == pytest.approx(expected45)


def test_auc_extremes():
    assert ev.pose_auc([0.0, 0.0], [15])[0] == pytest.approx(1.0)
    assert ev.pose_auc([180.0] * 3, [15, 30, 45]) == [0.0, 0.0, 0.0]


def _random_poses(rng, n):
    poses = {}
    for i in range(n):
        R = Rotation.random(random_state=rng.integers(1 << 31)).as_matrix()
        poses[f"im{i}.jpg"] = np.c_[R, rng.normal(size=3)]
    return poses


def test_errors_vanish_under_a_similarity_transform():
    rng = np.random.default_rng(0)
    gt = _random_poses(rng, 5)
    # world' = s R0 world + t0  =>  cam_from_world' = [R R0^T | s t - R R0^T t0]
    R0 = Rotation.random(random_state=3).as_matrix()
    t0, s = rng.normal(size=3), 2.5
    pred = {
        k: np.c_[P[:, :3] @ R0.T, s * P[:, 3] - P[:, :3] @ R0.T @ t0]
        for k, P in gt.items()
    }
    m = ev.evaluate_poses(pred, gt)
    assert m.num_registered == 5 and len(m.pairs) == 10
    assert max(p.error_deg for p in m.pairs) < 1e-6
    assert m.auc["30"] == pytest.approx(100.0)


def test_known_rotation_error_and_unregistered_pairs():
    gt = {
        "a": np.c_[np.eye(3), [0, 0, 0]],
        "b": np.c_[np.eye(3), [1.0, 0, 0]],
        "c": np.c_[np.eye(3), [0, 1.0, 0]],
    }
    R = Rotation.from_euler("y", 20, degrees=True).as_matrix()
    pred = {"a": gt["a"], "b": np.c_[R, [1.0, 0, 0]]}  # c unregistered
    m = ev.evaluate_poses(pred, gt)
    by_pair = {(p.image_name1, p.image_name2): p for p in m.pairs}
    assert by_pair[("a", "b")].rotation_deg == pytest.approx(20.0)
    assert by_pair[("a", "b")].translation_deg == pytest.approx(0.0, abs=1e-9)
    assert by_pair[("a", "c")].error_deg == 180.0 and not by_pair[("a", "c")].registered
    assert m.num_registered == 2
    assert m.median_error_deg == 180.0


def test_translation_sign_is_not_folded():
    gt = {"a": np.c_[np.eye(3), [0, 0, 0]], "b": np.c_[np.eye(3), [1.0, 0, 0]]}
    pred = {"a": gt["a"], "b": np.c_[np.eye(3), [-1.0, 0, 0]]}
    (pair,) = ev.evaluate_poses(pred, gt).pairs
    assert pair.translation_deg == pytest.approx(180.0)
    assert math.isclose(pair.error_deg, 180.0)


def test_tilt_errors_ignore_the_world_rotation_and_find_a_tilted_camera():
    rng = np.random.default_rng(1)
    gt = _random_poses(rng, 8)
    up = np.array([0.0, 0.0, 1.0])
    R0 = Rotation.random(random_state=5).as_matrix()  # the model's own world
    pred = {k: np.c_[P[:, :3] @ R0.T, P[:, 3]] for k, P in gt.items()}
    assert max(ev.tilt_errors_deg(pred, gt, up).values()) < 1e-6
    # One camera turned 3 deg about its optical axis (a roll: its up tilts by
    # 3 deg, unless it looks straight down): the others stay near 0.
    roll = Rotation.from_rotvec(np.radians(3.0) * np.array([0.0, 0, 1])).as_matrix()
    pred["im0.jpg"] = np.c_[roll @ pred["im0.jpg"][:, :3], pred["im0.jpg"][:, 3]]
    tilt = ev.tilt_errors_deg(pred, gt, up)
    axis = gt["im0.jpg"][:, :3] @ up  # the up in im0's frame
    expected = np.degrees(np.arcsin(np.linalg.norm(axis[:2]) * np.sin(np.radians(3))))
    # the fitted world rotation shares the turn among 8 cameras: 7/8 of it stays
    assert tilt["im0.jpg"] == pytest.approx(expected * 7 / 8, abs=0.3)
    assert max(v for k, v in tilt.items() if k != "im0.jpg") < 0.5
    assert ev.tilt_errors_deg({"im0.jpg": pred["im0.jpg"]}, gt, up) == {}
