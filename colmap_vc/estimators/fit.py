"""Fit the Anny body to one person's 2D + 3D body landmarks in a known camera.

Input: the 33 landmarks of BlazePose (MediaPipe Pose's layout; any estimator can fill
it) as pixels (COLMAP convention), metric 3D points in an unknown rigid frame
(MediaPipe's hip-centred "world" landmarks) and a visibility per landmark (see
:mod:`colmap_vc.estimators.body`). Output: the Anny mesh in the camera frame
(template ``"anny"``), its 17 joints and fit diagnostics; :mod:`.prior` turns it into
a :class:`~colmap_vc.structs.PersonPrior`.

The fit, in order (all numpy + scipy, no MediaPipe):

1. **Left/right.** The person's facing direction from the labels (left-right axis x up,
   from the shoulders and from the hips) must agree with the one the face (ears ->
   nose) and the feet (heel -> toe) point to; if both disagree, every left/right pair
   is relabelled (:func:`fix_left_right`).
2. **Shape.** The phenotype, or the blend of two, whose limb and torso lengths best
   match the 3D landmarks (:func:`choose_shape`). The body size sets the metric depth.
3. **Pose.** The rest body is aligned to the 3D torso (Kabsch), then each limb bone is
   turned by the smallest rotation that points it at its next landmark.
4. **Placement.** PnP (SQPnP on undistorted points) of the posed landmarks of the body
   on their pixels gives ``cam_from_body``.
5. **Refinement.** One robust least-squares over the camera pose, the rigid alignment to
   the 3D landmarks and 15 bone groups (spine and neck chains share one rotation),
   minimising 2D reprojection (pixels) and 3D (metres) residuals with a weak pose prior.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass

import cv2
import numpy as np
import pycolmap
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from colmap_vc.estimators.body import (
    BLAZEPOSE_NAMES,
    SEGMENTS,
    BodyLandmarks,
    FitTemplate,
    LandmarkBasis,
    bone_transforms,
    landmark_basis,
    landmark_index,
    load_template,
    pose_landmarks,
    posed_vertices,
    project_clamped,
)
from colmap_vc.structs import BoolArray, FloatArray, IndexArray
from colmap_vc.synthetic import bodies as body_lib

logger = logging.getLogger(__name__)

# Limb bones aimed at their next landmark in the initial pose: (group, from, to).
_AIM = tuple(
    (f"{bone}.{s[0].upper()}", f"{s}_{a}", f"{s}_{b}")
    for bone, a, b in (
        ("upperarm01", "shoulder", "elbow"),
        ("lowerarm01", "elbow", "wrist"),
        ("upperleg01", "hip", "knee"),
        ("lowerleg01", "knee", "ankle"),
        ("foot", "heel", "foot_index"),
    )
    for s in ("left", "right")
)
_TORSO = ("left_shoulder", "right_shoulder", "left_hip", "right_hip")


@dataclass(frozen=True, kw_only=True, slots=True)
class FitOptions:
    """Options of :func:`fit_body`."""

    min_visibility: float = 0.5
    """Landmarks below this visibility are not used as 2D evidence."""
    sigma_px: float = 4.0
    """Expected 2D landmark error, pixels (weight of the reprojection residuals)."""
    sigma_3d_m: float = 0.04
    """Expected 3D landmark error, metres (weight of the 3D residuals)."""
    sigma_limb_rad: float = 1.0
    """Prior on the limb rotations' change from the initial (aimed) pose, radians."""
    sigma_torso_rad: float = 0.35
    """Prior on spine, neck, head and clavicle rotations (from the rest pose)."""
    fix_left_right: bool = True
    """Relabel left/right when the labels contradict the face and feet."""
    min_left_right_cos: float = 0.3
    """Relabel only when the facing directions disagree by this cosine or more."""
    phenotype: int | None = None
    """Force this phenotype (row of ``BodyModel.phenotype_names``) with no blend."""
    max_iterations: int = 60
    """Function evaluations of the refinement, in units of the parameter count."""


