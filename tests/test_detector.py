"""The multi-person BlazePose detector: anchors, decoding, ROI geometry, real photos."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from colmap_vc.estimators import EstimatorOptions, body
from colmap_vc.estimators import blazepose as bp

HERE = Path(__file__).resolve().parent
LABELS = HERE / "data" / "pose2sim_people.json"
DATA = next(
    (
        p
        for p in (HERE.parents[1] / "shared" / "data", Path("/work/shared/data"))
        if p.is_dir()
    ),
    HERE.parents[1] / "shared" / "data",
)
HIPS = [body.BLAZEPOSE_NAMES.index(n) for n in ("left_hip", "right_hip")]


def test_ssd_anchors_match_mediapipe_layout():
    a = bp.ssd_anchors()
    assert a.shape == (2254, 2)  # 28^2 * 2 + 14^2 * 2 + 7^2 * 6
    assert np.all((a > 0) & (a < 1))
    # First layer: stride 8 (28 x 28 cells), two anchors per cell, row-major.
    np.testing.assert_allclose(a[0], a[1])
    np.testing.assert_allclose(a[0], [0.5 / 28, 0.5 / 28])
    np.testing.assert_allclose(a[2], [1.5 / 28, 0.5 / 28])
    np.testing.assert_allclose(a[56], [0.5 / 28, 1.5 / 28])
    # Last group: stride 32 (7 x 7 cells), six anchors per cell.
    tail = a[1568 + 392 :]
    assert len(tail) == 294 and np.all(tail[:6] == tail[0])


def test_decode_and_nms_recover_planted_detections():
    """Two people planted in the raw outputs at known anchors come back as two
    detections at the planted places; neighbours of one person merge into it."""
    anchors = bp.ssd_anchors()
    raw = np.zeros((2254, 12))
    scores = np.full((2254, 1), -10.0)
    truth = {}
    for idx, centre in ((300, (0.3, 0.4)), (1000, (0.7, 0.6))):
        for j, jitter in ((idx, 0.0), (idx + 1, 0.004)):  # a duplicate, jittered
            c = np.array(centre) + jitter
            raw[j, :2] = (c - anchors[j]) * bp.DETECTOR_SIZE
            raw[j, 2:4] = 0.2 * bp.DETECTOR_SIZE
            kps = c + np.array([[0.0, 0.1], [0.0, -0.15], [0.0, -0.05], [0.0, -0.1]])
            raw[j, 4:] = ((kps - anchors[j]) * bp.DETECTOR_SIZE).ravel()
            scores[j] = 3.0 if jitter == 0 else 1.0
        truth[idx] = np.array(centre)
    s, boxes, kps = bp.weighted_nms(*bp.decode_detections(raw, scores, 0.5))
    assert len(s) == 2
    np.testing.assert_allclose(s, 1 / (1 + np.exp(-3.0)))
    centres = (boxes[:, :2] + boxes[:, 2:]) / 2
    for c in truth.values():
        assert np.min(np.linalg.norm(centres - c, axis=1)) < 0.004
    np.testing.assert_allclose(boxes[:, 2:] - boxes[:, :2], 0.2)
    np.testing.assert_allclose(kps[:, 0] - centres, [[0.0, 0.1]] * 2, atol=0.004)


def test_roi_rotation_and_crop_matrix():
    up = bp.PersonBox(
        score=1.0,
        box=np.zeros(4),
        keypoints=np.array([[500.0, 800.0], [500.0, 400.0], [0, 0], [0, 0]]),
    )
    roi = bp.roi_from_detection(up)
    assert roi.rotation == pytest.approx(0.0)
    assert roi.side == pytest.approx(2 * 400 * 1.25)
    # Lying person, head (scale point) to the right: the crop's up is the image's right.
    lying = bp.PersonBox(
        score=1.0,
        box=np.zeros(4),
        keypoints=np.array([[500.0, 800.0], [900.0, 800.0], [0, 0], [0, 0]]),
    )
    roi = bp.roi_from_detection(lying)
    assert roi.rotation == pytest.approx(np.pi / 2)
    m = bp._crop_matrix(roi, 256)
    # Tensor centre (127.5, 127.5) -> ROI centre (OpenCV pixels = COLMAP - 0.5).
    np.testing.assert_allclose(m @ [127.5, 127.5, 1.0], roi.center - 0.5, atol=1e-9)
    top = m @ [127.5, -0.5, 1.0] + 0.5  # the crop's top edge centre
    np.testing.assert_allclose(top, np.add(roi.center, [roi.side / 2, 0.0]), atol=1e-9)


def _load_image(dataset: str, name: str) -> np.ndarray:
    from colmap_vc.estimators.mediapipe import read_image

    img = read_image(DATA / dataset / "images" / name)
    assert img is not None
    return img


@pytest.fixture(scope="module")
def model():
    pytest.importorskip("ai_edge_litert")
    if not DATA.is_dir():
        pytest.skip(f"{DATA} not available")
    return bp.BlazePose()


def test_two_people_side_by_side(model):
    """A photo of one man next to its mirror image: two people, each at his place,
    the mirrored one's hips the mirror of the original's, masks disjoint."""
    img = _load_image("pose2sim_single", "cam03_t010.jpg")
    w = img.shape[1]
    pair = np.concatenate([img, img[:, ::-1]], axis=1)
    people = bp.find_people(model, np.ascontiguousarray(pair))
    assert len(people) == 2
    hips = sorted(p.landmarks.xy_img[HIPS].mean(axis=0)[0] for p in people)
    assert hips[0] < w < hips[1]
    np.testing.assert_allclose(hips[0] + hips[1], 2 * w, atol=0.02 * w)
    seg = [bp.segmentation_mask(p) for p in people]
    assert all(s.sum() > 10_000 for s in seg) and not (seg[0] & seg[1]).any()


@pytest.fixture(scope="module")
def synthetic_pair(tmp_path_factory: pytest.TempPathFactory):
    """A synthetic pair (colmap-vc synth): two people, two cameras."""
    from colmap_vc.synthetic import SynthOptions, generate

    out = tmp_path_factory.mktemp("synth")
    generate(
        "pair",
        out,
        SynthOptions(
            seed=3,
            num_people=2,
            width=960,
            height=720,
            make_database=False,
            overwrite=True,
        ),
    )
    return out


def test_synthetic_two_people_found_at_their_places(model, synthetic_pair):
    """Every detection is a rendered person, found once, where the ground truth puts
    it (its landmark box overlaps the box of the projected joints, IoU >= 0.5); every
    person whose box overlaps nobody else's is found (one may hide the other)."""
    from colmap_vc.estimators.mediapipe import read_image
    from colmap_vc.priors import read_priors

    gt = read_priors(synthetic_pair / "gt" / "priors")
    num_apart = 0
    for name, image_prior in gt.images.items():
        image = read_image(synthetic_pair / "images" / name)
        assert image is not None
        people = bp.find_people(model, image, levels=3)
        truth = np.array(
            [
                np.r_[p.keypoints_xy.min(axis=0), p.keypoints_xy.max(axis=0)]
                for p in image_prior.persons
            ]
        )
        assert len(truth) == 2 and 1 <= len(people) <= 2, name
        found = np.array([bp.landmark_box(p.landmarks, 0.5) for p in people])
        iou = bp.box_iou(found, truth)
        assert iou.max(axis=1).min() >= 0.5, (name, iou)
        assert len(set(iou.argmax(axis=1))) == len(people), (name, iou)
        if bp.box_iou(truth[:1], truth[1:])[0, 0] == 0.0:  # apart: both visible
            num_apart += 1
            assert len(people) == 2, name
    assert num_apart >= 1  # the scene has a view with the two people apart


