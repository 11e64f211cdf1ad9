"""The metric scale's location estimate over the people's per-view size ratios."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pycolmap
import pytest
from scipy.spatial.transform import Rotation

from colmap_vc.metric_scale import (
    PERSON_SIZE_SD,
    MetricScale,
    effective_people,
    hodges_lehmann,
    people_disagreement,
    read_metric_scale,
    relative_pose_uncertainty,
    scale_uncertainty,
    skeleton_ratio,
    weighted_median,
    within_person_spread,
    write_metric_scale,
)


def test_hodges_lehmann_is_the_median_of_pair_averages() -> None:
    v = np.array([1.0, 2.0, 4.0])
    # pair averages (each with itself too): 1, 1.5, 2.5, 2, 3, 4 -> median 2.25
    assert hodges_lehmann(v) == pytest.approx(2.25)
    assert hodges_lehmann(np.array([0.9, 1.1])) == pytest.approx(1.0)


def test_size_errors_of_either_sign_average_out_where_the_median_does_not() -> None:
    # A fit a few percent too large or too small in each view (no mass near 1):
    # 7 views too large, 5 too small. The median picks a side, HL does not.
    rng = np.random.default_rng(3)
    e = rng.uniform(0.05, 0.15, 12) * np.r_[np.ones(7), -np.ones(5)]
    v = 1.0 + e
    assert abs(np.median(v) - 1.0) > 0.04
    assert abs(hodges_lehmann(v) - 1.0) < abs(np.median(v) - 1.0) / 2


def test_hodges_lehmann_resists_a_quarter_of_wild_views() -> None:
    v = np.r_[np.random.default_rng(0).normal(1.0, 0.03, 30), np.full(10, 6.0)]
    assert hodges_lehmann(v) == pytest.approx(1.0, abs=0.1)


def test_hodges_lehmann_does_not_depend_on_order_even_when_sampled() -> None:
    v = np.random.default_rng(1).normal(1.0, 0.1, 2000)
    full = hodges_lehmann(v)
    sampled = hodges_lehmann(v, max_pairs=50_000)
    assert sampled == hodges_lehmann(v[::-1], max_pairs=50_000)
    assert sampled == pytest.approx(full, abs=0.005)
    with pytest.raises(ValueError, match="at least one"):
        hodges_lehmann(np.array([]))


def _skeleton(seed: int = 0) -> np.ndarray:
    """17 points spread like a standing body (0.4 x 0.3 x 1.7 m)."""
    return np.random.default_rng(seed).uniform(-0.5, 0.5, (17, 3)) * [0.4, 0.3, 1.7]


def test_skeleton_ratio_reads_size_not_placement() -> None:
    model = _skeleton()
    turn = Rotation.from_rotvec([0.3, -1.2, 0.5]).as_matrix()
    prior = 1.07 * model @ turn.T + [0.2, -0.1, 4.0]
    assert skeleton_ratio(prior, model) == pytest.approx(1.07)
    # The same fit placed 10% nearer the camera: the distances from the camera
    # say 0.9 x, the skeleton still 1.07.
    nearer = prior - [0.0, 0.0, 0.4]
    assert skeleton_ratio(nearer, model) == pytest.approx(1.07)
    assert (
        np.median(np.linalg.norm(nearer, axis=1) / np.linalg.norm(prior, axis=1)) < 0.95
    )
    # And the model's own frame and scale: 3 x larger model, 1 / 3 the ratio.
    assert skeleton_ratio(prior, 3.0 * model - 5.0) == pytest.approx(1.07 / 3.0)


def test_skeleton_ratio_resists_a_stray_keypoint_and_needs_two() -> None:
    model = _skeleton(1)
    prior = 0.95 * model
    stray = model.copy()
    stray[4] += [0.5, 0.0, 0.0]  # one keypoint triangulated half a metre off
    assert skeleton_ratio(prior, stray) == pytest.approx(0.95, rel=0.03)
    noisy = model + np.random.default_rng(2).normal(0, 0.02, model.shape)
    assert skeleton_ratio(prior, noisy) == pytest.approx(0.95, rel=0.02)
    assert np.isnan(skeleton_ratio(prior[:1], model[:1]))


def test_weighted_median() -> None:
    v = np.array([3.0, 1.0, 2.0])
    assert weighted_median(v, np.ones(3)) == 2.0
    assert weighted_median(v, np.array([5.0, 1.0, 1.0])) == 3.0
    assert weighted_median(np.array([1.0, 2.0]), np.ones(2)) == 1.0  # lower on a tie


def test_uncertainty_averages_the_size_error_over_people_not_views() -> None:
    # One person seen by many views that agree: the person's size error stays.
    assert scale_uncertainty(0.0, 100, 1) == pytest.approx(PERSON_SIZE_SD)
    assert scale_uncertainty(0.01, 100, 1) == pytest.approx(
        np.hypot(PERSON_SIZE_SD, 0.001)
    )
    # Four people: half of it. The views' spread averages over the views.
    assert scale_uncertainty(0.0, 8, 4) == pytest.approx(PERSON_SIZE_SD / 2)
    assert scale_uncertainty(0.2, 4, 4) == pytest.approx(
        np.hypot(PERSON_SIZE_SD / 2, 0.1)
    )
    with pytest.raises(ValueError, match="at least one view"):
        scale_uncertainty(0.0, 0, 1)


def test_views_spread_is_taken_about_each_persons_own_size() -> None:
    # Two people 15% apart, each person's views within about 1% of each other:
    # the views' error is 1%, the people's difference is the size error's.
    rng = np.random.default_rng(5)
    a, b = 1.0 + rng.normal(0, 0.01, 6), 1.15 + rng.normal(0, 0.01, 6)
    values, person = np.r_[a, b], np.r_[np.zeros(6), np.ones(6)].astype(np.int64)
    within = within_person_spread(values, person)
    assert 0.003 < within < 0.02
    overall = 1.4826 * np.median(np.abs(values / np.median(values) - 1.0))
    assert overall > 0.05
    # One view per person: nothing within a person to measure, the overall one.
    single = within_person_spread(values[[0, 6]], np.array([0, 1]))
    assert single == pytest.approx(
        1.4826 * np.median(np.abs(values[[0, 6]] / np.median(values[[0, 6]]) - 1))
    )


def test_people_of_different_instants_may_be_one_person() -> None:
    # Two people seen 4 times each at one instant: two independent sizes.
    assert effective_people(np.array([4, 4]), ["", ""]) == pytest.approx(2.0)
    # One seen 9 times, one once: the first's size is nearly all of it.
    assert effective_people(np.array([9, 1]), ["", ""]) == pytest.approx(100 / 82)
    # A static camera's five instants of one man: five identities, one size.
    assert effective_people(np.array([4] * 5), list("abcde")) == pytest.approx(1.0)
    # Two people at each of two instants: two sizes, not four.
    assert effective_people(np.array([4, 4, 4, 4]), list("aabb")) == pytest.approx(2)


def test_people_who_disagree_beyond_their_size_error_widen_the_uncertainty() -> None:
    person = np.r_[np.zeros(4), np.ones(4)].astype(np.int64)
    # One person: nothing to disagree with.
    assert people_disagreement(np.full(4, 1.3), person[:4], 0.01) == 1.0
    # Two people 5% apart: within a 7% size error each, not widened.
    agree = np.r_[np.full(4, 1.0), np.full(4, 1.05)]
    assert people_disagreement(agree, person, 0.0) == 1.0
    # 17% apart (pose2sim_multi's man and avatar): chi^2 of one degree of
    # freedom is d^2 / (2 var), the Birge ratio its root.
    far = np.r_[np.full(4, 1.0), np.full(4, 1.17)]
    var = PERSON_SIZE_SD**2 + 0.02**2 / 4
    assert people_disagreement(far, person, 0.02) == pytest.approx(
        np.log(1.17) / np.sqrt(2 * var)
    )
    # Each person's scale is the median of its views': one wild view of four
    # does not make two people who agree disagree.
    wild = agree.copy()
    wild[0] = 3.0
    assert people_disagreement(wild, person, 0.0) == 1.0
    # Static cameras: one person at each of two instants may be one person, so
    # two identities 17% apart are not two people who disagree...
    assert people_disagreement(far, person, 0.02, {0: "t1", 1: "t2"}) == 1.0
    # ...while two people at each of two instants disagree within each instant.
    four = np.r_[far, far]
    both = np.repeat(np.arange(4), 4)
    when = {0: "t1", 1: "t1", 2: "t2", 3: "t2"}
    assert people_disagreement(four, both, 0.02, when) == pytest.approx(
        np.log(1.17) / np.sqrt(2 * var)
    )


def test_describe_says_when_the_people_disagree() -> None:
    two = MetricScale(
        scale=1.0,
        spread=0.08,
        num_person_views=8,
        num_people=2,
        uncertainty=0.079,
        disagreement=1.58,
    )
    assert two.describe() == (
        "+-7.9% (2 people, widened x1.6: they disagree on the size)"
    )


def test_a_scale_file_without_uncertainty_gets_it_from_its_fields(
    tmp_path: Path,
) -> None:
    assert read_metric_scale(tmp_path) is None  # no file: the scale is arbitrary
    old = {"scale": 0.8, "spread": 0.02, "num_person_views": 4, "num_people": 1}
    (tmp_path / "metric_scale.json").write_text(json.dumps(old))
    scale = read_metric_scale(tmp_path)
    assert scale is not None and scale.scale == 0.8
    assert scale.uncertainty == pytest.approx(np.hypot(PERSON_SIZE_SD, 0.01))


def test_a_broken_scale_file_names_itself(tmp_path: Path) -> None:
    (tmp_path / "metric_scale.json").write_text('{"scale": 0.8}')
    with pytest.raises(ValueError, match=r"metric_scale\.json.*spread"):
        read_metric_scale(tmp_path)
    (tmp_path / "metric_scale.json").write_text("{not json")
    with pytest.raises(ValueError, match=r"metric_scale\.json is not a metric scale"):
        read_metric_scale(tmp_path)


def _pair(angle_deg: float, first_id: int = 1) -> pycolmap.Reconstruction:
    """Two cameras 4 m from the origin, ``angle_deg`` apart about it, looking at
    it; image a.jpg gets id ``first_id``, b.jpg the other."""
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(
        pycolmap.Camera(
            camera_id=1,
            model="PINHOLE",
            width=640,
            height=480,
            params=[500, 500, 320, 240],
        )
    )
    for k, (name, az) in enumerate((("a.jpg", 0.0), ("b.jpg", angle_deg))):
        a = np.radians(az)
        centre = 4.0 * np.array([np.sin(a), 0.0, -np.cos(a)])
        z = -centre / np.linalg.norm(centre)  # looks at the origin
        x = np.cross([0.0, 1.0, 0.0], z)
        R = np.stack([x, np.cross(z, x), z])
        image_id = first_id if k == 0 else 3 - first_id
        rec.add_image_with_trivial_frame(
            pycolmap.Image(name=name, camera_id=1, image_id=image_id),
            pycolmap.Rigid3d(pycolmap.Rotation3d(R), -R @ centre),
        )
    return rec


def _scale_of_truth(rec: pycolmap.Reconstruction):
    """A scale from the pair: the true depths of a person-sized cloud over the
    depths the model's poses triangulate from its true pixels (1 at the truth)."""
    points = np.random.default_rng(0).uniform(
        [-0.3, -0.9, -0.2], [0.3, 0.9, 0.2], (40, 3)
    )
    ids = sorted(rec.reg_image_ids())
    camera = rec.camera(1)
    truth = {i: rec.image(i).cam_from_world().matrix() for i in ids}
    pixels = {
        i: camera.img_from_cam(points @ T[:, :3].T + T[:, 3]) for i, T in truth.items()
    }
    depth = {
        i: np.linalg.norm(points @ T[:, :3].T + T[:, 3], axis=1)
        for i, T in truth.items()
    }

    def scale_of(model: pycolmap.Reconstruction) -> float:
        Ts = {i: model.image(i).cam_from_world().matrix() for i in ids}
        rays = {
            i: np.c_[camera.cam_from_img(pixels[i]), np.ones(len(points))] for i in ids
        }
        X = []
        for n in range(len(points)):  # loop over 40 points: DLT of two views
            rows = []
            for i in ids:
                P = Ts[i]
                u, v = rays[i][n, :2]
                rows += [u * P[2] - P[0], v * P[2] - P[1]]
            h = np.linalg.svd(np.array(rows))[2][-1]
            X.append(h[:3] / h[3])
        X = np.array(X)
        ratios = [
            depth[i] / np.linalg.norm(X @ Ts[i][:, :3].T + Ts[i][:, 3], axis=1)
            for i in ids
        ]
        return float(np.median(np.concatenate(ratios)))

    return scale_of