@dataclass(frozen=True, kw_only=True, slots=True)
class FittedBody:
    """An Anny body fitted to one person in one camera."""

    vertices_cam: FloatArray  # (V, 3) float64 metres, camera frame (OpenCV axes)
    joints_cam: FloatArray  # (17, 3) float64, Anny joints (BodyModel.joint_names)
    cam_from_body: FloatArray  # (3, 4) float64, body frame of the rest skeleton
    shape: tuple[int, int, float]  # phenotype p, phenotype q, blend weight of q
    group_rotvec: FloatArray  # (G, 3) float64 rad, local rotation of each bone group
    landmark_xy: FloatArray  # (M, 2) float64, the fitted landmarks projected
    landmark_idx: IndexArray  # (M,) int64, their BlazePose indices
    used_2d: BoolArray  # (M,) bool, which were 2D evidence
    reprojection_error_px: FloatArray  # (M,) float64
    error_3d_m: FloatArray  # (M,) float64, after the rigid alignment
    relabelled: bool  # left/right labels were exchanged before the fit
    landmarks: BodyLandmarks  # the landmarks as fitted (relabelled when relabelled)


def _kabsch(src: FloatArray, dst: FloatArray) -> tuple[FloatArray, FloatArray]:
    """R, t minimising |R src + t - dst| over rows (N >= 3, not collinear)."""
    cs, cd = src.mean(axis=0), dst.mean(axis=0)
    u, _, vt = np.linalg.svd((src - cs).T @ (dst - cd))
    d = np.sign(np.linalg.det(vt.T @ u.T))
    rot = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return rot, cd - rot @ cs


def _min_rotation(a: FloatArray, b: FloatArray) -> FloatArray:
    """The smallest rotation (3, 3) turning direction a onto direction b."""
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    axis = np.cross(a, b)
    s, c = np.linalg.norm(axis), float(a @ b)
    if s < 1e-9:  # parallel: identity; antiparallel: half-turn about any normal
        if c > 0:
            return np.eye(3)
        n = np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0])
        return Rotation.from_rotvec(np.pi * n / np.linalg.norm(n)).as_matrix()
    return Rotation.from_rotvec(axis / s * np.arctan2(s, c)).as_matrix()


def facing_cosines(landmarks: BodyLandmarks) -> tuple[float, float]:
    """Cosines between the facing directions of the labels and of the face and feet.

    Labels: (left - right) x up, once from the shoulders and once from the hips (the
    person's left is -X and forward is +Y in Anny's frame: forward = left x up). Face
    and feet: ears -> nose plus heels -> toes, horizontal components. Negative: those
    labels are mirrored. 0 when a direction is undefined.
    """
    p = landmarks.points_3d
    g = {n: p[landmark_index(n)] for n in BLAZEPOSE_NAMES}
    up = g["left_shoulder"] + g["right_shoulder"] - g["left_hip"] - g["right_hip"]
    up_n = up / max(np.linalg.norm(up), 1e-9)
    cue = g["nose"] - 0.5 * (g["left_ear"] + g["right_ear"])
    cue = cue / max(np.linalg.norm(cue), 1e-9)
    for s in ("left", "right"):
        foot = g[f"{s}_foot_index"] - g[f"{s}_heel"]
        cue = cue + 0.5 * foot / max(np.linalg.norm(foot), 1e-9)
    cue = cue - (cue @ up_n) * up_n
    out = []
    for part in ("shoulder", "hip"):
        facing = np.cross(g[f"left_{part}"] - g[f"right_{part}"], up)
        facing = facing - (facing @ up_n) * up_n
        na, nb = np.linalg.norm(facing), np.linalg.norm(cue)
        out.append(0.0 if na < 1e-9 or nb < 1e-9 else float(facing @ cue / (na * nb)))
    return out[0], out[1]


def facing_cosine(landmarks: BodyLandmarks) -> float:
    """The larger of :func:`facing_cosines` (negative: the whole body is mirrored)."""
    return max(facing_cosines(landmarks))


