"""Building blocks of :func:`colmap_vc.augment.compute_virtual_correspondences`.

Per image, the observations of every person (re-posed prior, surface samples and
keypoints); per image pair, the concatenated person matches, their initial
thickness (a, b), and the person-link evidence and cues the association weighs.
"""

from __future__ import annotations

import dataclasses
import itertools
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING

import numpy as np
import pycolmap

from . import raycast
from .association import LinkEvidence, PersonCue
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
from .structs import FloatArray, ImagePrior, IndexArray, PairGeometry, ScenePriors
from .verification import Verification, verify_pair, verify_pair_with_classic

if TYPE_CHECKING:
    from .augment import AugmentOptions


def template_samples(
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
    groups: Sequence[str] | None = None,
) -> tuple[ImagePrior, list[PersonObservations]]:
    """The re-posed priors of one image and the observations of every person.

    ``groups`` (one per person): people occlude only people of their own group
    (instant), for a static camera's view that holds several instants.
    """
    prior = refit_image_prior(priors.images[image_name], camera, options)
    groups = groups or [""] * len(prior.persons)
    out = []
    for group in sorted(set(groups)):  # loop over instants of the view
        members = [k for k, g in enumerate(groups) if g == group]
        sub = dataclasses.replace(
            prior, persons=tuple(prior.persons[k] for k in members)
        )
        others = None
        if len(members) > 1 and options.people_occlude:
            others = raycast.build_scene(
                [(p.vertices_cam, p.faces) for p in sub.persons]
            )
        for j, k in enumerate(members):
            obs = observe_person(
                sub, j, camera, samples[template_key(sub.persons[j])], options, others
            )
            out.append((k, dataclasses.replace(obs, person_index=k)))
    return prior, [obs for _, obs in sorted(out, key=lambda kv: kv[0])]


def concat_matches(
    matches: list[tuple[int, int, PersonMatches]],
) -> tuple[IndexArray, ...]:
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


def gather(
    obs: list[PersonObservations], person: IndexArray, row: IndexArray, attr: str
) -> FloatArray:
    """Rows ``row`` of attribute ``attr`` of the observations of people ``person``."""
    first = getattr(obs[0], attr) if obs else np.zeros((0, 2))
    out = np.zeros((len(row), *first.shape[1:]))
    for k in range(len(obs)):  # loop over people, vectorized over matches
        sel = person == k
        out[sel] = getattr(obs[k], attr)[row[sel]]
    return out


def observation_codes(person: IndexArray, row: IndexArray) -> IndexArray:
    """One int64 per (person, observation row)."""
    return person.astype(np.int64) * (1 << 32) + row.astype(np.int64)