@pytest.mark.parametrize(
    ("dataset", "levels", "min_recall_main", "min_recall_all"),
    [
        ("pose2sim_multi", 3, 0.9, 0.9),
        ("pose2sim_single", 3, 1.0, 0.9),
        ("pose2sim_multi", 2, 0.9, 0.7),
    ],
)
def test_pose2sim_recall_and_precision(
    model, dataset, levels, min_recall_main, min_recall_all
):
    """Against the hand labels (bench/detection.py). 3 detector passes:
    pose2sim_multi recall 0.97 of the man and the woman, 0.96 with the bystander,
    precision 1.00; pose2sim_single 1.00 / 0.97 / 1.00. 2 passes (the default) on
    pose2sim_multi: 0.95 / 0.76 / 1.00. The former repaint-and-rerun path: 0.88 / 0.70
    and 1.00 / 0.67. Thresholds: the measured values rounded down to 0.1."""
    if not (DATA / dataset).is_dir():
        pytest.skip(f"{dataset} not available")
    from bench.detection import match
    from colmap_vc.estimators import mediapipe as mp_estimator

    labels = json.loads(LABELS.read_text())[dataset]
    options = EstimatorOptions(show_progress=False, detector_levels=levels)
    found: list[tuple[str, bool]] = []
    num_detections = 0
    for name, people in labels.items():
        image = _load_image(dataset, name)
        lms = [d.landmarks for d in mp_estimator.detect_people(model, image, options)]
        num_detections += len(lms)
        hits = match(lms, people)
        found += [
            (p["label"], m is not None) for p, m in zip(people, hits, strict=True)
        ]
    main = [ok for label, ok in found if label in ("man", "woman")]
    assert np.mean(main) >= min_recall_main
    assert np.mean([ok for _, ok in found]) >= min_recall_all
    assert sum(ok for _, ok in found) / num_detections >= 0.95  # precision


