"""`colmap-vc augment`: priors -> VC matching -> verification -> the COLMAP database.

:func:`compute_virtual_correspondences` is the pure stage (no I/O) usable inside any
pycolmap workflow; :func:`run` reads the database and priors, calls it and writes the
result in one transaction (or only reports, with ``dry_run``).
"""

from __future__ import annotations

import itertools
import logging
import time
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import pycolmap
from tqdm import tqdm

from . import __version__, database, raycast
from .matching import (
    MatchingOptions,
    PersonMatches,
    PersonObservations,
    TemplateSamples,
    match_persons,
    observe_person,
    refit_image_prior,
    sample_template,
    template_key,
)
from .priors import read_priors
from .structs import (
    FloatArray,
    HitKind,
    IndexArray,
    PairGeometry,
    PairVcMatches,
    ScenePriors,
    VcKeypoints,
)
from .verification import Verification, VerificationOptions, verify_pair

logger = logging.getLogger(__name__)

Pair = tuple[int, int]


@dataclass(frozen=True, kw_only=True, slots=True)
class AugmentOptions:
    """Options of `colmap-vc augment`."""

    matching: MatchingOptions = field(default_factory=MatchingOptions)
    """How VCs are found."""
    verification: VerificationOptions = field(default_factory=VerificationOptions)
    """How VCs are verified."""
    use_classic_matches: bool = True
    """Verify jointly with the pair's classic matches where there are any."""
    min_num_vcs: int = 15
    """Pairs with fewer candidate VCs are skipped."""
    max_classic_inliers: int = 100
    """Pairs whose classic two-view geometry already has this many inliers get no
    VCs: SIFT is far more precise than any human prior where views overlap (0: add
    VCs to every pair)."""
    dry_run: bool = False
    """Compute and report, write nothing."""
    show_progress: bool = True
    """Progress bar on stderr."""


@dataclass(frozen=True, kw_only=True, slots=True)
class PairReport:
    """Per-pair line of the summary."""

    image_name1: str
    image_name2: str
    num_vcs: int
    num_inliers: int
    num_classic: int
    num_classic_inliers: int
    num_by_kind: dict[str, int]
    association: list[tuple[int, int]]  # (person index 1, person index 2)
    association_method: str
    verified: bool

    @property
    def inlier_ratio(self) -> float:
        """VC inliers / VCs."""
        return self.num_inliers / self.num_vcs if self.num_vcs else 0.0


@dataclass(frozen=True, kw_only=True, slots=True)
class VirtualCorrespondences:
    """Output of :func:`compute_virtual_correspondences` (what gets written)."""

    keypoints: list[VcKeypoints]
    pairs: list[PairVcMatches]
    geometries: dict[Pair, PairGeometry]
    classic_inliers: dict[Pair, IndexArray]
    associations: list[database.PersonAssociation]
    reports: list[PairReport]
    skipped_images: dict[str, str]  # image name -> reason


@dataclass(frozen=True, kw_only=True, slots=True)
class AugmentSummary:
    """What `augment` did."""

    database_path: Path
    dry_run: bool
    num_images: int
    num_images_with_priors: int
    skipped_images: dict[str, str]
    pairs: list[PairReport]
    timings_s: dict[str, float]
    write: database.WriteSummary | None

    @property
    def num_verified_pairs(self) -> int:
        """Pairs that got a verified two-view geometry."""
        return sum(p.verified for p in self.pairs)


def _template_samples(
    priors: ScenePriors, num_samples: int
) -> dict[str, TemplateSamples]:
    """Samples per topology, from the first mesh of it (images in name order)."""
    out: dict[str, TemplateSamples] = {}
    for name in sorted(priors.images):
        for person in priors.images[name].persons:
            key = template_key(person)
            if key not in out:
                out[key] = sample_template(
                    person.vertices_cam, person.faces, key, num_samples
                )
    return out


def observe_image(
    priors: ScenePriors,
    image_name: str,
    camera: pycolmap.Camera,
    samples: Mapping[str, TemplateSamples],
    options: MatchingOptions,
) -> list[PersonObservations]:
    """Observations of every person of one image."""
    prior = refit_image_prior(priors.images[image_name], camera, options)
    others = None
    if len(prior.persons) > 1 and options.people_occlude:
        others = raycast.build_scene([(p.vertices_cam, p.faces) for p in prior.persons])
    return [
        observe_person(prior, k, camera, samples[template_key(p)], options, others)
        for k, p in enumerate(prior.persons)
    ]


