"""Pair selection (issue 14): k partners per image by predicted view angle."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from colmap_vc.pair_selection import body_frames, predicted_angles, select_pairs
from colmap_vc.structs import ImagePrior, PersonPrior
from colmap_vc.synthetic import bodies as body_lib
from colmap_vc.synthetic.layout import look_at


@pytest.fixture(scope="module")
def ring_priors() -> tuple[dict[str, ImagePrior], np.ndarray]:
    """24 cameras evenly around two people facing different ways; the priors list
    the people in a shuffled order per image (anonymous)."""
    model = body_lib.load_bodies()
    rng = np.random.default_rng(3)
    people = []
    for k, (xy, yaw) in enumerate([((0.0, 0.0), 0.3), ((0.9, 0.2), 2.2)]):
        v = body_lib.pose_body(model, k, k)
        c, s = math.cos(yaw), math.sin(yaw)
        Rz = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
        people.append(v @ Rz.T + np.r_[xy, 0.0])
    azimuth = np.deg2rad(np.arange(24) * 15.0)
    priors = {}
    centres = np.stack(
        [4 * np.cos(azimuth), 4 * np.sin(azimuth), np.full(24, 1.5)], axis=1
    )
    # The true angle between two views, seen from each person's centroid.
    true = []
    for v in people:
        rays = centres - v.mean(axis=0)
        rays /= np.linalg.norm(rays, axis=1, keepdims=True)
        true.append(np.degrees(np.arccos(np.clip(rays @ rays.T, -1, 1))))
    for i, centre in enumerate(centres):
        P = look_at(centre, np.array([0.45, 0.1, 1.0]))
        persons = [
            PersonPrior(vertices_cam=v @ P[:, :3].T + P[:, 3], faces=model.faces)
            for v in people
        ]
        order = rng.permutation(2)
        name = f"cam{i:02d}.jpg"
        priors[name] = ImagePrior(
            image_name=name, persons=tuple(persons[j] for j in order)
        )
    return priors, np.stack(true)


def test_predicted_angle_is_the_angle_between_the_views(ring_priors) -> None:
    priors, true = ring_priors
    names = sorted(priors)
    angles = predicted_angles(body_frames(priors, names), 40.0)
    # The angle seen from one of the two people (they stand 0.9 m apart: up to
    # 20 deg different from 4 m), although every image lists them in its own order
    # and they face 110 deg apart (a wrong person pair predicts a wrong angle).
    assert np.abs(angles - true).min(axis=0).max() < 1.0
    assert np.abs(angles - true[0]).max() > 10.0  # the two people do differ
    assert np.allclose(angles, angles.T)


def test_each_image_keeps_its_nearest_views_and_the_graph_is_connected(
    ring_priors,
) -> None:
    priors, _ = ring_priors
    names = sorted(priors)
    pairs = select_pairs(priors, names, max_partners=4)
    assert len(pairs) == len(set(pairs)) and all(a < b for a, b in pairs)
    # On an even ring, the 4 nearest views are the neighbours 15 and 30 deg away.
    want = {
        tuple(sorted((names[i], names[(i + d) % 24])))
        for i in range(24)
        for d in (1, 2)
    }
    assert set(pairs) == want
    # Every pair, below max_partners + 1 images.
    few = names[:5]
    assert select_pairs(priors, few, max_partners=4) == list(
        itertools.combinations(few, 2)
    )
    assert len(select_pairs(priors, names, None)) == 24 * 23 // 2


def test_components_are_joined(ring_priors) -> None:
    priors, _ = ring_priors
    # Two far groups of views (0-45 deg and 180-225 deg): 1 partner each would give
    # separate components; the selection joins them.
    names = [f"cam{i:02d}.jpg" for i in (0, 1, 2, 3, 12, 13, 14, 15)]
    pairs = select_pairs(priors, names, max_partners=1)
    parent = {n: n for n in names}

    def find(n: str) -> str:
        while parent[n] != n:
            n = parent[n]
        return n

    for a, b in pairs:
        parent[find(a)] = find(b)
    assert len({find(n) for n in names}) == 1
    assert len(pairs) < len(names) * (len(names) - 1) // 2
