"""Each camera's "up" from the scene's vertical lines.

People pin down where the cameras stand around them only weakly: turning every
camera by a degree about the people, each about its own horizontal axis, moves
the keypoints' reprojections by a tenth of a pixel (docs/results.md, "Static
cameras: where the keypoints' optimum lies"), so the keypoints' small biases move
the cameras by degrees. Rooms, gyms, stages and streets hold what fixes that
turn: vertical edges (door and window frames, pillars, shelves), whose images meet
at the vertical vanishing point, the direction of gravity in the camera. Every
camera that sees the same gravity must be turned so that they agree
(:func:`colmap_vc.gba.ceres.bundle_adjust_inplace` with ``up``, run by
:mod:`colmap_vc.mapping.up`).

Per camera (a static camera: pooled over all its images, whose background is the
same):

1. Line segments (OpenCV's LSD) of at least ``min_segment_deg`` of the
   camera's view and ``min_segment_floor_px`` (or a fixed ``min_segment_px``),
   outside the people's boxes (limbs are near-vertical and not vertical), as
   planes through the camera centre (undistorted with the camera's model); the
   pieces of one broken edge joined into one line (one edge, one vote).
2. The vanishing point nearest the people's up: the people stand upright, so the
   direction from their feet to their heads (the major axis of each person's
   mesh) is gravity within ``max_hint_deg``. RANSAC over pairs of segments; a
   segment supports a point when its endpoints lie within ``endpoint_tol_px`` of
   the line from its midpoint to the point (LSD locates a sharp edge to a pixel
   or better; two pixels let a different bundle of oblique lines win on
   pose2sim).
3. The direction refined by weighted least squares over its segments, with its
   standard error from the same fit (a static camera's images repeat the same
   background lines: scaled by the square root of their number).
4. Another vanishing point, farther than three standard errors (after its own
   refinement), with as many lines within counting noise (two standard
   deviations of a count): the image does not say which is the vertical. When
   most of its lines are the best one's too (a bundle of near-parallel edges
   that two directions explain about as well) and it is within
   ``max_rival_deg``, the up stays the best one with its error widened to
   reach the rival; otherwise None. On pose2sim's full frames: single t090's
   cam03 has a rival 1.1 deg away (35 of 37 lines shared) and multi t010's
   cam02 one 1.6 deg away (37 of 41), both best ups within 0.5-0.8 deg of the
   calibration's; single t010's cam02 has a treadmill's long edge, window
   blinds and a skeleton model 4.7 deg from the verticals (56 lines against
   57, 45 shared), and in the top 60 % of its frame the treadmill wins.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pycolmap
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components

from .image_io import read_image
from .structs import BoolArray, FloatArray, IndexArray, PersonPrior

logger = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True, slots=True)
class GravityOptions:
    """Options of the vertical vanishing point."""

    min_segment_px: float | None = None
    """Shorter segments are left out (also the margin around the people's
    boxes), pixels; None (the default): ``min_segment_deg`` of the camera's
    view, but no fewer than ``min_segment_floor_px``. A fixed value does not
    follow the image's scale: at 30 px, the value the step was first measured
    with on pose2sim's 1920-px frames, those frames halved (f = 839 px) lost
    their short verticals, a bundle of long oblique edges (a treadmill's side,
    window blinds) won, and cam02's up came out 4.6-5.5 deg off at all five
    instants with a standard error of 0.4-0.7 deg (docs/real-data.md, "Image
    scale")."""
    min_segment_deg: float = 1.0244
    """The shortest segment by the angle it subtends at the camera: 1.0244 deg
    is 30 px at pose2sim's f = 1678 px, 15 px at half its size. An angle, not a
    fraction of the image: a crop shrinks the image, not the scene."""
    min_segment_floor_px: float = 15.0
    """The angle's floor, pixels. A segment L px long supports every vanishing
    direction within asin(2 ``endpoint_tol_px`` / L) of its own: 7.7 deg at 15
    px, 11.5 deg at 10 px, half of the ``max_hint_deg`` search cone, where
    short texture edges vote for anything. On the synthetic 640-px room (the
    angle is 9-11 px there) the bare angle took such edges for verticals and
    their ups broke a model SIFT had placed (tests/test_mapping.py); with a
    floor of 10, 12, 15 or 20 px the test passes. At 15 px the synthetic
    domes' backdrops give ups too: 21 in 20 of bench/gba_seeds.py's 48 scenes,
    17 within 6.2 deg of the truth and 4 16-23 deg off (one from 31 segments
    with a 0.3 deg standard error). One camera's up alone is unused (ups count
    from two cameras on); two came in one of those scenes (1.5 and 4.9 deg off;
    91.1 -> 90.8 AUC@15) and in the 16-view speed dome (1.4 and 23.8 deg off,
    25.4 deg apart: both pass the up check, ``max_hint_deg``). At 20 px none
    comes in two cameras, but pose2sim's half-size frames lose their short
    verticals again (cam02 3.7-5.4 deg off at four instants)."""
    endpoint_tol_px: float = 1.0
    """A segment supports a vanishing point when both its endpoints lie within
    this of the line from its midpoint to the point (module doc)."""
    max_hint_deg: float = 25.0
    """Gravity lies within this of the people's up (feet to head). The up check
    (colmap_vc/mapping/up.py) leaves out a camera whose up, turned into the
    world by the people's model, is farther than this from the mean of all the
    measured ups, its own included: with two cameras that is half their angle,
    so two ups up to 50 deg apart are both used. A tighter bound on each up
    against the others' (15 deg, from the people's tilt error between two of
    pose2sim's four cameras per instant) was tried at c58f014 and reverted: a
    model of two cameras leaves their tilts 15-31 deg apart where both ups are
    right, and the ups are what fixes it (bench/subsets.py: static cam02-cam03
    2.2 -> 37.3 deg; docs/real-data.md, "Why people alone stop at 2-3
    degrees, and the cameras' up")."""
    max_rival_deg: float = 2.0
    """A rival vanishing point with about as many lines, most of them the best
    one's too, closer than this: the up is the best one, its error widened to
    reach the rival; farther: no up (module doc, step 4). Whichever is the
    vertical, the chosen one is then within this of it. The people alone set a
    camera's tilt to 1.4-2.7 deg (median per camera, pose2sim per instant
    without the up), the ups to 0.4-0.7 deg (bench/evidence.py's tilt column):
    an up the image cannot tell to better than that is no better than the
    people's. Kept farther, it cost: a treadmill's bundle 4.7 deg from the
    verticals, kept with a 4.7 deg error, won the count in the top 60 % of
    t010's frames and cost that instant 9.4 points of AUC@15 (81.0 -> 71.6);
    the rivals at 1.1 and 1.6 deg kept their ups within 0.8 deg."""
    min_segments: int = 20
    """Fewer supporting segments: no vertical direction for that camera."""
    num_trials: int = 2000
    """RANSAC hypotheses (pairs of segments)."""
    ransac_seed: int = 0
    """Seed of those hypotheses."""


@dataclass(frozen=True, kw_only=True, slots=True)
class Gravity:
    """The direction of "up" in one camera's frame, from its vertical lines."""

    up_cam: FloatArray  # (3,) unit vector, camera frame (x right, y down, z forward)
    sigma_rad: float  # standard error of its direction
    num_segments: int  # segments supporting it
    num_images: int  # images pooled
    lines_px: FloatArray  # (num_segments, 4) x1 y1 x2 y2, pixels (COLMAP's centres)
    people_up_cam: FloatArray | None = None  # (3,) the people's up, the search's hint


@dataclass(frozen=True, kw_only=True, slots=True)
class Segments:
    """Line segments as rays of their endpoints, in one camera's frame."""

    ray1: FloatArray  # (S, 3) float64, z = 1
    ray2: FloatArray  # (S, 3)
    normal: FloatArray  # (S, 3) unit normal of the plane through both rays

    @property
    def midpoint(self) -> FloatArray:
        return (self.ray1 + self.ray2) / 2.0


def min_segment_px(options: GravityOptions, camera: pycolmap.Camera) -> float:
    """The shortest segment kept in ``camera``'s images, pixels."""
    if options.min_segment_px is not None:
        return options.min_segment_px
    angle = float(np.radians(options.min_segment_deg)) * camera.mean_focal_length()
    return max(angle, options.min_segment_floor_px)


def long_axis_up(points: FloatArray) -> FloatArray:
    """(3,) unit major axis of (N, 3) camera-frame points, turned towards the
    image's top (-y)."""
    axis = np.linalg.svd(points - points.mean(axis=0), full_matrices=False)[2][0]
    return axis if axis[1] < 0 else -axis


def people_up(persons: Sequence[PersonPrior]) -> FloatArray | None:
    """The people's up in the camera frame: each person's mesh major axis, turned
    towards the image's top (-y), averaged. None without people."""
    if not persons:
        return None
    up = np.mean([long_axis_up(p.vertices_cam) for p in persons], axis=0)
    return up / np.linalg.norm(up)


def people_mask(
    persons: Sequence[PersonPrior], camera: pycolmap.Camera, margin_px: float
) -> BoolArray:
    """(H, W) True inside the boxes of the people's meshes, grown by ``margin_px``."""
    mask = np.zeros((camera.height, camera.width), dtype=bool)
    for p in persons:  # loop over the image's people
        front = p.vertices_cam[p.vertices_cam[:, 2] > 1e-6]
        if not len(front):
            continue
        xy = np.asarray(camera.img_from_cam(front))
        x0, y0 = np.floor(xy.min(axis=0) - margin_px).astype(int)
        x1, y1 = np.ceil(xy.max(axis=0) + margin_px).astype(int)
        mask[max(y0, 0) : max(y1, 0), max(x0, 0) : max(x1, 0)] = True
    return mask


def detect_segments(
    image: np.ndarray,
    camera: pycolmap.Camera,
    mask: BoolArray,
    options: GravityOptions,
) -> Segments:
    """LSD segments of a grey or BGR image, outside ``mask``, as rays."""
    grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    found = cv2.createLineSegmentDetector().detect(grey)[0]
    lines = np.zeros((0, 4)) if found is None else found.reshape(-1, 4).astype(float)
    length = np.linalg.norm(lines[:, 2:] - lines[:, :2], axis=1)
    mid = np.round((lines[:, :2] + lines[:, 2:]) / 2).astype(int)
    h, w = mask.shape
    inside = mask[np.clip(mid[:, 1], 0, h - 1), np.clip(mid[:, 0], 0, w - 1)]
    shortest = min_segment_px(options, camera)
    lines = lines[(length >= shortest) & ~inside] + 0.5  # -> COLMAP's
    ray1 = np.c_[np.asarray(camera.cam_from_img(lines[:, :2])), np.ones(len(lines))]
    ray2 = np.c_[np.asarray(camera.cam_from_img(lines[:, 2:])), np.ones(len(lines))]
    tol = options.endpoint_tol_px / camera.mean_focal_length()
    return _joined(ray1, ray2, tol)


def _joined(ray1: FloatArray, ray2: FloatArray, tol: float) -> Segments:
    """Segments on one image line (pieces of one edge LSD broke up) joined into
    one, from the farthest two of their endpoints: a long edge in ten pieces is
    one line, not ten votes for every vanishing point it passes."""
    normal = _unit_normals(ray1, ray2)
    if len(normal) < 2:
        return Segments(ray1=ray1, ray2=ray2, normal=normal)
    scale = np.linalg.norm(normal[:, :2], axis=1)  # line i: normal_i . (x, y, 1) = 0
    rows, cols = [], []
    for start in range(0, len(normal), 512):  # (512, S) at a time: 4k images
        n = normal[start : start + 512] / scale[start : start + 512, None]
        near = (np.abs(n @ ray1.T) < tol) & (np.abs(n @ ray2.T) < tol)  # j on line i
        i, j = np.nonzero(near)
        rows.append(i + start)
        cols.append(j)
    i, j = np.concatenate(rows), np.concatenate(cols)
    graph = csr_matrix((np.ones(len(i), bool), (i, j)), shape=(len(normal),) * 2)
    graph = graph.multiply(graph.T)  # both ways: each on the other's line
    _, group = connected_components(graph, directed=False)
    num = int(group.max()) + 1
    index = np.arange(len(group))
    first = np.full(num, len(group))
    np.minimum.at(first, group, index)
    last = np.zeros(num, dtype=np.int64)
    np.maximum.at(last, group, index)
    direction = ray2[last, :2] - ray1[first, :2]  # a line's span: first to last piece
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    points = np.concatenate([ray1, ray2])
    owner = np.r_[group, group]
    along = np.einsum("ij,ij->i", points[:, :2], direction[owner])
    ranked = np.lexsort((along, owner))  # by line, then along it
    bounds = np.searchsorted(owner[ranked], np.arange(num + 1))
    r1 = points[ranked[bounds[:-1]]]  # each line's extreme endpoints
    r2 = points[ranked[bounds[1:] - 1]]
    n = _unit_normals(r1, r2)
    return Segments(ray1=r1, ray2=r2, normal=n)


def _unit_normals(ray1: FloatArray, ray2: FloatArray) -> FloatArray:
    """(S, 3) unit normal of the plane through the camera centre and each segment."""
    normal = np.cross(ray1, ray2)
    return normal / np.linalg.norm(normal, axis=1, keepdims=True)


def endpoint_distance(segments: Segments, points: FloatArray) -> FloatArray:
    """(P, S) distance, normalised image units, of each segment's first endpoint
    from the line through its midpoint and each vanishing point (P, 3)."""
    mid = segments.midpoint
    lines = np.cross(mid[None, :, :], points[:, None, :])  # (P, S, 3)
    num = np.abs(np.einsum("psk,sk->ps", lines, segments.ray1))
    return num / np.maximum(np.linalg.norm(lines[..., :2], axis=2), 1e-12)


def vertical_direction(
    segments: Segments,
    up_hint: FloatArray,
    focal_px: float,
    options: GravityOptions,
    repeats: int = 1,
) -> tuple[FloatArray, float, Segments] | None:
    """The vanishing direction nearest ``up_hint`` (module doc) -> (unit direction
    towards up, its standard error in radians, its supporting segments), or None.

    ``repeats``: how many images of one static camera the segments pool. Their
    background lines are the same lines seen again, so the fit is about as
    certain as one image's: its standard error is scaled by sqrt(repeats).
    """
    n = segments.normal
    near = np.abs(n @ up_hint) < np.sin(np.radians(options.max_hint_deg))
    if near.sum() < max(options.min_segments, 2):
        return None
    segs = Segments(ray1=segments.ray1[near], ray2=segments.ray2[near], normal=n[near])
    n = segs.normal
    tol = options.endpoint_tol_px / focal_px
    rng = np.random.default_rng(options.ransac_seed)
    pairs = rng.integers(0, len(n), size=(options.num_trials, 2))
    v = np.cross(n[pairs[:, 0]], n[pairs[:, 1]])
    norm = np.linalg.norm(v, axis=1)
    ok = norm > 1e-9
    v = v[ok] / norm[ok, None]
    v *= np.sign(v @ up_hint)[:, None]
    v = v[v @ up_hint > np.cos(np.radians(options.max_hint_deg))]
    if not len(v):
        return None
    support = np.zeros(len(v), dtype=np.int64)
    step = max(1, 2_000_000 // len(n))  # hypotheses per block: (step, S) distances
    for start in range(0, len(v), step):
        block = endpoint_distance(segs, v[start : start + step])
        support[start : start + step] = (block < tol).sum(axis=1)
    best = v[int(np.argmax(support))]
    for _ in range(5):  # refine on its support (weighted total least squares)
        inlier = endpoint_distance(segs, best[None])[0] < tol
        if inlier.sum() < options.min_segments:
            return None
        M, best = _refit(segs, inlier, best)
    weights = _weights(segs, inlier)
    residual = n[inlier] @ best
    dof = max(int(inlier.sum()) - 2, 1)
    s2 = float(weights @ residual**2) / dof
    eig = np.linalg.eigvalsh(M)  # ascending; eig[0] ~ 0 along best
    sigma = float(np.sqrt(s2 / max(eig[1], 1e-18) * repeats))
    # Another vanishing point that the best one's uncertainty cannot explain,
    # supported within counting noise as well: the image does not say which.
    count = int(inlier.sum())
    rival = _rival(segs, v, support, best, sigma, tol)
    if rival is not None and rival[1].sum() >= count - 2.0 * np.sqrt(count):
        direction, lines = rival
        shared = int((lines & inlier).sum())
        apart = float(np.arccos(np.clip(direction @ best, -1.0, 1.0)))
        if 2 * shared < lines.sum() or apart > np.radians(options.max_rival_deg):
            logger.debug(
                "gravity: two vanishing points %.1f deg apart: %d and %d lines, "
                "%d shared",
                np.degrees(apart),
                count,
                lines.sum(),
                shared,
            )
            return None
        # Mostly the same lines, which two close directions explain about as
        # well: the up stays the best one (the most lines), its error widened
        # to reach the rival.
        sigma = float(np.hypot(sigma, apart))
    return (
        best,
        sigma,
        Segments(ray1=segs.ray1[inlier], ray2=segs.ray2[inlier], normal=n[inlier]),
    )


def _rival(
    segs: Segments,
    hypotheses: FloatArray,
    support: IndexArray,
    best: FloatArray,
    sigma: float,
    tol: float,
    attempts: int = 5,
) -> tuple[FloatArray, BoolArray] | None:
    """The best-supported other vanishing point and its lines: the strongest
    hypotheses farther than three standard errors from ``best``, each refined on
    its lines; one that refines back to ``best`` was a noisy pair of its own
    lines. None when every one does."""
    apart = np.arccos(np.clip(hypotheses @ best, -1.0, 1.0)) > 3.0 * sigma
    for k in np.argsort(-support[apart], kind="stable")[:attempts].tolist():
        candidate = hypotheses[apart][k]
        for _ in range(3):
            inlier = endpoint_distance(segs, candidate[None])[0] < tol
            if inlier.sum() < 2:
                break
            _, candidate = _refit(segs, inlier, candidate)
        if np.arccos(np.clip(candidate @ best, -1.0, 1.0)) > 3.0 * sigma:
            return candidate, endpoint_distance(segs, candidate[None])[0] < tol
    return None


def _weights(segs: Segments, inlier: BoolArray) -> FloatArray:
    """A segment's weight: its squared length (its direction's precision)."""
    d = segs.ray2[inlier, :2] - segs.ray1[inlier, :2]
    return np.einsum("ij,ij->i", d, d)


def _refit(
    segs: Segments, inlier: BoolArray, previous: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """The direction that is closest to every supporting plane: the smallest
    eigenvector of their weighted scatter, signed like ``previous``."""
    n = segs.normal[inlier]
    w = _weights(segs, inlier)
    M = (n * w[:, None]).T @ n
    v = np.linalg.eigh(M)[1][:, 0]
    return M, v if v @ previous > 0 else -v


def measure_gravity(
    image_dir: Path,
    groups: Mapping[str, Sequence[str]],
    cameras: Mapping[str, pycolmap.Camera],
    persons: Mapping[str, Sequence[PersonPrior]],
    options: GravityOptions | None = None,
) -> dict[str, Gravity]:
    """Gravity per camera: ``groups`` maps a name (a static camera's
    representative, or an image) to the images pooled for it, ``cameras`` each
    image's camera, ``persons`` each image's people. Cameras without people (no
    hint), without enough vertical segments, or whose images cannot be read are
    left out."""
    options = options or GravityOptions()
    out: dict[str, Gravity] = {}
    for key in sorted(groups):  # loop over cameras
        parts, hints = [], []
        camera = cameras[key]
        for name in sorted(groups[key]):  # loop over the camera's images
            people = persons.get(name, ())
            hint = people_up(people)
            if hint is None:
                continue
            image = read_image(Path(image_dir) / name, grey=True)
            if image is None:
                logger.warning("gravity: cannot read %s: no up from it", name)
                continue
            if image.shape != (camera.height, camera.width):
                logger.warning(
                    "gravity: %s is %dx%d but its camera is %dx%d: no up from it",
                    name,
                    image.shape[1],
                    image.shape[0],
                    camera.width,
                    camera.height,
                )
                continue
            hints.append(hint)
            mask = people_mask(people, camera, min_segment_px(options, camera))
            parts.append(detect_segments(image, camera, mask, options))
        if not parts:
            continue
        hint = np.mean(hints, axis=0)
        hint /= np.linalg.norm(hint)
        segments = Segments(
            ray1=np.concatenate([p.ray1 for p in parts]),
            ray2=np.concatenate([p.ray2 for p in parts]),
            normal=np.concatenate([p.normal for p in parts]),
        )
        found = vertical_direction(
            segments,
            hint,
            camera.mean_focal_length(),
            options,
            repeats=len(parts),
        )
        if found is None:
            logger.info(
                "gravity: %s: no vertical direction (too few vertical lines, or "
                "two vanishing points with as many lines)",
                key,
            )
            continue
        up, sigma, lines = found
        support = len(lines.normal)
        out[key] = Gravity(
            up_cam=up,
            sigma_rad=sigma,
            num_segments=support,
            num_images=len(parts),
            lines_px=np.c_[
                np.asarray(camera.img_from_cam(lines.ray1)),
                np.asarray(camera.img_from_cam(lines.ray2)),
            ],
            people_up_cam=hint,
        )
        logger.info(
            "gravity: %s: %d vertical segments in %d image(s), +-%.2f deg",
            key,
            support,
            len(parts),
            np.degrees(sigma),
        )
    return out