def test_a_narrow_pairs_scale_follows_its_relative_pose_more() -> None:
    """Triangulated depths follow the relative pose by more the narrower the
    baseline: turning one camera of a 15 deg pair by a few degrees moves its
    scale several times more than a 90 deg pair's."""
    narrow, wide = _pair(15.0), _pair(90.0)
    assert _scale_of_truth(narrow)(narrow) == pytest.approx(1.0, abs=1e-6)
    u_narrow = relative_pose_uncertainty(narrow, _scale_of_truth(narrow), 3.8)
    u_wide = relative_pose_uncertainty(wide, _scale_of_truth(wide), 3.8)
    assert u_wide > 0.01 and u_narrow > 3.0 * u_wide, (u_narrow, u_wide)


def test_the_relative_pose_term_follows_names_not_image_ids() -> None:
    """Which camera is turned is the second by name, whatever ids COLMAP gave."""
    one, other = _pair(40.0, first_id=1), _pair(40.0, first_id=2)
    u = relative_pose_uncertainty(one, _scale_of_truth(one), 3.8)
    assert u == pytest.approx(
        relative_pose_uncertainty(other, _scale_of_truth(other), 3.8), rel=1e-9
    )
    # A scale that does not depend on the poses has no such part.
    assert relative_pose_uncertainty(one, lambda model: 2.0, 3.8) == 0.0


