"""What `augment` writes, assembled from the verified (and failed) image pairs.

Per image, the VC keypoints: every observation some pair uses, grouped by person;
per pair, the VC matches with their initial thickness, the two-view geometry, the
classic inliers, the person associations, and a report line.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from . import database
from .matching import PersonObservations
from .structs import (
    HitKind,
    IndexArray,
    PairGeometry,
    PairVcMatches,
    VcKeypoints,
)
from .vc_pairs import gather, initial_thickness, observation_codes
from .verification import Verification

Pair = tuple[int, int]


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
    reason: str = ""  # why a pair with VCs has no geometry (or was dropped)

    @property
    def inlier_ratio(self) -> float:
        """VC inliers / VCs."""
        return self.num_inliers / self.num_vcs if self.num_vcs else 0.0


class Candidate(NamedTuple):
    """One image pair with VCs, in image-id order (verified or not, and why)."""

    name1: str
    name2: str
    result: Verification
    cat: tuple[IndexArray, ...]  # concatenated matches (vc_pairs.concat_matches)
    assignment: list[tuple[int, int]]  # (person index 1, person index 2)
    method: str  # the association's method
    num_classic: int  # classic matches verified with the VCs
    reason: str = ""  # why it has no geometry


def assemble(
    candidates: Sequence[Candidate],
    names: Sequence[str],
    observations: Mapping[str, list[PersonObservations]],
    image_id: Mapping[str, int],
    classic_matches: Mapping[Pair, IndexArray],
) -> tuple[
    list[VcKeypoints],
    list[PairVcMatches],
    dict[Pair, PairGeometry],
    dict[Pair, IndexArray],
    list[database.PersonAssociation],
    list[PairReport],
]:
    """Keypoints, matches, geometries, classic inliers, associations and reports."""
    used: dict[str, list[IndexArray]] = {n: [] for n in names}
    for n1, n2, _, cat, *_rest in candidates:
        used[n1].append(observation_codes(cat[0], cat[1]))
        used[n2].append(observation_codes(cat[2], cat[3]))

    # VC keypoints per image: every observation some pair uses, grouped by person.
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
                image_id=image_id[name],
                xy_img=gather(obs, person, row, "xy_img"),
                person_id=pid_of[person],
                track_id=gather(obs, person, row, "track_id").astype(np.int64),
            )
        )

    pairs: list[PairVcMatches] = []
    geometries: dict[Pair, PairGeometry] = {}
    classic_inliers: dict[Pair, IndexArray] = {}
    associations: list[database.PersonAssociation] = []
    reports: list[PairReport] = []
    for n1, n2, result, cat, assignment, method, num_classic, reason in candidates:
        id1, id2 = image_id[n1], image_id[n2]
        k1, r1, k2, r2, kind, _ = cat
        obs1, obs2 = observations[n1], observations[n2]
        idx1 = np.searchsorted(codes_of[n1], observation_codes(k1, r1))
        idx2 = np.searchsorted(codes_of[n2], observation_codes(k2, r2))
        x1 = gather(obs1, k1, r1, "first_hit_cam")
        p1 = gather(obs1, k1, r1, "point_cam")
        x2 = gather(obs2, k2, r2, "first_hit_cam")
        p2 = gather(obs2, k2, r2, "point_cam")
        pid_of = np.array(
            [o.person_id if o.person_id >= 0 else k for k, o in enumerate(obs1)],
            np.int64,
        )
        pid = pid_of[k1]
        a, b = initial_thickness(x1, x2, p1, p2, result.geometry)
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
            if num_classic and len(result.classic_is_inlier):
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
                reason=reason,
            )
        )
    return keypoints, pairs, geometries, classic_inliers, associations, reports
