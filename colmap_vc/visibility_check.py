"""Visibility check of the associated people: a person is where the detector looks.

The association links people pair by pair, and a *false* detection (a body that is
not there) can be linked across images too: its VCs verify with any partner (VCs
tolerate large prior errors), two false bodies in front of two neighbouring
cameras can sit where one person would, and the link prior outweighs a moderate
layout error. Transitivity then chains such links into one "person" over several
images, whose keypoint tracks pull cameras to wrong poses.

What a real person does that a false one does not: it is seen wherever it is in
view. Each detection of an identity X says where X is; another identity R, seen
in most of X's images, carries that place into the other images R is seen in:
R's meshes in image i and j give the motion camera j <- camera i
(:func:`colmap_vc.meshalign.procrustes`), which moves X's mesh of image i into
camera j. X is *in view* there when that mesh lies inside the frame
(``inside_frac`` of its vertices), is no smaller than X was found anywhere (up to
the layout noise), and is apart from every other person found in j (an overlap may
hide it); an image with a detection left unlinked is not judged (that may be X).
A real person in view is missed with a small probability; a body that is not
there is missed wherever a detection of it places it. The probability is the
other identities' share of misses in view (leave one out), or ``miss_prob`` if
that is smaller: a detector that misses small or far people often makes a real
person's misses likely, and the test says so. Each detection i gets the binomial
tail, for a real person, of the images that should show its person and do not (k
of the n in view, its own image included). An identity is left out, all its
detections unlinked, when at least half of its detections have a tail below
``unseen_alpha``. A real person's detections agree on where it is, and a real
miss (a person hidden behind something that is not a person) counts against
them as often as the detector's miss rate allows; a false identity's detections
are scattered in space, and each puts it in view of other images. Not every
false detection shows it: one in front of the real person places its partners
behind that person. Half, not all: two of three is already a false identity, and
one is not (a single bad mesh of a real person).
Identities the priors give are kept as given.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Mapping, Sequence

import numpy as np
import pycolmap

from .association import Association, AssociationOptions, PersonCue, PersonKey
from .meshalign import procrustes
from .structs import FloatArray

logger = logging.getLogger(__name__)


def binomial_tail(k: int, n: int, p: float) -> float:
    """P(K >= k) for K ~ Binomial(n, p)."""
    return float(
        sum(math.comb(n, i) * p**i * (1.0 - p) ** (n - i) for i in range(k, n + 1))
    )


def _box(camera: pycolmap.Camera, vertices_cam: FloatArray) -> tuple[FloatArray, float]:
    """Bounding box (x0, y0, x1, y1) of the vertices in front of the camera, and the
    fraction of all vertices that project inside the frame."""
    front = vertices_cam[:, 2] > 1e-3
    if not front.any():
        return np.zeros(4), 0.0
    xy = np.asarray(
        camera.img_from_cam(vertices_cam[front], check_cheirality=False), dtype=float
    )
    inside = (
        (xy[:, 0] >= 0)
        & (xy[:, 0] < camera.width)
        & (xy[:, 1] >= 0)
        & (xy[:, 1] < camera.height)
    )
    return np.r_[xy.min(axis=0), xy.max(axis=0)], float(inside.sum()) / len(front)


def _height(box: FloatArray) -> float:
    return float(box[3] - box[1])


def _overlap(box: FloatArray, other: FloatArray) -> float:
    """Area of ``box`` that ``other`` covers, as a fraction of ``box``'s."""
    w = min(box[2], other[2]) - max(box[0], other[0])
    h = min(box[3], other[3]) - max(box[1], other[1])
    area = (box[2] - box[0]) * (box[3] - box[1])
    return float(max(w, 0.0) * max(h, 0.0) / area) if area > 0 else 0.0


@dataclasses.dataclass(frozen=True, kw_only=True, slots=True)
class DetectionVisibility:
    """Where one detection of an identity places its person."""

    key: PersonKey  # (image name, person index) of the detection
    missed: tuple[str, ...]  # images that should show its person and do not
    in_view: int  # images that should show it, its own included
    tail: float  # binomial tail of that many misses for a real person

    @property
    def reason(self) -> str:
        return (
            f"not found in {len(self.missed)} of the {self.in_view - 1} other images "
            f"it is in view of ({', '.join(self.missed) or '-'}, P = {self.tail:.1e})"
        )


@dataclasses.dataclass(frozen=True, kw_only=True, slots=True)
class UnseenPerson:
    """An identity left out: most of its detections place it where it is not seen."""

    identity: int  # as the association numbered it
    detections: tuple[DetectionVisibility, ...]  # each judged detection
    miss_prob: float  # the detector's miss rate the tails assume

    @property
    def reason(self) -> str:
        parts = [f"{d.key[0]} #{d.key[1]} {d.reason}" for d in self.detections]
        return (
            f"not seen where its detections place it in view (a real person is "
            f"missed there with p = {self.miss_prob:.2f}): {'; '.join(parts)}"
        )


