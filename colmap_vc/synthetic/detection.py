"""Detection failures: which people a person detector reports in an image, and spurious
people it invents.

A real detector (MediaPipe, a multi-person detector, DensePose) reports some of the
people in an image, anonymously and in no particular order, and now and then a person
who is not there. The model (numbers per level in :data:`DETECTION_LEVELS`, explained
in docs/synthetic.md), per image and per visible person:

- cut by the frame: kept only when at least ``min_landmarks_inside`` of the 12 body
  landmarks (shoulders, elbows, wrists, hips, knees, ankles) project inside the image,
  the rule of the bundled MediaPipe estimator;
- too small: dropped when the landmarks inside span fewer than ``min_size_px``;
- missed: dropped with a probability that rises as the person is small, occluded by
  another person, or partly outside the frame;
- false detection: with probability ``false_prob`` per image, a body that is not there
  (random shape, pose, place and heading) with a surface map over the background.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
import pycolmap

from .. import raycast
from ..estimators import appearance
from ..structs import FloatArray, IndexArray, PersonPrior
from .bodies import BodyModel, joints, pose_body
from .noise import NoiseLevel, PersonView
from .render import FIRST_PERSON

BODY_LANDMARKS: tuple[str, ...] = tuple(
    f"{s}_{j}"
    for j in ("shoulder", "elbow", "wrist", "hip", "knee", "ankle")
    for s in ("left", "right")
)
"""The 12 body landmarks of the cut-by-the-frame rule (Anny joint names)."""


@dataclass(frozen=True, kw_only=True, slots=True)
class DetectionModel:
    """Parameters of the detection-failure model (probabilities per person, image)."""

    min_landmarks_inside: int
    """A person is reported only with at least this many of the 12 body landmarks
    inside the image (0: always)."""
    min_size_px: float
    """A person is reported only when its landmarks inside span at least this many
    pixels (the larger of the x and y extents)."""
    miss_base: float
    """Probability of missing a large, fully visible person."""
    miss_small: float
    """Added miss probability of a person at ``small_px`` or less (linear above)."""
    small_px: float
    """Landmark span below which a person counts as small, pixels."""
    miss_occluded: float
    """Added miss probability per fraction of the 12 landmarks hidden by another person
    (all hidden: this much more)."""
    miss_cut: float
    """Added miss probability per fraction of the 12 landmarks outside the image."""
    miss_max: float
    """Cap of the miss probability."""
    false_prob: float
    """Probability that an image gets one false detection."""


DETECTION_LEVELS: dict[NoiseLevel, DetectionModel] = {
    NoiseLevel.CLEAN: DetectionModel(
        min_landmarks_inside=0,
        min_size_px=0.0,
        miss_base=0.0,
        miss_small=0.0,
        small_px=0.0,
        miss_occluded=0.0,
        miss_cut=0.0,
        miss_max=0.0,
        false_prob=0.0,
    ),
    NoiseLevel.REALISTIC: DetectionModel(
        min_landmarks_inside=8,
        min_size_px=50.0,
        miss_base=0.03,
        miss_small=0.4,
        small_px=100.0,
        miss_occluded=0.8,
        miss_cut=0.5,
        miss_max=0.9,
        false_prob=0.1,
    ),
    NoiseLevel.HARD: DetectionModel(
        min_landmarks_inside=8,
        min_size_px=50.0,
        miss_base=0.08,
        miss_small=0.6,
        small_px=130.0,
        miss_occluded=1.0,
        miss_cut=0.8,
        miss_max=0.95,
        false_prob=0.25,
    ),
}
DETECTION_LEVELS[NoiseLevel.FITTED] = DETECTION_LEVELS[NoiseLevel.REALISTIC]
"""The bundled estimator's priors (:mod:`colmap_vc.synthetic.fitted`) are found by
the same kind of detector as the ``realistic`` level's."""


@dataclass(frozen=True, kw_only=True, slots=True)
class Visibility:
    """How much of one person one camera sees (from the 12 body landmarks)."""

    inside: int  # landmarks projecting inside the image, in front of the camera
    occluded: int  # landmarks inside whose pixel shows another person
    size_px: float  # larger extent of the landmarks inside, pixels


def landmark_visibility(
    bodies: BodyModel,
    view: PersonView,
    camera: pycolmap.Camera,
    geom_idx: IndexArray,
    mesh_index: int,
) -> Visibility:
    """Landmarks of ``view``'s person inside the image and hidden by another person.

    ``geom_idx`` (H, W) is the rendered mesh index per pixel; the person is mesh
    ``mesh_index``, other people are the other indices >= ``FIRST_PERSON``.
    """
    names = list(bodies.joint_names)
    rows = np.array([names.index(n) for n in BODY_LANDMARKS])
    verts = view.body_vertices @ view.cam_from_body[:, :3].T + view.cam_from_body[:, 3]
    pts = joints(bodies, verts)[rows]
    xy = camera.img_from_cam(pts, check_cheirality=False)
    h, w = geom_idx.shape
    inside = (
        (pts[:, 2] > 0)
        & np.isfinite(xy).all(axis=1)
        & (xy[:, 0] >= 0)
        & (xy[:, 1] >= 0)
        & (xy[:, 0] < w)
        & (xy[:, 1] < h)
    )
    px = np.floor(xy[inside]).astype(np.int64)
    seen = geom_idx[px[:, 1], px[:, 0]]
    # Hidden by another person: the pixel shows a person mesh that is not this one.
    occluded = int(((seen >= FIRST_PERSON) & (seen != mesh_index)).sum())
    size = float(np.ptp(xy[inside], axis=0).max()) if inside.sum() >= 2 else 0.0
    return Visibility(inside=int(inside.sum()), occluded=occluded, size_px=size)


