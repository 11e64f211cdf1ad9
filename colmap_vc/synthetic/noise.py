"""Predicted human priors: ground truth degraded like real networks degrade it.

The model (numbers per level in :data:`NOISE_LEVELS`, explained in docs/synthetic.md)
mimics a mesh-recovery network (HMR/EFT-like) and a dense-correspondence network
(DensePose-like), each run independently on every image:

- mesh: another phenotype's proportions (shape error), perturbed joint angles
  (articulation error), a global orientation error about the pelvis, a scale error
  (the person's, shared by its views, and the view's) with the depth scaled alike,
  then the translation refitted so the mesh's joints project onto the person's 2D
  joints, plus a small 2D offset;
- dense map: spatially smooth sliding of the surface coordinates, left/right flips
  of whole limbs, front/back flips of body parts (the back surface behind a pixel),
  dropped blobs;
- 2D keypoints: Gaussian pixel noise and occasional left/right swaps;
- silhouette: the visible mask, eroded or dilated by a pixel or more.
"""

from __future__ import annotations

import dataclasses
import enum
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import cv2
import numpy as np
import pycolmap
from scipy.spatial.transform import Rotation

from .. import raycast
from ..structs import BoolArray, FloatArray, IndexArray, PersonPrior, SurfaceMap

if TYPE_CHECKING:
    from .bodies import BodyModel


NOISE_REVISION = 2
"""Bumped when the code changes what a noise model draws from the same parameters
(2: a left/right flip of the dense map mirrors the hand or foot with its limb; it
left them unflipped before). A scene made at another revision is stale."""


class NoiseLevel(enum.StrEnum):
    """Named prior-noise levels."""

    CLEAN = "clean"
    REALISTIC = "realistic"
    HARD = "hard"
    FITTED = "fitted"


@dataclass(frozen=True, kw_only=True, slots=True)
class NoiseModel:
    """Parameters of the prior noise (ranges are uniform, sigmas Gaussian)."""

    rotation_deg: tuple[float, float]
    """Global orientation error: rotation angle about a random axis, degrees."""
    scale_error: tuple[float, float]
    """Relative body-size error of one view (random sign), on top of the person's
    (``person_size_error``); depth scales alike."""
    shape_blend: tuple[float, float]
    """Weight of another phenotype's rest shape (0: true shape, 1: the other)."""
    joint_sigma_deg: float
    """Articulation error: per joint and axis."""
    offset_px: float
    """2D translation error of the whole mesh, pixels."""
    map_slide_px: float
    """Dense map: amplitude of the smooth sliding of surface coordinates, pixels."""
    lr_flip_prob: float
    """Dense map: probability that a limb pair (arms, legs) is left/right flipped."""
    fb_flip_prob: float
    """Dense map: probability that a body part shows its back surface (front/back)."""
    drop_fraction: float
    """Dense map: fraction of the person's pixels dropped, in blobs."""
    keypoint_sigma_px: float
    """2D keypoint noise, pixels."""
    keypoint_swap_prob: float
    """Probability of a left/right swap of the 2D keypoints of a person."""
    turn_prob: float = 0.0
    """Probability that the whole prior is turned front to back: the estimator took
    a person seen from the back for one facing the camera, so the mesh is turned
    180 deg about the body's vertical axis, the dense map is read off that mesh and
    every left keypoint is labelled right. pose2sim_single: 2 of 20 person views
    (cam02 at t050 and t070, docs/real-data.md)."""
    mask_jitter_px: int
    """Silhouette: erosion or dilation radius, pixels."""
    confidence: tuple[float, float]
    """Reported confidence range."""
    person_size_error: tuple[float, float] = (0.0, 0.0)
    """Relative body-size error shared by every view of one person (random sign,
    :func:`person_size_error`): a network sees a body's proportions, not its size,
    so it takes a tall person for an average one in every image alike."""
    fitted: bool = False
    """The bundled estimator's priors instead (:mod:`colmap_vc.synthetic.fitted`):
    noisy BlazePose landmarks, the Anny body fitted to them, the mask ray-cast on
    it. Only ``landmark_noise_scale``, ``turn_prob``, ``mask_jitter_px`` and
    ``confidence`` apply."""
    landmark_noise_scale: float = 1.0
    """With ``fitted``: a multiple of the landmark noise measured on pose2sim."""