def _assignments(n1: int, n2: int) -> list[list[tuple[int, int]]]:
    """All injective assignments of min(n1, n2) people between two images."""
    if n1 <= n2:
        return [
            list(zip(range(n1), perm, strict=True))
            for perm in itertools.permutations(range(n2), n1)
        ]
    return [
        list(zip(perm, range(n2), strict=True))
        for perm in itertools.permutations(range(n1), n2)
    ]


def _concat(matches: list[tuple[int, int, PersonMatches]]) -> tuple[IndexArray, ...]:
    """(person 1, row 1, person 2, row 2, kind, track) of the concatenated matches."""
    if not matches:
        z = np.zeros(0, np.int64)
        return z, z, z, z, z, z
    return tuple(
        np.concatenate(parts)
        for parts in zip(
            *[
                (
                    np.full(len(m), k1),
                    m.idx1,
                    np.full(len(m), k2),
                    m.idx2,
                    m.kind,
                    m.track_id,
                )
                for k1, k2, m in matches
            ],
            strict=True,
        )
    )


def _gather(
    obs: list[PersonObservations], person: IndexArray, row: IndexArray, attr: str
) -> FloatArray:
    """Rows ``row`` of attribute ``attr`` of the observations of people ``person``."""
    first = getattr(obs[0], attr) if obs else np.zeros((0, 2))
    out = np.zeros((len(row), *first.shape[1:]))
    for k in range(len(obs)):  # loop over people, vectorized over matches
        sel = person == k
        out[sel] = getattr(obs[k], attr)[row[sel]]
    return out


def _codes(person: IndexArray, row: IndexArray) -> IndexArray:
    """One int64 per (person, observation row)."""
    return person.astype(np.int64) * (1 << 32) + row.astype(np.int64)


def _thickness(
    x1: FloatArray,
    x2: FloatArray,
    p1: FloatArray,
    p2: FloatArray,
    geometry: PairGeometry | None,
) -> tuple[FloatArray, FloatArray]:
    """Initial (a, b) with X2 = X1 + a (X1 - o1) + b (o2 - o1), in camera 1's frame.

    The relative pose fixes directions; its scale comes from the meshes (the
    meeting points ``p1``/``p2`` should coincide). NaN first hits give a = b = 0.
    """
    a, b = np.zeros(len(x1)), np.zeros(len(x1))
    if geometry is None or len(x1) == 0:
        return a, b
    R, t = geometry.cam2_from_cam1[:, :3], geometry.cam2_from_cam1[:, 3]
    c = -R.T @ t  # camera 2's centre in camera 1 (unit baseline)
    # S1 = R^T S2 + s c for the meeting point S seen in both frames.
    scale = np.nanmedian((p1 - p2 @ R) @ c)
    scale = float(scale) if np.isfinite(scale) and scale > 0 else 1.0
    o2 = scale * c
    x2_in_1 = (x2 - scale * t) @ R  # R^T (X2 - s t)
    # Least squares of [X1 | o2] (a, b)^T = X2 - X1, one 3x2 system per VC.
    A = np.stack([x1, np.broadcast_to(o2, x1.shape)], axis=2)  # (M, 3, 2)
    rhs = x2_in_1 - x1
    AtA = np.einsum("mki,mkj->mij", A, A)
    Atb = np.einsum("mki,mk->mi", A, rhs)
    ok = np.isfinite(AtA).all(axis=(1, 2)) & np.isfinite(Atb).all(axis=1)
    ok &= np.abs(np.linalg.det(np.where(ok[:, None, None], AtA, np.eye(2)))) > 1e-12
    sol = np.zeros((len(x1), 2))
    if ok.any():
        sol[ok] = np.linalg.solve(AtA[ok], Atb[ok][..., None])[..., 0]
    return sol[:, 0], sol[:, 1]