def miss_reason(
    vis: Visibility, model: DetectionModel, rng: np.random.Generator
) -> str | None:
    """Why the detector does not report this person, or None when it does.

    Always draws one random number, so the random stream does not depend on the rules.
    """
    u = rng.random()
    n = len(BODY_LANDMARKS)
    if vis.inside < model.min_landmarks_inside:
        return (
            f"cut by the frame ({vis.inside} of {n} body landmarks inside, "
            f"need {model.min_landmarks_inside})"
        )
    if vis.size_px < model.min_size_px:
        return f"too small ({vis.size_px:.0f} px < {model.min_size_px:g} px)"
    small = (
        float(np.clip((model.small_px - vis.size_px) / model.small_px, 0.0, 1.0))
        if model.small_px > 0
        else 0.0
    )
    p = (
        model.miss_base
        + model.miss_small * small
        + model.miss_occluded * vis.occluded / n
        + model.miss_cut * (n - vis.inside) / n
    )
    p = min(p, model.miss_max)
    if u < p:
        return (
            f"missed (p = {p:.2f}: {vis.size_px:.0f} px, {vis.occluded} of {n} "
            f"landmarks occluded, {n - vis.inside} outside)"
        )
    return None


def false_person_view(
    bodies: BodyModel,
    camera: pycolmap.Camera,
    rng: np.random.Generator,
    person_id: int = -1,
) -> PersonView | None:
    """A person that is not there: a random body 2.5-6 m in front of the camera, at a
    random place of the image and heading, seen over whatever the image shows.

    Returns None when the body happens to cover fewer than 200 pixels.
    """
    phenotype = int(rng.integers(bodies.rest_vertices.shape[0]))
    pose = int(rng.integers(bodies.pose_rotvec.shape[0]))
    body = pose_body(bodies, phenotype, pose)
    depth = rng.uniform(2.5, 6.0)
    # A pixel for the pelvis well inside the image, then the ray through it.
    u = rng.uniform(0.2, 0.8) * camera.width
    v = rng.uniform(0.3, 0.7) * camera.height
    ray = camera.cam_from_img(np.array([[u, v]]))[0]
    pelvis_cam = np.r_[ray, 1.0] * depth
    # Upright (body +Z along the image's up, -y of the camera), random heading.
    yaw = rng.uniform(-math.pi, math.pi)
    c, s = math.cos(yaw), math.sin(yaw)
    R_yaw = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    cam_from_upright = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])
    R = cam_from_upright @ R_yaw
    pelvis_body = joints(bodies, body)[0]
    t = pelvis_cam - R @ pelvis_body
    cam_from_body = np.concatenate([R, t[:, None]], axis=1)
    verts = body @ R.T + t
    xy = _project_bbox_pixels(camera, verts)
    if len(xy) == 0:
        return None
    scene = raycast.build_scene([(verts, bodies.faces)])
    dirs = raycast.rays_cam(camera, xy)
    geom, face, _, bary = raycast.first_hits(scene, np.zeros_like(dirs), dirs)
    hit = geom >= 0
    if hit.sum() < 200:
        return None
    mask = np.zeros((camera.height, camera.width), dtype=bool)
    px = np.floor(xy[hit]).astype(np.int64)
    mask[px[:, 1], px[:, 0]] = True
    return PersonView(
        person_id=person_id,
        phenotype=phenotype,
        pose=pose,
        body_vertices=body,
        cam_from_body=cam_from_body,
        xy_img=xy[hit],
        face_idx=face[hit],
        bary=raycast.inside_face(bary, hit)[hit],
        mask=mask,
    )


def _project_bbox_pixels(camera: pycolmap.Camera, verts_cam: FloatArray) -> FloatArray:
    """Pixel centres (N, 2) of the image inside the bounding box of the projection."""
    xy = camera.img_from_cam(verts_cam, check_cheirality=False)
    assert xy is not None  # (N, 3) points take the batch overload: never None
    lo = np.clip(np.floor(xy.min(axis=0)) - 1, 0, [camera.width, camera.height])
    hi = np.clip(np.ceil(xy.max(axis=0)) + 1, 0, [camera.width, camera.height])
    if (hi <= lo).any():
        return np.zeros((0, 2))
    xs = np.arange(int(lo[0]), int(hi[0])) + 0.5
    ys = np.arange(int(lo[1]), int(hi[1])) + 0.5
    gx, gy = np.meshgrid(xs, ys)
    return np.stack([gx.ravel(), gy.ravel()], axis=1)


def with_appearance(
    person: PersonPrior, image_rgb: np.ndarray, joint_names: tuple[str, ...]
) -> PersonPrior:
    """The person's clothing colours, as the bundled estimator measures them.

    The same regions (:mod:`colmap_vc.estimators.appearance`) are cut from the
    prior's own noisy joints and predicted silhouette in the rendered image, so
    the colours carry the prior's errors, other people's occlusions and, for a false
    detection, whatever background it covers.
    """
    if person.keypoints_xy is None or person.keypoints_valid is None:
        return person
    xy = np.zeros((appearance.NUM_LANDMARKS, 2))
    seen = np.zeros(appearance.NUM_LANDMARKS, dtype=bool)
    for name, index in appearance.LANDMARK_INDEX.items():
        j = joint_names.index(name)
        xy[index] = person.keypoints_xy[j]
        seen[index] = person.keypoints_valid[j]
    colours = appearance.describe_person(image_rgb, xy, seen, person.mask)
    return dataclasses.replace(person, appearance=colours)