NOISE_LEVELS: dict[NoiseLevel, NoiseModel] = {
    NoiseLevel.CLEAN: NoiseModel(
        rotation_deg=(0.0, 0.0),
        scale_error=(0.0, 0.0),
        shape_blend=(0.0, 0.0),
        joint_sigma_deg=0.0,
        offset_px=0.0,
        map_slide_px=0.0,
        lr_flip_prob=0.0,
        fb_flip_prob=0.0,
        drop_fraction=0.0,
        keypoint_sigma_px=0.0,
        keypoint_swap_prob=0.0,
        mask_jitter_px=0,
        confidence=(1.0, 1.0),
    ),
    NoiseLevel.REALISTIC: NoiseModel(
        rotation_deg=(5.0, 15.0),
        scale_error=(0.0, 0.05),
        person_size_error=(0.03, 0.08),
        shape_blend=(0.3, 0.8),
        joint_sigma_deg=6.0,
        offset_px=2.0,
        map_slide_px=3.0,
        lr_flip_prob=0.1,
        fb_flip_prob=0.05,
        drop_fraction=0.1,
        keypoint_sigma_px=3.0,
        keypoint_swap_prob=0.05,
        turn_prob=0.1,
        mask_jitter_px=1,
        confidence=(0.7, 0.95),
    ),
    NoiseLevel.HARD: NoiseModel(
        rotation_deg=(10.0, 25.0),
        scale_error=(0.0, 0.10),
        person_size_error=(0.05, 0.15),
        shape_blend=(0.6, 1.0),
        joint_sigma_deg=12.0,
        offset_px=5.0,
        map_slide_px=6.0,
        lr_flip_prob=0.25,
        fb_flip_prob=0.15,
        drop_fraction=0.25,
        keypoint_sigma_px=6.0,
        keypoint_swap_prob=0.15,
        turn_prob=0.2,
        mask_jitter_px=3,
        confidence=(0.4, 0.8),
    ),
}
NOISE_LEVELS[NoiseLevel.FITTED] = dataclasses.replace(
    NOISE_LEVELS[NoiseLevel.CLEAN],
    mask_jitter_px=1,
    confidence=(0.7, 0.95),
    person_size_error=NOISE_LEVELS[NoiseLevel.REALISTIC].person_size_error,
    fitted=True,
)
"""The bundled estimator's priors: the fit itself makes every error (the mesh and
map fields stay at ``clean``'s zeros) but the person's size error, which scales
the 3D landmarks it fits; people are masked and scored as at ``realistic``."""


def person_size_error(model: NoiseModel, seed: int, person_id: int) -> float:
    """The relative size error of every view of one person (``person_size_error``):
    drawn from the person's own stream (seed, 3000, person_id), so it does not
    depend on which images see the person, in what order, or on the other people.
    0 for a false detection (a negative id: its body is drawn at random anyway)."""
    low, high = model.person_size_error
    if high <= 0.0 or person_id < 0:
        return 0.0
    rng = np.random.default_rng([seed, 3000, person_id])
    return float(rng.uniform(low, high) * rng.choice([-1.0, 1.0]))


@dataclass(frozen=True, kw_only=True, slots=True)
class PersonView:
    """Ground truth of one person in one image, input of the noise model."""

    person_id: int
    phenotype: int
    pose: int
    body_vertices: FloatArray  # (V, 3) body frame, the true posed body
    cam_from_body: FloatArray  # (3, 4)
    xy_img: FloatArray  # (N, 2) visible pixels of the person
    face_idx: IndexArray  # (N,)
    bary: FloatArray  # (N, 3)
    mask: BoolArray  # (H, W) visible silhouette


def _smooth_field(
    rng: np.random.Generator, shape: tuple[int, int], sigma_px: float
) -> FloatArray:
    """Gaussian-smoothed white noise with unit standard deviation, (H, W)."""
    field = cv2.GaussianBlur(rng.normal(size=shape), (0, 0), sigma_px)
    return field / max(field.std(), 1e-12)


