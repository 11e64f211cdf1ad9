"""Which image pairs get VCs: every pair up to a few dozen images, then k partners.

Linking and verifying every pair grows with the square of the images (a 256-image
scene has 32,640 pairs). Past ``max_partners + 1`` images each image keeps its
``max_partners`` most promising partners, ranked by the angle between the two views
that the people's meshes predict, and whatever links the view graph into one
component is added.

The predicted angle of two views of the same person: each person's mesh is aligned
rigidly (rotation only, Kabsch) to one reference mesh of the same topology, which
puts the direction from the body to the camera in one body frame; the angle between
two such directions is the angle between the views, seen from the person. People
are anonymous, so every person pair of two images is a hypothesis; the one whose
relative rotation the other shared people confirm wins (:func:`predicted_angles`).
VCs of near views share visible surface (more, and more exact,
matches) while wide views still close the loop through the chain of near ones; the
accuracy cost against all pairs is measured in bench/scale.py.
"""

from __future__ import annotations

import itertools
import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from .matching import template_key
from .meshalign import procrustes
from .structs import FloatArray, ImagePrior, IndexArray

logger = logging.getLogger(__name__)

MAX_VERTICES = 500  # an even subsample of each mesh is enough for a rotation


@dataclass(frozen=True, kw_only=True, slots=True)
class BodyFrames:
    """Per image (row) and person (column, padded): the rotation body -> camera of
    each person's mesh against the reference mesh of its topology, and the unit
    direction from the body to the camera in the body frame."""

    rotation: FloatArray  # (N, P, 3, 3)
    to_camera: FloatArray  # (N, P, 3)
    topology: IndexArray  # (N, P), -1 where padded


def body_frames(priors: Mapping[str, ImagePrior], names: Sequence[str]) -> BodyFrames:
    """Kabsch of every person's mesh (an even subsample) to the first mesh of its
    topology, images in the order of ``names``."""
    names = list(names)
    num = max((len(priors[n].persons) for n in names), default=0)
    rotation = np.tile(np.eye(3), (len(names), max(num, 1), 1, 1))
    to_camera = np.zeros((len(names), max(num, 1), 3))
    topology = np.full((len(names), max(num, 1)), -1, np.int64)
    reference: dict[str, FloatArray] = {}
    keys: dict[str, int] = {}
    for i, name in enumerate(names):
        for k, person in enumerate(priors[name].persons):
            v = person.vertices_cam
            rows = np.linspace(0, len(v) - 1, min(len(v), MAX_VERTICES)).astype(int)
            pts = v[rows]
            key = template_key(person)
            ref = reference.setdefault(key, pts)
            if len(ref) != len(pts):
                continue
            T = procrustes(ref, pts)  # body (reference mesh) -> this camera
            direction = T[:, :3].T @ (-pts.mean(axis=0))
            rotation[i, k] = T[:, :3]
            to_camera[i, k] = direction / max(np.linalg.norm(direction), 1e-12)
            topology[i, k] = keys.setdefault(key, len(keys))
    return BodyFrames(rotation=rotation, to_camera=to_camera, topology=topology)


def predicted_angles(frames: BodyFrames, max_disagreement_deg: float) -> FloatArray:
    """(N, N) angle between the views (degrees) that the people predict; 180 where
    two images share no topology.

    Each person pair (a, b) of two images is a hypothesis "a is b", with its
    relative rotation cam2 <- cam1 through the body frame. Right hypotheses agree
    with each other (the same relative rotation from every shared person), wrong
    ones do not: the hypothesis that the most others (other people on both sides)
    agree with within ``max_disagreement_deg`` wins, ties by the smaller angle.
    """
    n, p = frames.topology.shape
    out = np.full((n, n), 180.0)
    R, d, topo = frames.rotation, frames.to_camera, frames.topology
    a_of = np.repeat(np.arange(p), p)  # hypothesis h = (a, b), a in image i
    b_of = np.tile(np.arange(p), p)
    distinct = (a_of[:, None] != a_of[None, :]) & (b_of[:, None] != b_of[None, :])
    cos_tol = math.cos(math.radians(max_disagreement_deg))
    for i in range(n):  # loop over images, vectorized over partners and people
        # H[j, a, b] = R_j[b] R_i[a]^T, the rotation camera i -> camera j.
        H = np.einsum("jbxy,azy->jabxz", R, R[i]).reshape(n, p * p, 3, 3)
        valid = (topo[i][a_of][None, :] == topo[:, b_of]) & (topo[i][a_of] >= 0)
        cos = (np.einsum("jhxy,jkxy->jhk", H, H) - 1.0) / 2.0
        agree = (cos > cos_tol) & distinct & valid[:, :, None] & valid[:, None, :]
        support = agree.sum(axis=2)  # (N, P*P)
        angle = np.degrees(
            np.arccos(
                np.clip(np.einsum("ax,jbx->jab", d[i], d).reshape(n, p * p), -1, 1)
            )
        )
        # Best hypothesis: most support, then the smaller angle.
        score = np.where(valid, support * 1000.0 - angle, -np.inf)
        best = np.argmax(score, axis=1)
        ok = valid.any(axis=1)
        out[i, ok] = angle[np.arange(n), best][ok]
    out = np.minimum(out, out.T)  # the same rule from both sides: symmetric
    np.fill_diagonal(out, 0.0)
    return out


def select_pairs(
    priors: Mapping[str, ImagePrior],
    names: Sequence[str],
    max_partners: int | None,
    max_disagreement_deg: float = 40.0,
) -> list[tuple[str, str]]:
    """Image pairs (name order within and across pairs) to link and verify."""
    names = sorted(names)
    every = list(itertools.combinations(names, 2))
    if max_partners is None or len(names) <= max_partners + 1:
        return every
    angles = predicted_angles(body_frames(priors, names), max_disagreement_deg)
    n = len(names)
    # Each image's partners: smallest predicted angle, ties by name (stable).
    order = np.argsort(angles + np.eye(n) * 1e9, axis=1, kind="stable")
    keep = np.zeros((n, n), dtype=bool)
    rows = np.repeat(np.arange(n), max_partners)
    keep[rows, order[:, :max_partners].ravel()] = True
    keep |= keep.T
    # Whatever joins the components: Kruskal over all pairs by predicted angle.
    parent = np.arange(n)

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = int(parent[i])
        return i

    for i, j in zip(*np.nonzero(np.triu(keep, 1)), strict=True):
        parent[find(int(i))] = find(int(j))
    iu, ju = np.triu_indices(n, 1)
    by_angle = np.lexsort((ju, iu, angles[iu, ju]))
    added = 0
    components = len({find(i) for i in range(n)})
    for i, j in zip(iu[by_angle], ju[by_angle], strict=True):
        if components == 1:
            break
        ri, rj = find(int(i)), find(int(j))
        if ri != rj:
            parent[ri] = rj
            keep[i, j] = keep[j, i] = True
            added += 1
            components -= 1
    out = [
        (names[i], names[j]) for i, j in zip(*np.nonzero(np.triu(keep, 1)), strict=True)
    ]
    logger.info(
        "pair selection: %d of %d pairs (%d partners per image by predicted view "
        "angle, %d to connect the view graph)",
        len(out),
        len(every),
        max_partners,
        added,
    )
    return out
