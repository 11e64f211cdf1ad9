"""What `map` reads from the database before mapping, read once: its images, what
`augment` wrote (VCs, person associations, options), the two-view geometries, the
static cameras, the priors and the keypoints' left/right counterparts. The
mappers (pycolmap's, and the mesh- and two-view-initialised ones) read their
matches from the database themselves."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .. import database
from ..static_cameras import StaticCameras, merge_priors, parse_static_cameras
from ..structs import ScenePriors
from ..vc_records import VcRecords, read_vc_records
from .options import MappingOptions
from .priors import keypoint_mirror, read_image_priors, with_associated_ids


@dataclass(frozen=True, kw_only=True, slots=True)
class MapInputs:
    """The inputs of one `map` run (the database is the mapper's working copy)."""

    database_path: Path
    records: VcRecords  # the images, and what augment wrote
    geometries: Mapping[database.Pair, database.TwoViewGeometryRow]
    static: StaticCameras | None
    mapped: tuple[str, ...]  # the images the mapper sees: one per static camera
    priors: ScenePriors | None  # static cameras: one merged view per camera
    image_priors: ScenePriors | None  # each image's own people
    mirror: dict[int, int] | None  # template track id -> left/right counterpart's
    instant_of: dict[int, str] | None = None
    """Static cameras: the instant of each person identity (people of the static
    cameras' views; an identity spans one instant)."""

    @property
    def views(self) -> database.DatabaseViews:
        """The database's images and cameras."""
        return self.records.views

    @property
    def focal_guessed(self) -> tuple[str, ...]:
        """The images whose camera has no known focal length: COLMAP guessed it
        (1.2 times the larger side when neither the user nor EXIF gave one)."""
        known = {
            i: bool(c.has_prior_focal_length) for i, c in self.views.cameras.items()
        }
        return tuple(
            name
            for name, camera_id in zip(
                self.views.image_names, self.views.camera_ids.tolist(), strict=True
            )
            if not known[int(camera_id)]
        )

    @property
    def num_classic(self) -> dict[int, int]:
        """Image id -> number of its classic keypoints (the VCs follow them)."""
        return self.records.num_classic


def read_inputs(
    database_path: Path, options: MappingOptions, priors_path: Path | None
) -> MapInputs:
    """Read the database's images, what `augment` wrote, the two-view geometries,
    the static cameras (given, else recorded by `augment`), the priors (given,
    else recorded; anonymous people get the association's identities) and the
    keypoint mirror."""
    records = read_vc_records(database_path)
    names = records.views.image_names
    static = static_cameras(options, records.run_info, names)
    mapped = (
        tuple(names)
        if static is None
        else tuple(sorted({*static.representative.values(), *static.unmatched}))
    )
    own = read_image_priors(records.run_info, priors_path, names)
    image_priors = None if own is None else with_associated_ids(own, records)
    priors = image_priors
    instant_of = None
    if own is not None and static is not None:  # the views augment wrote
        views, groups = merge_priors(own, static)
        priors = with_associated_ids(views, records)
        instant_of = identity_instants(views, groups, records)
    return MapInputs(
        database_path=database_path,
        records=records,
        geometries=database.read_two_view_geometries(database_path, include_vc=True),
        static=static,
        mapped=mapped,
        priors=priors,
        image_priors=image_priors,
        mirror=keypoint_mirror(records.num_samples, priors),
        instant_of=instant_of,
    )


def identity_instants(
    views: ScenePriors, groups: Mapping[tuple[str, int], str], records: VcRecords
) -> dict[int, str]:
    """Identity -> instant of the static cameras' people: ``views`` are the
    merged priors `augment` wrote VCs for, ``groups`` (view name, person index)
    -> instant (:func:`~colmap_vc.static_cameras.merge_priors`). A person's
    database id is its prior's id, else its index in the view (what `augment`
    writes)."""
    id_of = dict(
        zip(records.views.image_names, records.views.image_ids.tolist(), strict=True)
    )
    out: dict[int, str] = {}
    for (name, k), instant in groups.items():  # loop over the merged people
        if not instant or name not in id_of or name not in views.images:
            continue
        person = views.images[name].persons[k]
        key = k if person.person_id is None else person.person_id
        identity = records.identity.get((id_of[name], key))
        if identity is not None:
            out[identity] = instant
    return out


def static_cameras(
    options: MappingOptions, run_info: Mapping[str, Any], image_names: Sequence[str]
) -> StaticCameras | None:
    """The static cameras given, else those `augment` recorded, else None."""
    pattern = options.static_cameras
    if pattern is None:
        recorded = run_info.get("options", {})
        pattern = recorded.get("static_cameras") if isinstance(recorded, dict) else None
    return None if not pattern else parse_static_cameras(pattern, image_names)