def _random_rotation(rng: np.random.Generator, angle_deg: float) -> FloatArray:
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    return Rotation.from_rotvec(math.radians(angle_deg) * axis).as_matrix()


def _refit_translation(points_cam: FloatArray, target_norm: FloatArray) -> FloatArray:
    """Translation t (3,) making points (K, 3) + t project onto normalized xy (K, 2).

    Linear least squares on (x + tx) - u (z + tz) = 0 and (y + ty) - v (z + tz) = 0.
    """
    k = len(points_cam)
    u, v = target_norm[:, 0], target_norm[:, 1]
    A = np.zeros((2 * k, 3))
    A[:k, 0], A[:k, 2] = 1.0, -u
    A[k:, 1], A[k:, 2] = 1.0, -v
    rhs = np.r_[
        u * points_cam[:, 2] - points_cam[:, 0], v * points_cam[:, 2] - points_cam[:, 1]
    ]
    return np.asarray(np.linalg.lstsq(A, rhs, rcond=None)[0], dtype=np.float64)


def _transform(T: FloatArray, points: FloatArray) -> FloatArray:
    return points @ T[:, :3].T + T[:, 3]


def _predict_mesh(
    bodies: BodyModel,
    view: PersonView,
    camera: pycolmap.Camera,
    model: NoiseModel,
    rng: np.random.Generator,
    size_error: float,
) -> FloatArray:
    """Predicted vertices (V, 3) in the camera frame; ``size_error`` is the
    person's, shared by its views."""
    from .bodies import joints, pose_body

    num_phenotypes = bodies.rest_vertices.shape[0]
    if model.shape_blend[1] > 0 and num_phenotypes > 1:
        other = int(
            rng.choice([p for p in range(num_phenotypes) if p != view.phenotype])
        )
        blend: tuple[int, float] | None = (
            other,
            float(rng.uniform(*model.shape_blend)),
        )
    else:
        blend = None
    delta = None
    if model.joint_sigma_deg > 0:
        # Per-bone scale: the spine and neck chains share one joint's worth of error,
        # helper bones and the root (the global orientation) get none.
        delta = rng.normal(
            0, math.radians(model.joint_sigma_deg), bodies.pose_rotvec.shape[1:]
        )
        delta *= bodies.bone_sigma_scale[:, None]
    body = pose_body(
        bodies, view.phenotype, view.pose, delta_rotvec=delta, shape_blend=blend
    )
    # Scale error: the predicted body's height is off by e (the person's error and
    # this view's), and so is its depth.
    e_view = rng.uniform(*model.scale_error) * rng.choice([-1.0, 1.0])
    e = (1.0 + size_error) * (1.0 + e_view) - 1.0
    height_true = np.ptp(view.body_vertices[:, 2])
    body = body * (height_true / np.ptp(body[:, 2]) * (1.0 + e))
    verts = _transform(view.cam_from_body, body)
    pelvis = joints(bodies, verts)[0]  # joint 0 is the pelvis (bodies README)
    R_err = _random_rotation(rng, rng.uniform(*model.rotation_deg))
    verts = (verts - pelvis) @ R_err.T + pelvis * (1.0 + e)
    # Refit the translation so the predicted joints project onto the true 2D joints,
    # as mesh-recovery networks are trained to (a few pixels of 2D error remain).
    true_joints = joints(bodies, _transform(view.cam_from_body, view.body_vertices))
    target = true_joints[:, :2] / true_joints[:, 2:3]
    verts = verts + _refit_translation(joints(bodies, verts), target)
    z = joints(bodies, verts)[0, 2]
    focal = camera.mean_focal_length()
    shift_px = rng.normal(0, model.offset_px, 2) if model.offset_px > 0 else np.zeros(2)
    verts[:, :2] += shift_px * z / focal
    return verts


def limb_part_ids(names: np.ndarray, limb: str) -> IndexArray:
    """The body parts of both sides of ``limb`` ("arm" or "leg"), the hand or the
    foot included: the chain a left/right flip of the dense map mirrors whole."""
    end = ("hand_left", "hand_right") if limb == "arm" else ("foot_left", "foot_right")
    return np.flatnonzero(
        (np.char.find(names.astype(str), limb) >= 0) | np.isin(names, end)
    )