def test_describe_gives_the_uncertainty_people_and_relative_pose() -> None:
    one = MetricScale(
        scale=1.2, spread=0.02, num_person_views=4, num_people=1, uncertainty=0.0712
    )
    assert one.describe() == "+-7.1% (1 person)"
    pair = MetricScale(
        scale=1.2,
        spread=0.02,
        num_person_views=2,
        num_people=3,
        uncertainty=0.15,
        relative_pose=0.142,
    )
    assert pair.describe() == "+-15.0% (3 people, the relative pose +-14.2%)"


def test_static_cameras_identities_are_not_called_people(tmp_path: Path) -> None:
    # One man filmed at five instants: five identities, one person's size error.
    man = MetricScale(
        scale=1.2,
        spread=0.02,
        num_person_views=20,
        num_people=5,
        uncertainty=0.07,
        num_instants=5,
        people_per_instant=1,
    )
    assert man.describe() == (
        "+-7.0% (5 identities over 5 instants, taken as 1 person)"
    )
    write_metric_scale(tmp_path, man)
    assert read_metric_scale(tmp_path) == man
    # A file written before these fields: one instant, its identities as people.
    old = {"scale": 0.8, "spread": 0.02, "num_person_views": 8, "num_people": 2}
    (tmp_path / "metric_scale.json").write_text(json.dumps(old))
    read = read_metric_scale(tmp_path)
    assert read is not None and read.describe().endswith("(2 people)")
