"""Static cameras over several instants: one view per physical camera.

A user films people with cameras that do not move (a lab, a gym, a stage) and gives
colmap-vc frames of several instants. Every instant's people constrain the same
camera pose, and the people at different instants are different people. The user
names the physical camera of each image with a regular expression whose first
capturing group, searched in the image name, is the camera (``'(cam\\d+)_'`` makes
``cam01_t010.jpg`` camera ``cam01``); the name with that group cut out is the instant
(``_t010.jpg``), so images of one instant share it across cameras.

Inside, each physical camera becomes one view: its first image (by name) is the
*representative* that carries the VCs of every instant in the database, its priors
hold the people of all its images, each tagged with its instant (the association
never links people of different instants, and people occlude only people of their
own instant). ``map`` registers the representatives and gives every image of a
camera its representative's pose. Images the expression does not match stay cameras
of their own.
"""

from __future__ import annotations

import dataclasses
import logging
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components

from .database import DatabaseViews, TwoViewGeometryRow
from .structs import ImagePrior, PersonPrior, ScenePriors

logger = logging.getLogger(__name__)

PersonKey = tuple[str, int]


@dataclass(frozen=True, kw_only=True, slots=True)
class StaticCameras:
    """Which images come from which static camera, and at which instant."""

    pattern: str
    camera_of: dict[str, str]  # image name -> physical camera (matched images only)
    instant_of: dict[str, str]  # image name -> instant key (matched images only)
    unmatched: tuple[str, ...]  # images the expression does not match

    @property
    def representative(self) -> dict[str, str]:
        """Physical camera -> its representative image (first by name)."""
        out: dict[str, str] = {}
        for name in sorted(self.camera_of):
            out.setdefault(self.camera_of[name], name)
        return out

    def members(self, representative: str) -> list[str]:
        """The images of the representative's camera, by name."""
        cam = self.camera_of[representative]
        return sorted(n for n, c in self.camera_of.items() if c == cam)

    def representative_of(self, name: str) -> str:
        """The image that stands for ``name`` (itself when unmatched)."""
        return (
            self.representative[self.camera_of[name]]
            if name in self.camera_of
            else name
        )


def parse_static_cameras(pattern: str, image_names: Sequence[str]) -> StaticCameras:
    """Group images by physical camera with ``pattern`` (module doc).

    Raises:
        ValueError: the expression is invalid, has no capturing group, or matches
            none of the images.
    """
    try:
        regex = re.compile(pattern)
    except re.error as exc:
        raise ValueError(
            f"--static-cameras {pattern!r} is not a valid regular expression: {exc}"
        ) from exc
    if regex.groups < 1:
        raise ValueError(
            f"--static-cameras {pattern!r} has no capturing group: put the part of "
            "the image name that names the camera in parentheses, e.g. '(cam\\d+)_'"
        )
    camera_of, instant_of, unmatched = {}, {}, []
    for name in sorted(image_names):
        m = regex.search(name)
        if m is None or not m.group(1):
            unmatched.append(name)
            continue
        camera_of[name] = m.group(1)
        instant_of[name] = name[: m.start(1)] + name[m.end(1) :]
    if not camera_of:
        example = ", ".join(sorted(image_names)[:3])
        raise ValueError(
            f"--static-cameras {pattern!r} matches none of the {len(image_names)} "
            f"images (e.g. {example})"
        )
    static = StaticCameras(
        pattern=pattern,
        camera_of=camera_of,
        instant_of=instant_of,
        unmatched=tuple(unmatched),
    )
    logger.info(
        "static cameras %r: %d images on %d cameras%s",
        pattern,
        len(camera_of),
        len(static.representative),
        f"; {len(unmatched)} image(s) unmatched stay cameras of their own: "
        + ", ".join(unmatched[:5])
        if unmatched
        else "",
    )
    return static