def initial_thickness(
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
    median = np.nanmedian((p1 - p2 @ R) @ c)
    scale = float(median) if np.isfinite(median) and median > 0 else 1.0
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


def link_evidence(
    n1: str,
    n2: str,
    obs1: list[PersonObservations],
    obs2: list[PersonObservations],
    cam1: pycolmap.Camera,
    cam2: pycolmap.Camera,
    cache: dict[tuple[str, str, int, int], PersonMatches],
    options: AugmentOptions,
    groups1: Sequence[str] | None = None,
    groups2: Sequence[str] | None = None,
) -> list[LinkEvidence]:
    """Every person link of one pair, verified on its own VCs (a subsample).

    ``groups1``/``groups2`` (one per person, static cameras): people of different
    instants are never linked, so their links are not computed.
    """
    out = []
    for a, b in itertools.product(range(len(obs1)), range(len(obs2))):
        g1, g2 = (groups1[a] if groups1 else ""), (groups2[b] if groups2 else "")
        if g1 and g2 and g1 != g2:
            continue
        m = match_persons(obs1[a], obs2[b])
        cache[(n1, n2, a, b)] = m
        if len(m) < options.min_num_vcs:
            continue
        rows = np.arange(len(m))
        if len(m) > options.max_link_vcs:  # evenly spread, deterministic
            spread = np.linspace(0, len(m) - 1, options.max_link_vcs).round()
            rows = np.unique(spread.astype(np.int64))
        result = verify_pair(
            cam1,
            cam2,
            obs1[a].xy_img[m.idx1[rows]],
            obs2[b].xy_img[m.idx2[rows]],
            options=options.verification,
        )
        out.append(
            LinkEvidence(
                image_name1=n1,
                image_name2=n2,
                person1=a,
                person2=b,
                num_vcs=len(rows),
                num_inliers=int(result.vc_is_inlier.sum()),
                cam2_from_cam1=None
                if result.geometry is None
                else result.geometry.cam2_from_cam1,
            )
        )
    return out


def person_cues(
    name: str, prior: ImagePrior, groups: Sequence[str] | None = None
) -> list[PersonCue]:
    return [
        PersonCue(
            image_name=name,
            index=k,
            person_id=p.person_id,
            vertices_cam=p.vertices_cam,
            appearance=p.appearance,
            group=groups[k] if groups else "",
        )
        for k, p in enumerate(prior.persons)
    ]


@dataclasses.dataclass(frozen=True, kw_only=True, slots=True)
class PairContext:
    """What every per-pair task needs, shipped once per worker (colmap_vc.executor)."""

    observations: Mapping[str, list[PersonObservations]]
    cameras: Mapping[str, pycolmap.Camera]
    options: AugmentOptions
    groups: Mapping[str, Sequence[str]] | None = None  # instant per person


LinkResult = tuple[list[LinkEvidence], dict[tuple[int, int], PersonMatches]]


def link_pairs(ctx: PairContext, pairs: Sequence[tuple[str, str]]) -> list[LinkResult]:
    """:func:`link_evidence` of each image pair, with its person matches by link."""
    out: list[LinkResult] = []
    for n1, n2 in pairs:
        cache: dict[tuple[str, str, int, int], PersonMatches] = {}
        links = link_evidence(
            n1,
            n2,
            ctx.observations[n1],
            ctx.observations[n2],
            ctx.cameras[n1],
            ctx.cameras[n2],
            cache,
            ctx.options,
            ctx.groups.get(n1) if ctx.groups else None,
            ctx.groups.get(n2) if ctx.groups else None,
        )
        out.append((links, {(k[2], k[3]): m for k, m in cache.items()}))
    return out


@dataclasses.dataclass(frozen=True, kw_only=True, slots=True)
class VerifyTask:
    """One pair's associated VCs (image points) and classic matches to verify."""

    image_name1: str
    image_name2: str
    vc_xy1: FloatArray
    vc_xy2: FloatArray
    classic_xy1: FloatArray | None
    classic_xy2: FloatArray | None


def verify_task(
    n1: str,
    n2: str,
    cat: tuple[IndexArray, ...],
    observations: Mapping[str, list[PersonObservations]],
    classic: IndexArray,
    keypoints1: FloatArray | None,
    keypoints2: FloatArray | None,
) -> tuple[VerifyTask, IndexArray]:
    """The task of one associated pair, and the order RANSAC sees its classic
    matches in (``classic``: (C, 2) keypoint indices, image ``n1`` first).

    RANSAC sees the classic matches in a canonical order (then keypoints), whatever
    the image ids COLMAP gave; :func:`in_stored_order` puts the mask back.
    """
    canonical = np.lexsort((classic[:, 1], classic[:, 0]))
    cm = classic[canonical]
    has = len(cm) > 0 and keypoints1 is not None and keypoints2 is not None
    return (
        VerifyTask(
            image_name1=n1,
            image_name2=n2,
            vc_xy1=gather(observations[n1], cat[0], cat[1], "xy_img"),
            vc_xy2=gather(observations[n2], cat[2], cat[3], "xy_img"),
            classic_xy1=keypoints1[cm[:, 0]] if has else None,  # type: ignore[index]
            classic_xy2=keypoints2[cm[:, 1]] if has else None,  # type: ignore[index]
        ),
        canonical,
    )


def in_stored_order(result: Verification, canonical: IndexArray) -> Verification:
    """The classic inlier mask of :func:`verify_task`'s order, in the stored order."""
    if not len(canonical):
        return result
    stored = np.zeros(len(canonical), dtype=bool)
    stored[canonical] = result.classic_is_inlier
    return dataclasses.replace(result, classic_is_inlier=stored)


def verify_tasks(ctx: PairContext, tasks: Sequence[VerifyTask]) -> list[Verification]:
    """:func:`verify_pair_with_classic` of each task."""
    return [
        verify_pair_with_classic(
            ctx.cameras[t.image_name1],
            ctx.cameras[t.image_name2],
            t.vc_xy1,
            t.vc_xy2,
            t.classic_xy1,
            t.classic_xy2,
            ctx.options.verification,
            ctx.options.max_classic_disagreement_deg,
        )
        for t in tasks
    ]
