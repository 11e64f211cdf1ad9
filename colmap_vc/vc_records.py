"""What `augment` wrote into a database, with the database's images, read once.

`map` reads these before mapping (:mod:`colmap_vc.mapping.inputs`) and every stage
after the mapper takes them in memory: the keypoint and surface tracks by identity
(:mod:`colmap_vc.keypoint_tracks`), the camera checks, the metric scale.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from . import database


def person_identities(
    associations: list[database.PersonAssociation],
) -> dict[tuple[int, int], int]:
    """(image_id, person_id) -> identity, by union-find over the associations."""
    parent: dict[tuple[int, int], tuple[int, int]] = {}

    def find(a: tuple[int, int]) -> tuple[int, int]:
        parent.setdefault(a, a)
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    for a in associations:  # loop over person pairs (a handful per image pair)
        ra = find((a.image_id1, a.person_id1))
        rb = find((a.image_id2, a.person_id2))
        if ra != rb:
            parent[max(ra, rb)] = min(ra, rb)
    roots = sorted({find(k) for k in parent})
    index = {r: i for i, r in enumerate(roots)}
    return {k: index[find(k)] for k in parent}


@dataclass(frozen=True, kw_only=True, slots=True)
class VcRecords:
    """What `augment` wrote into a database, with the database's images, read once
    (:func:`read_vc_records`): what the tracks by identity are made of."""

    views: database.DatabaseViews
    vc_keypoints: tuple[database.VcKeypoints, ...]  # per image, after its classic
    pairs: tuple[database.PairVcMatches, ...]  # the kind each pair matched them as
    identity: dict[tuple[int, int], int]  # (image id, person id) -> identity
    run_info: dict[str, Any]  # augment's options and priors (database.read_run_info)

    @property
    def num_classic(self) -> dict[int, int]:
        """Image id -> number of its classic keypoints (its VCs follow them)."""
        return dict(
            zip(
                self.views.image_ids.tolist(),
                self.views.num_keypoints.tolist(),
                strict=True,
            )
        )

    @property
    def num_samples(self) -> int:
        """The template's surface samples: keypoint k's track id is num_samples + k
        (0: augment did not record it)."""
        run = self.run_info.get("options", {})
        return int(run.get("matching", {}).get("num_samples", 0)) if run else 0


def read_vc_records(database_path: Path) -> VcRecords:
    """The database's images, and the VCs, person associations and run options
    `augment` wrote (none for a database it has not augmented)."""
    vc_keypoints, pairs = database.read_virtual_correspondences(database_path)
    return VcRecords(
        views=database.read_views(database_path),
        vc_keypoints=tuple(vc_keypoints),
        pairs=tuple(pairs),
        identity=person_identities(database.read_person_associations(database_path)),
        run_info=database.read_run_info(database_path),
    )