def _associate_and_verify(
    obs1: list[PersonObservations],
    obs2: list[PersonObservations],
    cam1: pycolmap.Camera,
    cam2: pycolmap.Camera,
    classic_xy1: FloatArray | None,
    classic_xy2: FloatArray | None,
    options: AugmentOptions,
) -> tuple[Verification, tuple[IndexArray, ...], list[tuple[int, int]], str] | None:
    """People association of one pair (ids, else the most consistent assignment) and
    the verification of its VCs -> (verification, VCs, assignment, method), or None.
    """
    cache: dict[tuple[int, int], PersonMatches] = {}

    def matches_of(assignment: list[tuple[int, int]]) -> tuple[IndexArray, ...]:
        for k1, k2 in assignment:
            if (k1, k2) not in cache:
                cache[(k1, k2)] = match_persons(obs1[k1], obs2[k2])
        return _concat([(k1, k2, cache[(k1, k2)]) for k1, k2 in assignment])

    def verify(cat: tuple[IndexArray, ...]) -> Verification:
        xy1 = _gather(obs1, cat[0], cat[1], "xy_img")
        xy2 = _gather(obs2, cat[2], cat[3], "xy_img")
        return verify_pair(
            cam1, cam2, xy1, xy2, classic_xy1, classic_xy2, options.verification
        )

    ids1 = [o.person_id for o in obs1]
    ids2 = [o.person_id for o in obs2]
    if all(i >= 0 for i in ids1 + ids2):
        assignment = [
            (a, b)
            for a, b in itertools.product(range(len(obs1)), range(len(obs2)))
            if ids1[a] == ids2[b]
        ]
        cat = matches_of(assignment)
        if len(cat[0]) < options.min_num_vcs:
            return None
        return verify(cat), cat, assignment, "id"
    best = None
    for candidate in _assignments(len(obs1), len(obs2)):
        cat = matches_of(candidate)
        if len(cat[0]) < options.min_num_vcs:
            continue
        result = verify(cat)
        if best is None or result.num_inliers > best[0].num_inliers:
            best = (result, cat, candidate, "geometric")
    return best