def fix_left_right(
    landmarks: BodyLandmarks, options: FitOptions | None = None
) -> tuple[BodyLandmarks, bool]:
    """Relabel left/right when the labels of the whole body contradict face and feet.

    Rule: if :func:`facing_cosine` < ``-options.min_left_right_cos`` (the shoulders
    *and* the hips face away from where the face and feet point), exchange every
    left/right pair, in 2D and 3D together. A partial contradiction (only the
    shoulders, or only the hips) is left alone: on real photos it comes from a swap
    of one part or from a wrong 3D face direction, which relabelling the whole body
    makes worse (pose2sim t050, docs/real-data.md); ``augment`` handles part swaps
    across views. Returns the landmarks and whether they were relabelled.
    """
    options = options or FitOptions()
    if (
        options.fix_left_right
        and facing_cosine(landmarks) < -options.min_left_right_cos
    ):
        return landmarks.relabelled(), True
    return landmarks, False


def choose_shape(
    template: FitTemplate, landmarks: BodyLandmarks, options: FitOptions | None = None
) -> tuple[int, int, float]:
    """The phenotype blend (p, q, w) whose segment lengths best fit the 3D landmarks.

    Candidates: each phenotype and the blends of two at w = 1/4, 1/2, 3/4; the score is
    the visibility-weighted squared error of the lengths in ``SEGMENTS``.
    """
    options = options or FitOptions()
    if options.phenotype is not None:
        return (options.phenotype, options.phenotype, 0.0)
    ends = np.array([[landmark_index(a), landmark_index(b)] for a, b in SEGMENTS])
    p3 = landmarks.points_3d
    observed = np.linalg.norm(p3[ends[:, 0]] - p3[ends[:, 1]], axis=1)
    w_seg = landmarks.visibility[ends].min(axis=1).clip(0.05, 1.0)
    lengths = template.segment_lengths
    cands = _shape_candidates(len(lengths))
    pq = np.array([(p, q) for p, q, _ in cands])
    w = np.array([c[2] for c in cands])[:, None]
    model_len = (1.0 - w) * lengths[pq[:, 0]] + w * lengths[pq[:, 1]]
    score = ((model_len - observed) ** 2 * w_seg).sum(axis=1)
    return cands[int(np.argmin(score))]