def _unseen(
    i: str,
    members: Mapping[str, PersonKey],
    reference: Mapping[str, PersonKey],
    cues: Mapping[PersonKey, PersonCue],
    cameras: Mapping[str, pycolmap.Camera],
    boxes: Mapping[str, Mapping[PersonKey, FloatArray]],
    unlinked: set[str],
    options: AssociationOptions,
) -> tuple[list[str], int]:
    """Where the detection of ``members`` in image i places its person in view
    (module doc): the images that do not show it, and how many should."""
    own_height = min(_height(boxes[n][k]) for n, k in members.items())
    ref_i = cues[reference[i]].vertices_cam
    missed, in_view = [], 1  # its own image shows it
    for j in sorted(set(reference) - {i}):
        ref_j = cues[reference[j]].vertices_cam
        if j not in cameras or len(ref_i) != len(ref_j):
            continue
        if j not in members and j in unlinked:
            continue  # a detection left unlinked there may be this person
        T = procrustes(ref_i, ref_j)
        box, inside = _box(
            cameras[j], cues[members[i]].vertices_cam @ T[:, :3].T + T[:, 3]
        )
        if (
            inside >= options.inside_frac
            and _height(box) >= (1.0 - options.layout_sigma_frac) * own_height
            and all(
                _overlap(box, other) <= options.hidden_overlap
                for k, other in boxes[j].items()
                if k != members.get(j)
            )
        ):
            in_view += 1
            if j not in members:
                missed.append(j)
    return missed, in_view


def check_visibility(
    association: Association,
    cues: Sequence[PersonCue],
    cameras: Mapping[str, pycolmap.Camera],
    options: AssociationOptions | None = None,
) -> tuple[Association, list[UnseenPerson]]:
    """``association`` without the identities that are not seen where their
    detections place them (module doc), and those identities. Each identity is
    placed by the identity that shares most images with it."""
    options = options or AssociationOptions()
    if association.method == "id":
        return association, []  # the priors' identities win
    people: dict[int, dict[str, PersonKey]] = {}
    for key in sorted(association.identity):
        ident = association.identity[key]
        if ident >= 0:
            people.setdefault(ident, {})[key[0]] = key
    unlinked = {k[0] for k, v in association.identity.items() if v < 0}
    boxes: dict[str, dict[PersonKey, FloatArray]] = {}
    for c in sorted(cues, key=lambda c: c.key):
        if c.image_name in cameras:
            boxes.setdefault(c.image_name, {})[c.key] = _box(
                cameras[c.image_name], c.vertices_cam
            )[0]
    by_key = {c.key: c for c in cues}
    order = sorted(people, key=lambda x: (-len(people[x]), x))
    placed: dict[int, list[tuple[PersonKey, list[str], int]]] = {}
    for x in order:
        members = people[x]
        if any(n not in cameras for n in members):
            continue
        shared = {r: len(set(people[r]) & set(members)) for r in order if r != x}
        if not shared or max(shared.values()) == 0:
            continue
        ref = people[max(shared, key=lambda r: (shared[r], -r))]
        placed[x] = [
            (
                members[i],
                *_unseen(i, members, ref, by_key, cameras, boxes, unlinked, options),
            )
            for i in sorted(set(members) & set(ref))
        ]
    # The detector's miss rate, measured on the other people (leave one out): a
    # detector that misses small or far people often (the synthetic `hard` level)
    # makes a real person's misses likely, and the test says so.
    missed = {x: sum(len(m) for _, m, _ in v) for x, v in placed.items()}
    in_view = {x: sum(n - 1 for _, _, n in v) for x, v in placed.items()}
    left_out: list[UnseenPerson] = []
    for x, detections in placed.items():
        others = sum(in_view.values()) - in_view[x]
        rate = (sum(missed.values()) - missed[x]) / others if others else 0.0
        p = max(options.miss_prob, rate)
        judged = tuple(
            DetectionVisibility(
                key=key,
                missed=tuple(m),
                in_view=n,
                tail=binomial_tail(len(m), n, p),
            )
            for key, m, n in detections
        )
        failed = sum(d.tail < options.unseen_alpha for d in judged)
        if failed and 2 * failed >= len(judged):
            left_out.append(UnseenPerson(identity=x, detections=judged, miss_prob=p))
            logger.info(
                "visibility check: person %d left out, %s", x, left_out[-1].reason
            )
    if not left_out:
        return association, []
    gone = {u.identity for u in left_out}
    kept = sorted({v for v in association.identity.values() if v >= 0} - gone)
    number = {v: i for i, v in enumerate(kept)}  # identities stay 0..n-1
    identity = {k: number.get(v, -1) for k, v in association.identity.items()}
    links = {
        pair: kept_links
        for pair, pl in association.links.items()
        if (kept_links := [(a, b) for a, b in pl if identity[(pair[0], a)] >= 0])
    }
    return dataclasses.replace(association, identity=identity, links=links), left_out