def compute_virtual_correspondences(
    views: database.DatabaseViews,
    priors: ScenePriors,
    options: AugmentOptions | None = None,
    classic_keypoints: Mapping[int, FloatArray] | None = None,
    classic_matches: Mapping[Pair, IndexArray] | None = None,
    timings: dict[str, float] | None = None,
    solved_pairs: set[Pair] | None = None,
) -> VirtualCorrespondences:
    """Find, associate and verify VCs for every pair of images with priors.

    Args:
        views: images and cameras (from :func:`database.read_views`).
        priors: the human priors, by image name.
        options: augment options.
        classic_keypoints: classic keypoints (N, 2) by image id, for joint verification.
        classic_matches: raw classic matches (M, 2) by pair (id1 < id2).
        timings: filled with seconds per stage when given.
        solved_pairs: pairs (id1 < id2) classic matching already solved: no VCs.
    """
    options = options or AugmentOptions()
    timings = timings if timings is not None else {}
    classic_keypoints = classic_keypoints or {}
    classic_matches = classic_matches or {}
    name_to_idx = {n: i for i, n in enumerate(views.image_names)}
    skipped = {
        n: "no priors for this image"
        for n in views.image_names
        if n not in priors.images
    }
    skipped.update(
        {
            n: "no person in the priors"
            for n, p in priors.images.items()
            if not p.persons
        }
    )
    names = [
        n for n in views.image_names if n in priors.images and priors.images[n].persons
    ]

    t0 = time.perf_counter()
    samples = _template_samples(priors, options.matching.num_samples)
    observations: dict[str, list[PersonObservations]] = {}
    for name in tqdm(
        names, desc="observe", disable=not options.show_progress, leave=False
    ):
        i = name_to_idx[name]
        camera = views.cameras[int(views.camera_ids[i])]
        observations[name] = observe_image(
            priors, name, camera, samples, options.matching
        )
    timings["observe"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    used: dict[str, list[IndexArray]] = {n: [] for n in names}
    candidates: list[
        tuple[
            str,
            str,
            Verification,
            tuple[IndexArray, ...],
            list[tuple[int, int]],
            str,
            int,
        ]
    ] = []
    name_pairs = list(itertools.combinations(names, 2))
    for n1, n2 in tqdm(
        name_pairs, desc="match+verify", disable=not options.show_progress, leave=False
    ):
        i1, i2 = name_to_idx[n1], name_to_idx[n2]
        id1, id2 = int(views.image_ids[i1]), int(views.image_ids[i2])
        if id1 > id2:
            n1, n2, i1, i2, id1, id2 = n2, n1, i2, i1, id2, id1
        if solved_pairs and (id1, id2) in solved_pairs:
            continue
        obs1, obs2 = observations[n1], observations[n2]
        cam1 = views.cameras[int(views.camera_ids[i1])]
        cam2 = views.cameras[int(views.camera_ids[i2])]
        cm = (
            classic_matches.get((id1, id2), np.zeros((0, 2), np.int64))
            if options.use_classic_matches
            else np.zeros((0, 2), np.int64)
        )
        cxy1 = classic_keypoints[id1][cm[:, 0]] if len(cm) else None
        cxy2 = classic_keypoints[id2][cm[:, 1]] if len(cm) else None
        matched = _associate_and_verify(obs1, obs2, cam1, cam2, cxy1, cxy2, options)
        if matched is None:
            continue
        result, cat, assignment, method = matched
        if len(cat[0]) == 0:
            continue
        used[n1].append(_codes(cat[0], cat[1]))
        used[n2].append(_codes(cat[2], cat[3]))
        candidates.append((n1, n2, result, cat, assignment, method, len(cm)))
    timings["match_verify"] = time.perf_counter() - t0

    # VC keypoints per image: every observation some pair uses, grouped by person.
    t0 = time.perf_counter()
    keypoints: list[VcKeypoints] = []
    codes_of: dict[str, IndexArray] = {}
    for name in names:
        if not used[name]:
            continue
        codes = np.unique(np.concatenate(used[name]))
        codes_of[name] = codes
        obs = observations[name]
        person, row = codes >> 32, codes & 0xFFFFFFFF
        pid_of = np.array(
            [o.person_id if o.person_id >= 0 else k for k, o in enumerate(obs)],
            np.int64,
        )
        keypoints.append(
            VcKeypoints(
                image_id=int(views.image_ids[name_to_idx[name]]),
                xy_img=_gather(obs, person, row, "xy_img"),
                person_id=pid_of[person],
                track_id=_gather(obs, person, row, "track_id").astype(np.int64),
            )
        )

    pairs: list[PairVcMatches] = []
    geometries: dict[Pair, PairGeometry] = {}
    classic_inliers: dict[Pair, IndexArray] = {}
    associations: list[database.PersonAssociation] = []
    reports: list[PairReport] = []
    for n1, n2, result, cat, assignment, method, num_classic in candidates:
        id1 = int(views.image_ids[name_to_idx[n1]])
        id2 = int(views.image_ids[name_to_idx[n2]])
        k1, r1, k2, r2, kind, _ = cat
        obs1, obs2 = observations[n1], observations[n2]
        idx1 = np.searchsorted(codes_of[n1], _codes(k1, r1))
        idx2 = np.searchsorted(codes_of[n2], _codes(k2, r2))
        x1 = _gather(obs1, k1, r1, "first_hit_cam")
        p1 = _gather(obs1, k1, r1, "point_cam")
        x2 = _gather(obs2, k2, r2, "first_hit_cam")
        p2 = _gather(obs2, k2, r2, "point_cam")
        pid_of = np.array(
            [o.person_id if o.person_id >= 0 else k for k, o in enumerate(obs1)],
            np.int64,
        )
        pid = pid_of[k1]
        a, b = _thickness(x1, x2, p1, p2, result.geometry)
        pairs.append(
            PairVcMatches(
                image_id1=id1,
                image_id2=id2,
                idx1=idx1,
                idx2=idx2,
                person_id=pid,
                kind=kind,
                points1_cam=np.nan_to_num(x1, nan=0.0),
                points2_cam=np.nan_to_num(x2, nan=0.0),
                a=a,
                b=b,
                is_inlier=result.vc_is_inlier,
            )
        )
        if result.geometry is not None:
            geometries[(id1, id2)] = result.geometry
            if options.use_classic_matches and num_classic:
                cm = classic_matches[(id1, id2)]
                classic_inliers[(id1, id2)] = cm[result.classic_is_inlier]
        for a_k, b_k in assignment:
            associations.append(
                database.PersonAssociation(
                    image_id1=id1,
                    image_id2=id2,
                    person_id1=obs1[a_k].person_id if obs1[a_k].person_id >= 0 else a_k,
                    person_id2=obs2[b_k].person_id if obs2[b_k].person_id >= 0 else b_k,
                    method=database.AssociationMethod(method),
                    score=float(result.num_inliers),
                )
            )
        reports.append(
            PairReport(
                image_name1=n1,
                image_name2=n2,
                num_vcs=len(kind),
                num_inliers=int(result.vc_is_inlier.sum()),
                num_classic=num_classic,
                num_classic_inliers=int(result.classic_is_inlier.sum()),
                num_by_kind={h.name.lower(): int((kind == h).sum()) for h in HitKind},
                association=[(int(a_), int(b_)) for a_, b_ in assignment],
                association_method=method,
                verified=result.geometry is not None,
            )
        )
    timings["assemble"] = time.perf_counter() - t0
    return VirtualCorrespondences(
        keypoints=keypoints,
        pairs=pairs,
        geometries=geometries,
        classic_inliers=classic_inliers,
        associations=associations,
        reports=reports,
        skipped_images=skipped,
    )


def run(
    database_path: Path, priors_path: Path, options: AugmentOptions | None = None
) -> AugmentSummary:
    """Augment a COLMAP database with VCs from priors (one transaction)."""
    options = options or AugmentOptions()
    database_path = Path(database_path)
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    views = database.read_views(database_path)
    sizes = {
        name: (views.cameras[int(c)].width, views.cameras[int(c)].height)
        for name, c in zip(views.image_names, views.camera_ids, strict=True)
    }
    priors = read_priors(
        Path(priors_path), known_image_names=views.image_names, image_sizes=sizes
    )
    for name in views.image_names:
        if name not in priors.images:
            logger.warning("no priors for image %s: skipped", name)
    with_priors = [
        int(i)
        for i, n in zip(views.image_ids, views.image_names, strict=True)
        if n in priors.images
    ]
    classic_kp: dict[int, FloatArray] = {}
    classic_m: dict[Pair, IndexArray] = {}
    if options.use_classic_matches:
        classic_kp = {i: database.read_keypoints(database_path, i) for i in with_priors}
        classic_m = database.read_matches(database_path)
    solved: set[Pair] = set()
    if options.max_classic_inliers > 0:
        solved = {
            p
            for p, row in database.read_two_view_geometries(database_path).items()
            if len(row.inlier_matches) >= options.max_classic_inliers
        }
        if solved:
            logger.info(
                "%d pair(s) already solved by classic matching: no VCs there",
                len(solved),
            )
    timings["read"] = time.perf_counter() - t0
    vcs = compute_virtual_correspondences(
        views, priors, options, classic_kp, classic_m, timings, solved_pairs=solved
    )
    write = None
    if not options.dry_run:
        t0 = time.perf_counter()
        write = database.write_virtual_correspondences(
            database_path,
            vcs.keypoints,
            vcs.pairs,
            vcs.geometries,
            classic_inliers=vcs.classic_inliers,
            persons=vcs.associations,
            run_info={
                "colmap_vc_version": __version__,
                "priors": str(Path(priors_path).resolve()),
                "options": _jsonable(asdict(options)),
            },
        )
        timings["write"] = time.perf_counter() - t0
    summary = AugmentSummary(
        database_path=database_path,
        dry_run=options.dry_run,
        num_images=len(views.image_names),
        num_images_with_priors=len(with_priors),
        skipped_images=vcs.skipped_images,
        pairs=vcs.reports,
        timings_s=timings,
        write=write,
    )
    logger.info(
        "augment%s: %d/%d images with priors, %d pairs with VCs, %d verified, "
        "%d VCs (%d inliers)",
        " (dry run)" if options.dry_run else "",
        summary.num_images_with_priors,
        summary.num_images,
        len(summary.pairs),
        summary.num_verified_pairs,
        sum(p.num_vcs for p in summary.pairs),
        sum(p.num_inliers for p in summary.pairs),
    )
    return summary


def _jsonable(value: object) -> object:
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, (str, int, float, bool)) or value is None:
        return value
    return str(value)
