"""People association across all views at once (anonymous priors).

A detector's people carry no identity: person 0 of one image may be person 1 of the
next. VCs tolerate large prior errors, so a *wrong* person link (her chest matched to
his) also verifies with many inliers; a pair-by-pair "most inliers" choice is wrong on
a third of real pairs and breaks the cycles (A = B, B = C, but C != A). This module
decides identities jointly from three kinds of evidence:

- **unary, per link** (person a of image i = person b of image j): the link's own VC
  inlier ratio (5-point RANSAC over that person pair alone), the clothing colours of
  torso, upper and lower limbs when the priors carry them (``PersonPrior.appearance``,
  written by the bundled estimator), and the fitted body's height;
- **pairwise, per image pair**: two links of one image pair must describe *one*
  camera motion. Their VC relative poses must agree, and the rigid motion that maps
  one person's mesh onto its partner must also carry the other person onto hers
  (the people's layout). A wrong assignment of two people gives two motions;
- **global**: links are merged strongest first into identities (union-find) that
  never hold two people of one image (cycle consistency by construction).

All evidence is a log-likelihood ratio. Per image pair, link sets are grown greedily
from every seed link (the link that raises the score most joins, while it does); a
link is kept when the best set holding it beats the best set without it by
``min_link_margin``, else that person stays unassociated in that pair (left out, not
guessed; transitivity through other views may still link it). Identities given in
the priors win. Nothing is factorial: a pair with n and m people costs n m link
verifications and O((n m)^3) arithmetic.

The noise scales (degrees, metres, colour units) are the measured noise of the
quantity they scale; each option's docstring says where it comes from, and
docs/real-data.md ("Several people") sums them up.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from .evaluation import pose_disagreement_deg
from .meshalign import procrustes
from .structs import BoolArray, FloatArray

logger = logging.getLogger(__name__)

PersonKey = tuple[str, int]  # (image name, person index in the image's priors)


@dataclass(frozen=True, kw_only=True, slots=True)
class AssociationOptions:
    """Options of the joint people association (log-likelihood ratios)."""

    link_prior: float = 2.0
    """Log-odds that a person seen in both images of a pair is linked there at all
    (people are usually seen by most views): what a link must outweigh in penalties
    before it is left out."""
    pose_sigma_deg: float = 45.0
    """Noise of a one-person VC relative pose (max of rotation and translation-
    direction angle): median 38 deg on one-person synthetic pairs (bench/
    vc_geometry.py), so two links of one pair barely need to agree."""
    layout_sigma_frac: float = 0.25
    """Noise of where one person's mesh alignment carries the other people, as a
    fraction of their distance from the cameras: predicted meshes are 10-20% off in
    depth, and the error combines two meshes (0.5-1.2 m for the right assignment at
    3-5 m on pose2sim_multi)."""
    appearance_sigma: float = 18.0
    """Noise of a body region's median CIELAB colour between two cameras (lighting,
    white balance, shading): 8-bit Lab units."""
    height_sigma_m: float = 0.3
    """Noise of the fitted body's height between two views, metres: it follows the
    prior's scale error (one person's realistic synthetic priors differ by up to
    0.3 m, MediaPipe fits on pose2sim by up to 0.16 m), so height only breaks ties
    between people of clearly different size."""
    pose_range_deg: float = 180.0
    """Where a *wrong* pair of links puts its pose disagreement: anywhere in 0-180
    deg (pose2sim_multi, one right and one wrong link: median 120, 10-90% 54-171).
    With ``pose_sigma_deg`` it makes the pose term a likelihood *ratio*: positive
    for links that agree, negative for links that do not, so a set of many
    consistent links (static cameras: every instant's people) scores higher than
    a set of few, instead of paying a penalty per link."""
    pose_inlier_prob: float = 0.5
    """Probability that two *right* links' VC poses agree to ``pose_sigma_deg``;
    otherwise one of them is a RANSAC failure, spread like a wrong link's. One-person
    VC poses fail often on real photos: on pose2sim_multi two right links disagree
    by a median 77 deg (10-90%: 12-146, close to uniform), on one-person synthetic
    pairs by 38. The mixture bounds what one failed pose costs (log 0.5) instead of
    letting it outweigh appearance and layout."""
    layout_range_frac: float = 1.2
    """The same for the layout error: a wrong pair of links spreads it over about
    0-1.2 of the people's depth (pose2sim_multi: median 0.72, 10-90% 0.27-1.04;
    both links right: median 0.19)."""
    min_link_margin: float = 0.25
    """A link is kept only when the best assignment holding it beats the best one
    without it by this log-likelihood (else the pair abstains for that person)."""
    miss_prob: float = 0.1
    """Least probability that the detector misses a person in view: inside the
    frame, as large as where it was found, overlapped by no one
    (colmap_vc.visibility_check, which measures it on the other people and takes
    the larger). MediaPipe found every such person on pose2sim; the synthetic
    detectors miss 3% (realistic) and 8% (hard) at random, more when small. 0.1
    bounds the random misses."""
    unseen_alpha: float = 0.05
    """A detection places its person where it is not seen when a real person would
    be missed as often with a probability below this (binomial tail at the
    detector's miss rate); an identity is left out when half of its detections
    do. 0: no visibility check."""
    inside_frac: float = 0.9
    """A person is in view of an image when this share of its placed mesh's
    vertices falls inside the frame: a person cut by the frame is often missed."""
    hidden_overlap: float = 0.3
    """...and when no person detected there covers more than this share of its
    placed box (it may be hidden behind them, or be them, placed with the layout
    noise)."""


@dataclass(frozen=True, kw_only=True, slots=True)
class PersonCue:
    """What the association knows of one person in one image."""

    image_name: str
    index: int  # in the image's priors
    person_id: int | None  # the priors' identity, when given
    vertices_cam: FloatArray  # (V, 3) metres, this camera's frame
    appearance: FloatArray | None = None  # (R, 4): Lab colour + weight per region
    group: str = ""  # instant: people of different instants never match ("": any)

    @property
    def key(self) -> PersonKey:
        return (self.image_name, self.index)

    @property
    def height_m(self) -> float:
        """Extent of the mesh along its principal axis (standing height)."""
        v = self.vertices_cam - self.vertices_cam.mean(axis=0)
        axis = np.linalg.svd(v, full_matrices=False)[2][0]
        proj = v @ axis
        return float(proj.max() - proj.min())


@dataclass(frozen=True, kw_only=True, slots=True)
class LinkEvidence:
    """One candidate link between person a of image 1 and person b of image 2."""

    image_name1: str
    image_name2: str
    person1: int
    person2: int
    num_vcs: int
    num_inliers: int  # of the link's own verification
    cam2_from_cam1: FloatArray | None  # (3, 4) from the link's own VCs, unit t

    @property
    def ratio(self) -> float:
        return self.num_inliers / self.num_vcs if self.num_vcs else 0.0


@dataclass(frozen=True, kw_only=True, slots=True)
class Association:
    """Identities of the people, and the links each image pair keeps."""

    identity: dict[PersonKey, int]  # -1: left out (no confident partner anywhere)
    links: dict[tuple[str, str], list[tuple[int, int]]]  # name pair -> (a, b) links
    confidence: dict[tuple[str, str], float]  # per name pair, the hypothesis margin
    method: str = "joint"  # "id" when the priors' identities were used
    abstained: dict[tuple[str, str], str] = field(default_factory=dict)


def appearance_distance(a: FloatArray | None, b: FloatArray | None) -> float:
    """Weighted mean over regions seen in both of |Lab difference| (L halved).

    NaN when either has no appearance or no region in common.
    """
    if a is None or b is None or a.shape != b.shape:
        return math.nan
    w = np.minimum(a[:, 3], b[:, 3])
    if not (w > 0).any():
        return math.nan
    d = a[:, :3] - b[:, :3]
    d[:, 0] *= 0.5  # lightness changes most with lighting, chroma least
    dist = np.linalg.norm(d, axis=1)
    return float((w * dist).sum() / w.sum())


def _unary(
    link: LinkEvidence, c1: PersonCue, c2: PersonCue, options: AssociationOptions
) -> float:
    """Log-likelihood ratio of one link on its own: prior, appearance, height and
    (weakly) whether the link's own VCs verify."""
    score = options.link_prior + math.log((0.25 + link.ratio) / 0.75)
    d_app = appearance_distance(c1.appearance, c2.appearance)
    if math.isfinite(d_app):
        score += 0.5 - 0.5 * (d_app / options.appearance_sigma) ** 2
    d_h = c1.height_m - c2.height_m
    return score - 0.5 * (d_h / options.height_sigma_m) ** 2


@dataclass(frozen=True, slots=True)
class _LinkGeometry:
    """One link's mesh alignment, computed once per link (not per pair of links)."""

    motion: FloatArray | None  # (3, 4) person 1's mesh onto person 2's; None: the
    # two meshes have different topologies
    centre1: FloatArray  # (3,) person 1's mesh centroid, camera 1
    centre2: FloatArray  # (3,) person 2's mesh centroid, camera 2


def _link_geometry(c1: PersonCue, c2: PersonCue) -> _LinkGeometry:
    v1, v2 = c1.vertices_cam, c2.vertices_cam
    return _LinkGeometry(
        motion=procrustes(v1, v2) if len(v1) == len(v2) else None,
        centre1=v1.mean(axis=0),
        centre2=v2.mean(axis=0),
    )


def _layout_error(g1: _LinkGeometry, g2: _LinkGeometry) -> float:
    """Where link 1's mesh alignment puts link 2's person, against its partner (and
    the reverse), as a fraction of the people's mean distance from the cameras."""
    if g1.motion is None or g2.motion is None:
        return math.nan
    depth = np.mean(
        [np.linalg.norm(c) for c in (g1.centre1, g2.centre1, g1.centre2, g2.centre2)]
    )
    errs = [
        float(np.linalg.norm(T[:, :3] @ other.centre1 + T[:, 3] - other.centre2))
        for T, other in ((g1.motion, g2), (g2.motion, g1))
    ]
    return 0.5 * (errs[0] + errs[1]) / max(float(depth), 1e-6)


def _pairwise(
    l1: LinkEvidence,
    l2: LinkEvidence,
    g1: _LinkGeometry,
    g2: _LinkGeometry,
    options: AssociationOptions,
) -> float:
    """Log-likelihood ratio that two non-conflicting links of one pair share one
    motion: a half-normal of the disagreement (both links right) against a uniform
    spread (one of them wrong), for the layout and for the VC poses (these with a
    share of failed poses, ``pose_inlier_prob``)."""
    k = 0.0
    if l1.cam2_from_cam1 is not None and l2.cam2_from_cam1 is not None:
        d = pose_disagreement_deg(l1.cam2_from_cam1, l2.cam2_from_cam1)
        ratio = math.exp(
            _half_normal_vs_uniform(d, options.pose_sigma_deg, options.pose_range_deg)
        )
        w = options.pose_inlier_prob
        k += math.log(w * ratio + (1.0 - w))
    e = _layout_error(g1, g2)
    if math.isfinite(e):
        k += _half_normal_vs_uniform(
            e, options.layout_sigma_frac, options.layout_range_frac
        )
    return k


def _half_normal_vs_uniform(x: float, sigma: float, spread: float) -> float:
    """log of a half-normal(sigma) density over a uniform one on [0, spread], at x."""
    return (
        math.log(2.0 * spread / (math.sqrt(2.0 * math.pi) * sigma))
        - 0.5 * (x / sigma) ** 2
    )


def _conflict(l1: LinkEvidence, l2: LinkEvidence) -> bool:
    return l1.person1 == l2.person1 or l1.person2 == l2.person2


def _hypotheses(
    unary: FloatArray, pairwise: FloatArray, conflict: BoolArray
) -> list[tuple[float, frozenset[int]]]:
    """Greedy link sets, one per seed: add the link that raises the score most.

    score(H) = sum of unary + sum over link pairs of pairwise; polynomial, not a
    search over permutations.
    """
    n = len(unary)
    out: list[tuple[float, frozenset[int]]] = [(0.0, frozenset())]
    for seed in range(n):
        members = [seed]
        score = float(unary[seed])
        while True:
            # (n,) mask; asarray narrows the stub's "np.bool | array" of any(axis=0).
            free = np.asarray(~conflict[members].any(axis=0))
            free[members] = False
            if not free.any():
                break
            gain = unary + pairwise[:, members].sum(axis=1)
            gain[~free] = -np.inf
            best = int(np.argmax(gain))  # first maximum: deterministic
            if gain[best] <= 0:
                break
            members.append(best)
            score += float(gain[best])
        out.append((score, frozenset(members)))
    return out


def _pair_links(
    links: Sequence[LinkEvidence],
    cues: Mapping[PersonKey, PersonCue],
    options: AssociationOptions,
) -> FloatArray:
    """Per link, the margin: best score with it minus best score without it."""
    n = len(links)
    unary = np.array(
        [
            _unary(
                lk,
                cues[(lk.image_name1, lk.person1)],
                cues[(lk.image_name2, lk.person2)],
                options,
            )
            for lk in links
        ]
    )
    geometry = [
        _link_geometry(
            cues[(lk.image_name1, lk.person1)], cues[(lk.image_name2, lk.person2)]
        )
        for lk in links
    ]
    conflict = np.eye(n, dtype=bool)
    pairwise = np.zeros((n, n))
    for i in range(n):  # loop over person links (a few per pair), not matches
        for j in range(i + 1, n):
            if _conflict(links[i], links[j]):
                conflict[i, j] = conflict[j, i] = True
            else:
                pairwise[i, j] = pairwise[j, i] = _pairwise(
                    links[i], links[j], geometry[i], geometry[j], options
                )
    hyps = _hypotheses(unary, pairwise, conflict)
    margin = np.zeros(n)
    for i in range(n):
        with_i = (
            max(s for s, h in hyps if i in h)
            if any(i in h for _, h in hyps)
            else -np.inf
        )
        without = max(s for s, h in hyps if i not in h)
        margin[i] = with_i - without
    return margin


class _Identities:
    """Union-find over people that never joins two people of one image."""

    def __init__(self, keys: Sequence[PersonKey]) -> None:
        self.parent = {k: k for k in keys}
        self.images = {k: {k[0]} for k in keys}

    def find(self, k: PersonKey) -> PersonKey:
        while self.parent[k] != k:
            self.parent[k] = self.parent[self.parent[k]]
            k = self.parent[k]
        return k

    def union(self, a: PersonKey, b: PersonKey) -> bool:
        ra, rb = self.find(a), self.find(b)
        if ra == rb:
            return True
        if self.images[ra] & self.images[rb]:
            return False  # would see one image twice: a broken cycle
        ra, rb = min(ra, rb), max(ra, rb)  # deterministic root
        self.parent[rb] = ra
        self.images[ra] |= self.images.pop(rb)
        return True


def associate(
    cues: Sequence[PersonCue],
    links: Sequence[LinkEvidence],
    options: AssociationOptions | None = None,
) -> Association:
    """Identities of all people of all images, jointly (module doc).

    Args:
        cues: every person of every image.
        links: candidate links (any image pair, name order image_name1 < image_name2),
            with their own verification. Pairs absent here have no candidates.
        options: association options.
    """
    options = options or AssociationOptions()
    by_key = {c.key: c for c in cues}
    keys = sorted(by_key)
    if cues and all(c.person_id is not None for c in cues):
        # The priors' identities win.
        ids = {k: int(by_key[k].person_id) for k in keys}  # type: ignore[arg-type]
        out_links: dict[tuple[str, str], list[tuple[int, int]]] = {}
        names = sorted({c.image_name for c in cues})
        for i, n1 in enumerate(names):
            for n2 in names[i + 1 :]:
                pl = [
                    (a[1], b[1])
                    for a in keys
                    if a[0] == n1
                    for b in keys
                    if b[0] == n2 and ids[a] == ids[b]
                ]
                if pl:
                    out_links[(n1, n2)] = pl
        return Association(
            identity=ids,
            links=out_links,
            confidence={p: math.inf for p in out_links},
            method="id",
        )

    per_pair: dict[tuple[str, str], list[LinkEvidence]] = {}
    for lk in links:
        c1 = by_key[(lk.image_name1, lk.person1)]
        c2 = by_key[(lk.image_name2, lk.person2)]
        if c1.group and c2.group and c1.group != c2.group:
            continue  # people of different instants are different people
        per_pair.setdefault((lk.image_name1, lk.image_name2), []).append(lk)

    chosen: list[tuple[float, tuple[str, str], LinkEvidence]] = []
    confidence: dict[tuple[str, str], float] = {}
    abstained: dict[tuple[str, str], str] = {}
    for pair in sorted(per_pair):
        margin = _pair_links(per_pair[pair], by_key, options)
        kept = margin >= options.min_link_margin
        confidence[pair] = float(margin[kept].min()) if kept.any() else 0.0
        if not kept.any():
            abstained[pair] = (
                f"no person link beats its alternatives by {options.min_link_margin}"
                f" (best margin {margin.max():.2f})"
            )
        for lk, m in zip(per_pair[pair], margin, strict=True):
            if m >= options.min_link_margin:
                chosen.append((float(m), pair, lk))

    # Strongest evidence first; ties by names (never by the database's order).
    chosen.sort(key=lambda c: (-c[0], c[1], c[2].person1, c[2].person2))
    uf = _Identities(keys)
    for _, pair, lk in chosen:
        if not uf.union((pair[0], lk.person1), (pair[1], lk.person2)):
            logger.debug(
                "association: %s #%d = %s #%d contradicts stronger links: dropped",
                pair[0],
                lk.person1,
                pair[1],
                lk.person2,
            )
    roots = sorted({uf.find(k) for k in keys})
    sizes = {r: 0 for r in roots}
    for k in keys:
        sizes[uf.find(k)] += 1
    numbered = {r: i for i, r in enumerate(r for r in roots if sizes[r] > 1)}
    identity = {k: numbered.get(uf.find(k), -1) for k in keys}

    out: dict[tuple[str, str], list[tuple[int, int]]] = {}
    for pair in sorted(per_pair):
        n1, n2 = pair
        pl = sorted(
            {
                (lk.person1, lk.person2)
                for lk in per_pair[pair]
                if identity[(n1, lk.person1)] >= 0
                and identity[(n1, lk.person1)] == identity[(n2, lk.person2)]
            }
        )
        if pl:
            out[pair] = pl
    logger.info(
        "association: %d people in %d images -> %d identities seen in 2+ images; "
        "%d of %d image pairs abstained",
        len(keys),
        len({k[0] for k in keys}),
        len(numbered),
        len(abstained),
        len(per_pair),
    )
    return Association(
        identity=identity,
        links=out,
        confidence=confidence,
        abstained=abstained,
    )
