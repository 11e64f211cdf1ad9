"""Joint people association: identities from appearance, layout and cycles."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from colmap_vc.association import (
    LinkEvidence,
    PersonCue,
    appearance_distance,
    associate,
)
from colmap_vc.evaluation import relative_pose

_RNG = np.random.default_rng(3)
# A body-like point cloud: 1.7 m tall (y down), 0.4 m wide, 0.25 m deep.
_BODY = _RNG.uniform(-0.5, 0.5, (200, 3)) * [0.4, 1.7, 0.25]
_WORLD = {"A": np.array([0.0, 0.0, 0.0]), "B": np.array([1.2, 0.0, 0.3])}
_WHITE = np.array([[200.0, 128, 128, 1]] * 4)
_RED = np.array([[120.0, 170, 150, 1]] * 4)


def _cameras(n: int) -> dict[str, np.ndarray]:
    """cam_from_world (3, 4) of n cameras on a circle of 4 m around the people."""
    out = {}
    for k in range(n):
        yaw = 2 * np.pi * k / n
        R = Rotation.from_euler("y", -yaw).as_matrix()
        centre = np.array([4 * np.sin(yaw) + 0.6, 0.0, 0.15 - 4 * np.cos(yaw)])
        out[f"img{k}.jpg"] = np.c_[R, -R @ centre]
    return out


def _scene(
    num_images: int,
    order: dict[str, tuple[str, ...]] | None = None,
    appearance: bool = True,
) -> tuple[list[PersonCue], list[LinkEvidence], dict[tuple[str, int], str]]:
    """Cues and every candidate link; the truth (image, index) -> person."""
    cams = _cameras(num_images)
    order = order or {}
    cues, truth = [], {}
    for name, T in cams.items():
        for k, who in enumerate(order.get(name, ("A", "B"))):
            pts = _BODY + _WORLD[who]
            cues.append(
                PersonCue(
                    image_name=name,
                    index=k,
                    person_id=None,
                    vertices_cam=pts @ T[:, :3].T + T[:, 3],
                    appearance=(_WHITE if who == "A" else _RED) if appearance else None,
                )
            )
            truth[(name, k)] = who
    links = []
    wrong = Rotation.from_euler("y", 70, degrees=True).as_matrix()
    for c1, c2 in itertools.product(cues, cues):
        if c1.image_name >= c2.image_name:
            continue
        pose = relative_pose(cams[c1.image_name], cams[c2.image_name])
        pose[:, 3] /= np.linalg.norm(pose[:, 3])
        same = truth[c1.key] == truth[c2.key]
        # Wrong links verify too (VCs tolerate prior errors), with another pose.
        links.append(
            LinkEvidence(
                image_name1=c1.image_name,
                image_name2=c2.image_name,
                person1=c1.index,
                person2=c2.index,
                num_vcs=400,
                num_inliers=340 if same else 330,
                cam2_from_cam1=pose if same else np.c_[wrong @ pose[:, :3], pose[:, 3]],
            )
        )
    return cues, links, truth


def _check(result, truth) -> int:
    """Every kept identity holds one true person; returns the number linked."""
    by_identity: dict[int, set[str]] = {}
    for key, ident in result.identity.items():
        if ident >= 0:
            by_identity.setdefault(ident, set()).add(truth[key])
    assert all(len(v) == 1 for v in by_identity.values()), by_identity
    for (n1, n2), links in result.links.items():
        for a, b in links:
            assert truth[(n1, a)] == truth[(n2, b)]
    return sum(ident >= 0 for ident in result.identity.values())


def test_anonymous_people_in_shuffled_order_are_associated_consistently() -> None:
    order = {"img1.jpg": ("B", "A"), "img3.jpg": ("B", "A")}
    cues, links, truth = _scene(5, order)
    result = associate(cues, links)
    assert _check(result, truth) == len(cues)
    assert len(set(result.identity.values())) == 2


def test_layout_alone_separates_look_alikes() -> None:
    """Dressed alike: the mesh layout (who stands where) decides."""
    cues, links, truth = _scene(4, {"img2.jpg": ("B", "A")}, appearance=False)
    result = associate(cues, links)
    assert _check(result, truth) == len(cues)


def test_a_person_missing_in_some_views_and_a_bystander() -> None:
    order = {"img1.jpg": ("A",), "img2.jpg": ("B", "A"), "img4.jpg": ("B",)}
    cues, links, truth = _scene(5, order)
    result = associate(cues, links)
    assert _check(result, truth) == len(cues)


def test_ambiguous_people_are_left_out_not_guessed() -> None:
    """Two look-alikes standing in one place (overlapping in every view): no cue
    tells them apart, so no link between them may be kept."""
    cues, links, _ = _scene(3, appearance=False)
    overlapping = [
        PersonCue(
            image_name=c.image_name,
            index=c.index,
            person_id=None,
            vertices_cam=cues[2 * (i // 2)].vertices_cam,  # both where person 0 is
        )
        for i, c in enumerate(cues)
    ]
    same = [
        LinkEvidence(
            image_name1=lk.image_name1,
            image_name2=lk.image_name2,
            person1=lk.person1,
            person2=lk.person2,
            num_vcs=400,
            num_inliers=340,
            cam2_from_cam1=None,
        )
        for lk in links
    ]
    result = associate(overlapping, same)
    assert result.links == {}
    assert set(result.identity.values()) == {-1}
    assert len(result.abstained) == 3


def test_one_person_per_image_is_one_person() -> None:
    cues, links, truth = _scene(4, {f"img{k}.jpg": ("A",) for k in range(4)})
    assert _check(associate(cues, links), truth) == 4


def test_ids_in_the_priors_win() -> None:
    cues, links, truth = _scene(3)
    with_ids = [
        PersonCue(
            image_name=c.image_name,
            index=c.index,
            person_id=0 if truth[c.key] == "B" else 1,  # whatever the geometry says
            vertices_cam=c.vertices_cam,
        )
        for c in cues
    ]
    result = associate(with_ids, links)
    assert result.method == "id"
    assert all(
        result.identity[c.key] == (0 if truth[c.key] == "B" else 1) for c in with_ids
    )


def test_people_of_different_groups_never_match() -> None:
    cues, links, _ = _scene(3)
    grouped = [
        PersonCue(
            image_name=c.image_name,
            index=c.index,
            person_id=None,
            vertices_cam=c.vertices_cam,
            appearance=c.appearance,
            group=c.image_name,  # every image its own instant
        )
        for c in cues
    ]
    assert associate(grouped, links).links == {}


@pytest.mark.parametrize(
    ("a", "b", "expected"),
    [
        (_WHITE, _WHITE, 0.0),
        (_WHITE, np.c_[_WHITE[:, :3] + [20, 0, 0], _WHITE[:, 3:]], 10.0),
        (_WHITE, np.c_[_WHITE[:, :3], np.zeros((4, 1))], np.nan),
        (None, _WHITE, np.nan),
    ],
)
def test_appearance_distance(a, b, expected) -> None:
    d = appearance_distance(a, b)
    if np.isnan(expected):
        assert np.isnan(d)
    else:
        assert d == pytest.approx(expected)


def test_static_cameras_many_instants_link_everyone() -> None:
    """Static cameras: one view per camera holds the people of every instant, so a
    pair has one link per person and instant (here 12). The links of real photos
    give VC poses 40-120 deg apart even when right (pose2sim_multi); a set of many
    consistent links must still beat a set of few (the pairwise terms are
    likelihood ratios, not penalties per link)."""
    rng = np.random.default_rng(0)
    cams = _cameras(3)
    instants = 6
    cues, truth = [], {}
    for name, T in cams.items():
        for t in range(instants):
            for who in ("A", "B"):
                pts = _BODY + _WORLD[who] + rng.normal(0.0, 0.1, 3)  # moves a little
                key = (name, 2 * t + (who == "B"))
                cues.append(
                    PersonCue(
                        image_name=name,
                        index=key[1],
                        person_id=None,
                        vertices_cam=pts @ T[:, :3].T + T[:, 3],
                        appearance=_WHITE if who == "A" else _RED,
                        group=f"t{t}",
                    )
                )
                truth[key] = who
    links = []
    for c1, c2 in itertools.product(cues, cues):
        if c1.image_name >= c2.image_name or c1.group != c2.group:
            continue
        pose = relative_pose(cams[c1.image_name], cams[c2.image_name])
        noise = Rotation.from_rotvec(
            rng.normal(size=3) / np.sqrt(3) * np.radians(rng.uniform(40, 120))
        ).as_matrix()
        links.append(
            LinkEvidence(
                image_name1=c1.image_name,
                image_name2=c2.image_name,
                person1=c1.index,
                person2=c2.index,
                num_vcs=400,
                num_inliers=340 if truth[c1.key] == truth[c2.key] else 330,
                cam2_from_cam1=np.c_[noise @ pose[:, :3], pose[:, 3]],
            )
        )
    result = associate(cues, links)
    assert _check(result, truth) == len(cues)
    assert len(set(result.identity.values())) == 2 * instants