def _predict_surface_map(
    bodies: BodyModel,
    view: PersonView,
    camera: pycolmap.Camera,
    model: NoiseModel,
    rng: np.random.Generator,
) -> SurfaceMap:
    """DensePose-like noisy surface map from the true one."""
    from .bodies import mirror_surface

    h, w = view.mask.shape
    face_img = np.full((h, w), -1, dtype=np.int64)
    bary_img = np.zeros((h, w, 3))
    px = np.floor(view.xy_img).astype(np.int64)
    face_img[px[:, 1], px[:, 0]] = view.face_idx
    bary_img[px[:, 1], px[:, 0]] = view.bary
    xy, face, bary = view.xy_img, view.face_idx.copy(), view.bary.copy()
    keep = np.ones(len(xy), dtype=bool)
    if model.map_slide_px > 0:
        # Read the true map at a smoothly displaced pixel: correlated sliding.
        dx = model.map_slide_px * _smooth_field(rng, (h, w), 12.0)
        dy = model.map_slide_px * _smooth_field(rng, (h, w), 12.0)
        sx = np.clip(np.round(px[:, 0] + dx[px[:, 1], px[:, 0]]), 0, w - 1).astype(
            np.int64
        )
        sy = np.clip(np.round(px[:, 1] + dy[px[:, 1], px[:, 0]]), 0, h - 1).astype(
            np.int64
        )
        face = face_img[sy, sx]
        bary = bary_img[sy, sx]
        keep &= face >= 0
        face = np.where(keep, face, 0)
    part = bodies.face_part[face]
    names = np.array(bodies.part_names)
    if model.fb_flip_prob > 0:
        flipped_parts = np.flatnonzero(rng.random(len(names)) < model.fb_flip_prob)
        sel = np.flatnonzero(keep & np.isin(part, flipped_parts))
        if len(sel):
            # The back of the body behind the pixel: the ray's last hit on the body.
            verts = _transform(view.cam_from_body, view.body_vertices)
            scene = raycast.build_scene([(verts, bodies.faces)])
            dirs = raycast.rays_cam(camera, xy[sel])
            hits = raycast.all_hits(scene, np.zeros_like(dirs), dirs)
            last = np.r_[hits.ray_idx[1:] != hits.ray_idx[:-1], True]
            rows = sel[hits.ray_idx[last]]
            face[rows] = hits.face_idx[last]
            bary[rows] = raycast.inside_face(hits.bary[last], np.ones(last.sum(), bool))
    if model.lr_flip_prob > 0:
        for limb in ("arm", "leg"):
            if rng.random() < model.lr_flip_prob:
                limb_parts = limb_part_ids(names, limb)
                in_limb = keep & np.isin(bodies.face_part[face], limb_parts)
                face[in_limb], bary[in_limb] = mirror_surface(
                    bodies, face[in_limb], bary[in_limb]
                )
    if model.drop_fraction > 0:
        blob = _smooth_field(rng, (h, w), 8.0)[px[:, 1], px[:, 0]]
        keep &= blob > np.quantile(blob, model.drop_fraction)
    return SurfaceMap(xy_img=xy[keep], face_idx=face[keep], bary=bary[keep])


def _predict_mask(
    view: PersonView, model: NoiseModel, rng: np.random.Generator
) -> BoolArray:
    if model.mask_jitter_px <= 0:
        return view.mask.copy()
    r = int(rng.integers(1, model.mask_jitter_px + 1))
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    op = cv2.dilate if rng.random() < 0.5 else cv2.erode
    return op(view.mask.astype(np.uint8), kernel).astype(bool)


def _left_right(names: tuple[str, ...]) -> IndexArray:
    """Joint i of a person labelled left for right is joint ``[i]``."""
    return np.array(
        [
            names.index(
                n.replace("left", "#").replace("right", "left").replace("#", "right")
            )
            for n in names
        ],
        dtype=np.int64,
    )