def _initial_pose(
    template: FitTemplate, basis: LandmarkBasis, target_3d: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Group rotations aimed at the 3D landmarks (M, 3); the body -> 3D alignment."""
    pos = {int(b): m for m, b in enumerate(template.landmark_idx)}
    theta = np.zeros((len(template.group_bones), 3))
    rest_lm = pose_landmarks(template, basis, theta)
    torso = [pos[landmark_index(n)] for n in _TORSO]
    rot, t = _kabsch(rest_lm[torso], target_3d[torso])
    target_body = (target_3d - t) @ rot  # rot^T (target - t), row-wise
    groups = {n: g for g, n in enumerate(template.group_names)}
    parent = template.model.bone_parent
    for group, a, b in _AIM:  # parents before children
        g = groups[group]
        ia, ib = pos[landmark_index(a)], pos[landmark_index(b)]
        current = pose_landmarks(template, basis, theta)
        g_p = bone_transforms(template, basis.rest_heads, theta)[0][
            parent[template.bone_of_group[g]]
        ]
        # Turn the bone about its head (in the body frame) onto the target direction.
        turn = _min_rotation(
            current[ib] - current[ia], target_body[ib] - target_body[ia]
        )
        local = g_p.T @ turn @ g_p @ body_lib.rotvec_to_matrix(theta[g])
        theta[g] = Rotation.from_matrix(local).as_rotvec()
    return theta, np.column_stack([rot, t])


def _pnp(
    camera: pycolmap.Camera, points_body: FloatArray, xy_img: FloatArray
) -> FloatArray | None:
    """cam_from_body (3, 4) by SQPnP on undistorted points; None on failure."""
    # cam_from_img removes the distortion: normalized points with an identity K.
    norm = np.asarray(camera.cam_from_img(xy_img))
    try:
        ok, rvec, tvec = cv2.solvePnP(
            points_body.reshape(-1, 1, 3),
            norm.reshape(-1, 1, 2),
            np.eye(3),
            None,
            flags=cv2.SOLVEPNP_SQPNP,
        )
    except cv2.error:  # degenerate input (e.g. all points on a line)
        return None
    if not ok:
        return None
    rot = Rotation.from_rotvec(rvec.ravel()).as_matrix()
    return np.column_stack([rot, tvec.ravel()])


@dataclass(frozen=True, slots=True)
class _Problem:
    """The refinement's data: x = [cam rotvec, cam t, align rotvec, align t, theta]."""

    template: FitTemplate
    camera: pycolmap.Camera
    xy: FloatArray  # (M2, 2) 2D evidence
    use_2d: BoolArray  # (M,)
    w2: FloatArray  # (M2, 1)
    target_3d: FloatArray  # (M, 3)
    w3: FloatArray  # (M, 1)
    prior_centre: FloatArray  # (G, 3)
    sigma_g: FloatArray  # (G,)

    def residuals(self, basis: LandmarkBasis, x: FloatArray) -> FloatArray:
        """(N, R) residuals of a batch x (N, D)."""
        num = len(x)
        cam_r = Rotation.from_rotvec(x[:, 0:3]).as_matrix()
        align_r = Rotation.from_rotvec(x[:, 6:9]).as_matrix()
        theta = x[:, 12:].reshape(num, -1, 3)
        p = pose_landmarks(self.template, basis, theta)
        pc = np.einsum("nij,nmj->nmi", cam_r, p[:, self.use_2d]) + x[:, None, 3:6]
        r2 = (project_clamped(self.camera, pc) - self.xy) * self.w2
        pa = np.einsum("nij,nmj->nmi", align_r, p) + x[:, None, 9:12]
        r3 = (pa - self.target_3d) * self.w3
        rp = (theta - self.prior_centre) / self.sigma_g[:, None]
        return np.concatenate(
            [r2.reshape(num, -1), r3.reshape(num, -1), rp.reshape(num, -1)], axis=1
        )

    def solve(self, basis: LandmarkBasis, x0: FloatArray, max_nfev: int) -> FloatArray:
        """Robust least squares from x0 with a batched forward-difference Jacobian."""
        step = 1e-6  # radians and metres alike

        def jac(x: FloatArray) -> FloatArray:
            batch = np.concatenate([x[None], x + step * np.eye(len(x))])
            r = self.residuals(basis, batch)
            return ((r[1:] - r[0]) / step).T

        sol = least_squares(
            lambda x: self.residuals(basis, x[None])[0],
            x0,
            jac=jac,
            loss="soft_l1",
            f_scale=2.0,
            x_scale="jac",
            max_nfev=max_nfev,
            tr_solver="lsmr",
        )
        logger.debug("fit: %d evaluations, cost %.4g", sol.nfev, sol.cost)
        return np.asarray(sol.x)


def _shape_candidates(num_p: int) -> list[tuple[int, int, float]]:
    """Each phenotype, and the blends of two at w = 1/4, 1/2, 3/4."""
    cands = [(p, p, 0.0) for p in range(num_p)]
    cands += [
        (p, q, w)
        for p in range(num_p)
        for q in range(p + 1, num_p)
        for w in (0.25, 0.5, 0.75)
    ]
    return cands


def _reshape_by_pose(
    template: FitTemplate, theta: FloatArray, target_3d: FloatArray, w3: FloatArray
) -> tuple[int, int, float]:
    """The shape whose landmarks in pose theta best fit the 3D landmarks (Kabsch)."""
    best, best_err = (0, 0, 0.0), np.inf
    for cand in _shape_candidates(template.model.num_phenotypes):  # ~50 candidates
        p = pose_landmarks(template, landmark_basis(template, cand), theta)
        rot, t = _kabsch(p, target_3d)
        err = float(np.sum(((p @ rot.T + t - target_3d) * w3) ** 2))
        if err < best_err:
            best, best_err = cand, err
    return best


def fit_body(
    landmarks: BodyLandmarks,
    camera: pycolmap.Camera,
    template: FitTemplate | None = None,
    options: FitOptions | None = None,
) -> FittedBody:
    """Fit the Anny body to a person's landmarks in a known camera (module doc).

    Raises:
        ValueError: fewer than 6 usable 2D landmarks, or under 3 of the 4 torso
            landmarks in 2D, or PnP fails.
    """
    options = options or FitOptions()
    template = template or load_template()
    landmarks, relabelled = fix_left_right(landmarks, options)
    lm_idx = template.landmark_idx
    vis = landmarks.visibility[lm_idx]
    xy = landmarks.xy_img[lm_idx]
    inside = (
        np.isfinite(xy).all(axis=1)
        & (xy[:, 0] >= 0)
        & (xy[:, 1] >= 0)
        & (xy[:, 0] <= camera.width)
        & (xy[:, 1] <= camera.height)
    )
    use_2d = inside & (vis >= options.min_visibility)
    torso_2d = sum(bool(use_2d[list(lm_idx).index(landmark_index(n))]) for n in _TORSO)
    if use_2d.sum() < 6 or torso_2d < 3:
        raise ValueError(
            f"too few usable 2D landmarks ({int(use_2d.sum())} of {len(lm_idx)}, "
            f"{torso_2d} of 4 torso)"
        )
    target_3d = landmarks.points_3d[lm_idx]
    is_torso_group = np.array(
        [
            n.split(".")[0] in ("spine", "neck", "head", "clavicle")
            for n in template.group_names
        ]
    )
    sigma_g = np.where(is_torso_group, options.sigma_torso_rad, options.sigma_limb_rad)
    w3 = np.sqrt(vis.clip(0.2, 1.0))[:, None] / options.sigma_3d_m
    problem = _Problem(
        template=template,
        camera=camera,
        xy=xy[use_2d],
        use_2d=use_2d,
        w2=np.sqrt(vis[use_2d].clip(0.2, 1.0))[:, None] / options.sigma_px,
        target_3d=target_3d,
        w3=w3,
        prior_centre=np.zeros((len(sigma_g), 3)),
        sigma_g=sigma_g,
    )

    shape = choose_shape(template, landmarks, options)
    theta_prev: FloatArray | None = None
    for attempt in range(2):  # 2nd pass: shape re-chosen with the fitted pose
        basis = landmark_basis(template, shape)
        theta0, align0 = _initial_pose(template, basis, target_3d)
        theta = theta0 if theta_prev is None else theta_prev
        # The limbs' prior is centred on their aimed pose, the torso's on rest.
        centre = np.where(is_torso_group[:, None], 0.0, theta0)
        problem = dataclasses.replace(problem, prior_centre=centre)
        body_lm = pose_landmarks(template, basis, theta)
        cam0 = _pnp(camera, body_lm[use_2d], xy[use_2d])
        if cam0 is None or (body_lm @ cam0[:, :3].T + cam0[:, 3])[:, 2].min() <= 0:
            raise ValueError("PnP failed or put the body behind the camera")
        x0 = np.concatenate(
            [
                Rotation.from_matrix(cam0[:, :3]).as_rotvec(),
                cam0[:, 3],
                Rotation.from_matrix(align0[:, :3]).as_rotvec(),
                align0[:, 3],
                theta.ravel(),
            ]
        )
        x = problem.solve(basis, x0, options.max_iterations * len(x0))
        theta = theta_prev = x[12:].reshape(-1, 3)
        if attempt == 1 or options.phenotype is not None:
            break
        new_shape = _reshape_by_pose(template, theta, target_3d, w3)
        if new_shape == shape:
            break
        shape = new_shape

    cam = np.column_stack([Rotation.from_rotvec(x[0:3]).as_matrix(), x[3:6]])
    align = np.column_stack([Rotation.from_rotvec(x[6:9]).as_matrix(), x[9:12]])
    verts_cam = posed_vertices(template, shape, theta) @ cam[:, :3].T + cam[:, 3]
    p = pose_landmarks(template, basis, theta)
    proj = project_clamped(camera, p @ cam[:, :3].T + cam[:, 3])
    return FittedBody(
        vertices_cam=verts_cam,
        joints_cam=body_lib.joints(template.model, verts_cam),
        cam_from_body=cam,
        shape=shape,
        group_rotvec=theta,
        landmark_xy=proj,
        landmark_idx=lm_idx.copy(),
        used_2d=use_2d,
        reprojection_error_px=np.linalg.norm(proj - xy, axis=1),
        error_3d_m=np.linalg.norm(p @ align[:, :3].T + align[:, 3] - target_3d, axis=1),
        relabelled=relabelled,
        landmarks=landmarks,
    )