def merge_priors(
    priors: ScenePriors, static: StaticCameras
) -> tuple[ScenePriors, dict[PersonKey, str]]:
    """One prior per physical camera: the people of all its images.

    Returns the merged priors (representatives and unmatched images) and each
    merged person's instant ("" for unmatched images: they may match anyone).
    Persons keep their order: images by name, then the image's own order.
    """
    images: dict[str, ImagePrior] = {}
    groups: dict[PersonKey, str] = {}
    instants = sorted(set(static.instant_of.values()))
    for rep in sorted(static.representative.values()):
        persons: list[PersonPrior] = []
        for name in static.members(rep):
            if name not in priors.images:
                continue
            for p in priors.images[name].persons:
                groups[(rep, len(persons))] = static.instant_of[name]
                # Ids are per instant: make them unique across instants.
                pid = p.person_id
                if pid is not None:
                    pid += 100_000 * instants.index(static.instant_of[name])
                persons.append(dataclasses.replace(p, person_id=pid))
        images[rep] = ImagePrior(image_name=rep, persons=tuple(persons))
    for name in static.unmatched:
        if name in priors.images:
            images[name] = priors.images[name]
            for k in range(len(priors.images[name].persons)):
                groups[(name, k)] = ""
    return dataclasses.replace(priors, images=images), groups


def same_view_pairs(
    geometries: Mapping[tuple[int, int], TwoViewGeometryRow],
    sizes: Mapping[int, tuple[int, int]],
    min_inliers: int,
    max_shift_px: float,
) -> list[tuple[int, int, int]]:
    """Image pairs whose classic matches sit at the same pixels: ``min_inliers``
    or more inliers and a homography that moves no corner of the first image by
    more than ``max_shift_px`` -> (image id 1, image id 2, inliers), most inliers
    first. Frames of one static camera at two instants look so; two cameras,
    or one that moved, do not (a parallax of a pixel is a few millimetres of
    camera motion at the distance of the scene's background)."""
    out = []
    for (i, j), row in geometries.items():  # loop over pairs (one H each)
        if row.H is None or len(row.inlier_matches) < min_inliers or i not in sizes:
            continue
        w, h = sizes[i]
        corners = np.array([[0, 0, 1], [w, 0, 1], [0, h, 1], [w, h, 1]], float)
        moved = corners @ row.H.T
        if np.any(np.abs(moved[:, 2]) < 1e-12):
            continue
        shift = np.linalg.norm(moved[:, :2] / moved[:, 2:] - corners[:, :2], axis=1)
        if shift.max() <= max_shift_px:
            out.append((i, j, len(row.inlier_matches)))
    return sorted(out, key=lambda t: (-t[2], t[0], t[1]))


SAME_VIEW_MIN_INLIERS = 30
"""Classic inliers a same-pixels pair needs (what COLMAP's mapper asks to
register an image, abs_pose_min_num_inliers)."""
SAME_VIEW_MAX_SHIFT_PX = 2.0
"""Largest corner shift of such a pair's homography: pose2sim's frames of one
camera at two instants shift by 0.5 px at most, two cameras by hundreds."""


def warn_if_static_cameras(
    geometries: Mapping[tuple[int, int], TwoViewGeometryRow], views: DatabaseViews
) -> list[list[str]]:
    """Warn when images match at the same pixels (:func:`same_view_pairs`) and
    no static cameras were named: each frame would get its own pose, and the
    people of different instants would be matched as the same people. Returns
    the groups of such images (connected by same-pixel pairs), by name."""
    sizes = {
        int(i): (views.cameras[int(c)].width, views.cameras[int(c)].height)
        for i, c in zip(views.image_ids, views.camera_ids, strict=True)
    }
    names = dict(zip(views.image_ids.tolist(), views.image_names, strict=True))
    pairs = same_view_pairs(
        geometries, sizes, SAME_VIEW_MIN_INLIERS, SAME_VIEW_MAX_SHIFT_PX
    )
    if not pairs:
        return []
    ids = np.array(sorted({i for p in pairs for i in p[:2]}), dtype=np.int64)
    edges = np.searchsorted(ids, np.array([p[:2] for p in pairs]).reshape(-1, 2))
    graph = csr_matrix(
        (np.ones(len(edges), bool), (edges[:, 0], edges[:, 1])), shape=(len(ids),) * 2
    )
    _, label = connected_components(graph, directed=False)
    groups = sorted(
        sorted(names[int(i)] for i in ids[label == k]) for k in np.unique(label)
    )
    example = ", ".join(groups[0][:4]) + (", ..." if len(groups[0]) > 4 else "")
    logger.warning(
        "%d image pair(s) match at the same pixels, in %d group(s) (e.g. %s): "
        "frames of static cameras at several instants? Without "
        "--static-cameras each frame gets its own pose and the people of "
        "different instants are matched as the same people; give augment and "
        "map --static-cameras with a pattern whose group names the camera "
        '(docs/real-data.md, "Static cameras")',
        len(pairs),
        len(groups),
        example,
    )
    return groups