def _keypoints(
    bodies: BodyModel,
    view: PersonView,
    camera: pycolmap.Camera,
    pred_vertices: FloatArray,
    model: NoiseModel,
    rng: np.random.Generator,
) -> tuple[FloatArray, FloatArray, BoolArray]:
    """2D joint centres (noisy), 3D joints of the predicted mesh, validity."""
    from .bodies import joints

    true_cam = joints(bodies, _transform(view.cam_from_body, view.body_vertices))
    xy = camera.img_from_cam(true_cam, check_cheirality=False)
    assert xy is not None  # (K, 3) points take the batch overload: never None
    xy = (
        xy + rng.normal(0, model.keypoint_sigma_px, xy.shape)
        if model.keypoint_sigma_px
        else xy
    )
    pred_cam = joints(bodies, pred_vertices)
    if rng.random() < model.keypoint_swap_prob:
        xy = xy[_left_right(bodies.joint_names)]
    valid = (
        (true_cam[:, 2] > 0)
        & (xy[:, 0] >= 0)
        & (xy[:, 1] >= 0)
        & (xy[:, 0] < camera.width)
        & (xy[:, 1] < camera.height)
    )
    return xy, pred_cam, valid


def _turned(bodies: BodyModel, view: PersonView, verts: FloatArray) -> FloatArray:
    """``verts`` turned 180 deg about the body's vertical axis through the pelvis."""
    from .bodies import joints

    up = view.cam_from_body[:, :3] @ np.array([0.0, 0.0, 1.0])  # Anny: +Z is up
    turn = 2.0 * np.outer(up, up) - np.eye(3)  # rotation by pi about `up`
    pelvis = joints(bodies, verts)[0]
    return (verts - pelvis) @ turn.T + pelvis


def _map_of_mesh(
    verts: FloatArray, faces: IndexArray, camera: pycolmap.Camera, xy: FloatArray
) -> SurfaceMap:
    """The dense map a network renders from its own mesh at pixels ``xy``."""
    scene = raycast.build_scene([(verts, faces)])
    dirs = raycast.rays_cam(camera, xy)
    _, face, _, bary = raycast.first_hits(scene, np.zeros_like(dirs), dirs)
    hit = face >= 0
    return SurfaceMap(xy_img=xy[hit], face_idx=face[hit], bary=bary[hit])


def predict_person(
    bodies: BodyModel,
    view: PersonView,
    camera: pycolmap.Camera,
    level: NoiseLevel | NoiseModel,
    rng: np.random.Generator,
    size_error: float = 0.0,
) -> PersonPrior | None:
    """The predicted prior of one person in one image at a noise level (None: the
    ``fitted`` level's fit failed, the estimator reports no one). ``size_error``:
    the person's relative size error at that level (:func:`person_size_error`),
    shared by all its views."""
    model = level if isinstance(level, NoiseModel) else NOISE_LEVELS[NoiseLevel(level)]
    if model.fitted:
        from .fitted import fitted_person

        return fitted_person(
            bodies,
            view,
            camera,
            noise_scale=model.landmark_noise_scale,
            turn_prob=model.turn_prob,
            mask=_predict_mask(view, model, rng),
            confidence=float(rng.uniform(*model.confidence)),
            rng=rng,
            size_error=size_error,
        )
    verts = _predict_mesh(bodies, view, camera, model, rng, size_error)
    turned = model.turn_prob > 0 and rng.random() < model.turn_prob
    if turned:
        verts = _turned(bodies, view, verts)
    kp_xy, kp_cam, kp_valid = _keypoints(bodies, view, camera, verts, model, rng)
    surface_map = _predict_surface_map(bodies, view, camera, model, rng)
    if turned:
        swap = _left_right(bodies.joint_names)
        kp_xy, kp_valid = kp_xy[swap], kp_valid[swap]
        surface_map = _map_of_mesh(verts, bodies.faces, camera, surface_map.xy_img)
    return PersonPrior(
        vertices_cam=verts,
        faces=bodies.faces,
        template="anny",
        person_id=view.person_id,
        confidence=float(rng.uniform(*model.confidence)),
        surface_map=surface_map,
        keypoints_xy=kp_xy,
        keypoints_cam=kp_cam,
        keypoints_valid=kp_valid,
        mask=_predict_mask(view, model, rng),
    )
