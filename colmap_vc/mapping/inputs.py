"""What `map` reads before mapping, read once: the database's images, the static
cameras, the priors and the keypoints' left/right counterparts."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from .. import database
from ..static_cameras import StaticCameras, parse_static_cameras
from ..structs import ScenePriors
from .options import MappingOptions
from .priors import keypoint_mirror, load_priors


@dataclass(frozen=True, kw_only=True, slots=True)
class MapInputs:
    """The inputs of one `map` run (the database is the mapper's working copy)."""

    database_path: Path
    views: database.DatabaseViews
    static: StaticCameras | None
    mapped: tuple[str, ...]  # the images the mapper sees: one per static camera
    priors: ScenePriors | None
    mirror: dict[int, int] | None  # template track id -> left/right counterpart's

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
        return dict(
            zip(
                self.views.image_ids.tolist(),
                self.views.num_keypoints.tolist(),
                strict=True,
            )
        )


def read_inputs(
    database_path: Path, options: MappingOptions, priors_path: Path | None
) -> MapInputs:
    """Read the database's images, the static cameras (given, else recorded by
    `augment`), the priors (given, else recorded) and the keypoint mirror."""
    views = database.read_views(database_path)
    static = static_cameras(options, database_path, views.image_names)
    mapped = (
        tuple(views.image_names)
        if static is None
        else tuple(sorted({*static.representative.values(), *static.unmatched}))
    )
    priors = load_priors(database_path, priors_path, views.image_names, static)
    return MapInputs(
        database_path=database_path,
        views=views,
        static=static,
        mapped=mapped,
        priors=priors,
        mirror=keypoint_mirror(database_path, priors),
    )


def static_cameras(
    options: MappingOptions, database_path: Path, image_names: Sequence[str]
) -> StaticCameras | None:
    """The static cameras given, else those `augment` recorded, else None."""
    pattern = options.static_cameras
    if pattern is None:
        recorded = database.read_run_info(database_path).get("options", {})
        pattern = recorded.get("static_cameras") if isinstance(recorded, dict) else None
    return None if not pattern else parse_static_cameras(pattern, image_names)