def _standing(
    x0: float, top: float, height: float, width: float, feet_seen: bool = True
):
    """BlazePose landmarks of a person standing upright in the image: head at
    ``top``, feet ``height`` px below, ``width`` wide from ``x0``."""
    rng = np.random.default_rng(0)
    xy = np.c_[
        x0 + rng.uniform(0, width, body.NUM_LANDMARKS),
        top + rng.uniform(0, 0.75 * height, body.NUM_LANDMARKS),
    ]
    feet = np.asarray(bp.FEET)
    xy[feet, 1] = top + height - rng.uniform(0, 0.04 * height, len(feet))
    xy[feet[-1], 1] = top + height
    xy[[0, 1], 0] = x0, x0 + width  # the box's sides and top
    xy[0, 1] = top
    visibility = np.ones(body.NUM_LANDMARKS)
    if not feet_seen:
        visibility[feet] = 0.1
    return body.BodyLandmarks(
        xy_img=xy, points_3d=np.zeros((body.NUM_LANDMARKS, 3)), visibility=visibility
    )


def test_a_copy_on_a_persons_legs_is_part_of_them_a_child_in_front_is_not():
    # pose2sim_single t070 cam01 saved again as JPEG: the man's landmark box
    # (381-778, 525-1277) and a skeleton over his legs (376-703, 788-1267), 52 %
    # of his area and inside his box, its feet 330 px above his.
    adult = _standing(381.0, 525.0, 752.0, 397.0)
    copy = _standing(381.0, 788.0, 479.0, 322.0)
    copy.xy_img[np.asarray(bp.FEET), 1] -= 330.0
    copy.xy_img[2, 1] = 1267.0  # its box still reaches his feet
    # A child a step in front of him: nearly as wide, inside his box, its feet
    # lower in the image (nearer the camera, on the same floor).
    child = _standing(381.0, 760.0, 560.0, 380.0)

    def area(lm: body.BodyLandmarks) -> float:
        box = bp.landmark_box(lm, 0.5)
        return float(np.prod(box[2:] - box[:2]))

    assert area(copy) > 0.5 * area(adult)  # too large to be a crop of him
    assert area(child) > 0.5 * area(adult)
    assert bp._part_of(copy, adult)
    assert not bp._part_of(child, adult)
    # Without feet seen, nothing says which: the larger one is kept.
    unseen = _standing(381.0, 788.0, 479.0, 322.0, feet_seen=False)
    unseen.xy_img[2, 1] = 1267.0  # the same box as the copy's
    assert area(unseen) > 0.5 * area(adult)
    assert not bp._part_of(unseen, adult)
    # A crop of at most half the area is a part whatever its feet.
    assert bp._part_of(_standing(420.0, 900.0, 360.0, 300.0), adult)
