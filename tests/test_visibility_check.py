"""Visibility check: a linked "person" missing where it should be seen is left out."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pycolmap
import pytest
from scipy.spatial.transform import Rotation
from scipy.stats import binom

from colmap_vc import cli, database
from colmap_vc.association import Association, AssociationOptions, PersonCue
from colmap_vc.synthetic import SynthOptions, generate
from colmap_vc.synthetic.gt import gt_persons_path, read_gt_persons
from colmap_vc.visibility_check import _box, _overlap, binomial_tail, check_visibility

_RNG = np.random.default_rng(5)
# A body-like point cloud: 1.7 m tall (y down), 0.4 m wide, 0.25 m deep.
_BODY = _RNG.uniform(-0.5, 0.5, (300, 3)) * [0.4, 1.7, 0.25]
_CAMERA = pycolmap.Camera(
    model="PINHOLE", width=640, height=480, params=[500.0, 500.0, 320.0, 240.0]
)
_OPTIONS = AssociationOptions()


def _ring(n: int, radius: float = 5.0) -> dict[str, np.ndarray]:
    """cam_from_world (3, 4) of n cameras on a circle, looking at the origin."""
    out = {}
    for k in range(n):
        yaw = 2 * np.pi * k / n
        R = Rotation.from_euler("y", yaw).as_matrix()
        centre = np.array([radius * np.sin(yaw), 0.0, -radius * np.cos(yaw)])
        out[f"img{k}.jpg"] = np.c_[R, -R @ centre]
    return out


Detection = tuple[str, str, np.ndarray]  # image, who, vertices in the camera frame


def _detect(
    world: dict[str, np.ndarray],
    cams: dict[str, np.ndarray],
    missed: frozenset[tuple[str, str]] = frozenset(),
) -> list[Detection]:
    """What a detector finds of people at ``world``: whoever is inside the frame
    and not behind a nearer person (beyond the check's own overlap), except the
    ``missed`` (image, who)."""
    out = []
    for name, T in cams.items():
        people = sorted(
            ((who, (_BODY + p) @ T[:, :3].T + T[:, 3]) for who, p in world.items()),
            key=lambda wv: float(wv[1][:, 2].mean()),
        )
        nearer: list[np.ndarray] = []
        for who, v in people:
            box, inside = _box(_CAMERA, v)
            hidden = any(
                _overlap(box, _box(_CAMERA, o)[0]) > _OPTIONS.hidden_overlap
                for o in nearer
            )
            if inside >= 0.95 and not hidden and (name, who) not in missed:
                out.append((name, who, v))
            nearer.append(v)
    return out


def _associated(
    detections: list[Detection],
) -> tuple[list[PersonCue], Association, dict[str, int]]:
    """Cues and the association that links every detection of one "who" (what the
    joint association gives); identity numbers by name."""
    names = sorted({who for _, who, _ in detections})
    ident = {who: i for i, who in enumerate(names)}
    count: dict[str, int] = {}
    cues, identity = [], {}
    for image, who, v in detections:
        k = count.get(image, 0)
        count[image] = k + 1
        cues.append(
            PersonCue(image_name=image, index=k, person_id=None, vertices_cam=v)
        )
        identity[(image, k)] = ident[who]
    keys = sorted(identity)
    links: dict[tuple[str, str], list[tuple[int, int]]] = {}
    for a in keys:
        for b in keys:
            if a[0] < b[0] and identity[a] == identity[b]:
                links.setdefault((a[0], b[0]), []).append((a[1], b[1]))
    return cues, Association(identity=identity, links=links, confidence={}), ident


def _false_bodies(cams: dict[str, np.ndarray], images: list[str]) -> list[Detection]:
    """A body that is not there, in front of each camera of ``images`` (3.5 m deep,
    1 m to one side), each somewhere else in the world."""
    out = []
    for k, name in enumerate(images):
        offset = np.array([(-1) ** k * 1.0, 0.0, 3.5])
        out.append((name, "false", _BODY + offset))
    return out


def test_binomial_tail_is_the_binomial_survival_function() -> None:
    for k, n, p in [(0, 5, 0.1), (1, 8, 0.1), (4, 9, 0.1), (6, 8, 0.2), (3, 3, 0.5)]:
        assert abs(binomial_tail(k, n, p) - binom.sf(k - 1, n, p)) < 1e-12


def test_a_false_person_linked_across_images_is_left_out() -> None:
    cams = _ring(10)
    detections = _detect({"A": np.zeros(3)}, cams)
    detections += _false_bodies(cams, ["img0.jpg", "img1.jpg", "img5.jpg"])
    cues, association, ident = _associated(detections)
    cameras = {n: _CAMERA for n in cams}
    result, left_out = check_visibility(association, cues, cameras, _OPTIONS)
    assert [u.identity for u in left_out] == [ident["false"]]
    judged = left_out[0].detections
    assert [d.key for d in judged] == [
        ("img0.jpg", 1),
        ("img1.jpg", 1),
        ("img5.jpg", 1),
    ]
    for d in judged:
        # Each places the body in view of 3 more images that do not show it.
        assert len(d.missed) == 3 and d.in_view == 4
        assert d.tail == binomial_tail(3, 4, _OPTIONS.miss_prob) < _OPTIONS.unseen_alpha
    assert "img0.jpg #1 not found in 3 of the 3 other images" in left_out[0].reason
    off = dataclasses.replace(_OPTIONS, unseen_alpha=0.0)
    assert check_visibility(association, cues, cameras, off) == (association, [])
    # Its detections are unassociated, its links gone; the real person stays,
    # numbered 0.
    for c, (_, who, _) in zip(cues, detections, strict=True):
        assert (result.identity[c.key] == -1) == (who == "false")
    assert set(result.identity.values()) == {-1, 0}
    assert result.links and all(
        result.identity[(pair[0], a)] == 0
        for pair, pl in result.links.items()
        for a, _ in pl
    )
    num_links = sum(len(pl) for pl in result.links.values())
    assert num_links == sum(len(pl) for pl in association.links.values()) - 3


def test_half_of_the_detections_unseen_is_enough() -> None:
    """Two false bodies in front of the real person place each other behind it
    (hidden: no evidence), the two others in view of images that do not show it:
    half the detections fail, and the identity goes."""
    cams = _ring(10)
    detections = _detect({"A": np.zeros(3)}, cams)
    detections += _false_bodies(cams, ["img0.jpg", "img1.jpg", "img5.jpg", "img7.jpg"])
    cues, association, ident = _associated(detections)
    _, left_out = check_visibility(association, cues, {n: _CAMERA for n in cams})
    assert [u.identity for u in left_out] == [ident["false"]]
    failed = [d.tail < _OPTIONS.unseen_alpha for d in left_out[0].detections]
    assert failed == [True, True, False, False]


def test_real_people_hidden_cut_or_missed_once_stay() -> None:
    """A second person hidden behind the first in some views, a bystander outside
    the ring that only the cameras facing it see, and a person the detector missed
    in one view where it is in plain sight: all real, all kept."""
    cams = _ring(10)
    world = {
        "A": np.zeros(3),
        "B": np.array([0.5, 0.0, 0.4]),
        "C": np.array([0.0, 0.0, 9.0]),
    }
    detections = _detect(world, cams, missed=frozenset({("img3.jpg", "A")}))
    seen_by = {who: sum(d[1] == who for d in detections) for who in world}
    assert seen_by["B"] < 10 and 2 <= seen_by["C"] <= 5  # the scene tests what it says
    cues, association, _ = _associated(detections)
    cameras = {n: _CAMERA for n in cams}
    result, left_out = check_visibility(association, cues, cameras, _OPTIONS)
    assert left_out == []
    assert result is association


def test_the_miss_rate_comes_from_the_other_people() -> None:
    """A real person missed in plain sight in 4 of its 9 views looks like no one to
    a detector that misses 10% (left out, as designed); when the detector misses
    the others as often, the same misses are its noise, and the person stays."""
    cams = _ring(10)
    world = {
        "A": np.zeros(3),
        "B": np.array([1.5, 0.0, 0.5]),
        "C": np.array([-1.5, 0.0, -0.5]),
    }
    missed_b = {(f"img{k}.jpg", "B") for k in (1, 3, 5, 7)}
    missed_others = {(f"img{k}.jpg", "A") for k in (0, 2, 4, 6)} | {
        (f"img{k}.jpg", "C") for k in (1, 4, 6, 9)
    }
    cameras = {n: _CAMERA for n in cams}
    cues, association, ident = _associated(_detect(world, cams, frozenset(missed_b)))
    _, left_out = check_visibility(association, cues, cameras, _OPTIONS)
    assert [u.identity for u in left_out] == [ident["B"]]
    assert left_out[0].miss_prob == _OPTIONS.miss_prob
    cues, association, _ = _associated(
        _detect(world, cams, frozenset(missed_b | missed_others))
    )
    assert check_visibility(association, cues, cameras, _OPTIONS)[1] == []


def test_without_cameras_or_a_second_person_nothing_is_judged() -> None:
    cams = _ring(6)
    detections = _false_bodies(cams, ["img0.jpg", "img1.jpg", "img3.jpg"])
    cues, association, _ = _associated(detections)
    assert check_visibility(association, cues, {n: _CAMERA for n in cams})[1] == []
    detections += _detect({"A": np.zeros(3)}, cams)
    cues, association, _ = _associated(detections)
    assert check_visibility(association, cues, {})[1] == []


def test_augment_leaves_the_default_domes_false_identity_out(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`make demo`'s scene: a false detection in cam02 and another in cam11, which
    the association links as one person. `augment` leaves both out, says so, and
    the database's run info keeps why for the report; the real person stays."""
    scene = tmp_path / "scene"
    generate("dome", scene, SynthOptions(seed=0, num_people=1, sift=False))
    truth = read_gt_persons(gt_persons_path(scene)).images
    false = {(n, k) for n, ids in truth.items() for k, i in enumerate(ids) if i < 0}
    assert len(false) >= 2  # the scene tests what it says
    db = scene / "database.db"
    assert cli.main(["augment", str(db), "--priors", str(scene / "priors")]) == 0
    printed = capsys.readouterr().out
    assert "left out person" in printed and "not seen where its detections" in printed
    left = database.read_run_info(db)["left_out_people"]
    left_keys = {(k.split(" #")[0], int(k.split(" #")[1])) for k in left}
    assert left_keys and left_keys <= false
    views = database.read_views(db)
    name = dict(zip(views.image_ids.tolist(), views.image_names, strict=True))
    linked = {
        (name[image_id], person)
        for p in database.read_person_associations(db)
        for image_id, person in (
            (p.image_id1, p.person_id1),
            (p.image_id2, p.person_id2),
        )
    }
    assert not linked & false  # no false detection keeps a link
    assert linked  # the real person does
