"""The Anny body as the fit sees it: BlazePose's landmarks on it, batched posing.

A :class:`FitTemplate` says where BlazePose's 33 landmarks (MediaPipe Pose's layout)
lie on the Anny body: the 12 limb landmarks are Anny joints (joint regressor rows), 7
more (nose, ears, heels, toes) are surface vertices; eyes, mouth and hands are not
used. Posing works on 15 bone groups (a chain such as the spine shares one rotation)
and is batched over poses, so a finite-difference Jacobian costs one FK loop.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pycolmap

from colmap_vc.structs import FloatArray, IndexArray, PersonPrior
from colmap_vc.synthetic import bodies as body_lib
from colmap_vc.synthetic.bodies import BodyModel

TEMPLATE_NAME = "anny"

# fmt: off
BLAZEPOSE_NAMES: tuple[str, ...] = (
    "nose", "left_eye_inner", "left_eye", "left_eye_outer", "right_eye_inner",
    "right_eye", "right_eye_outer", "left_ear", "right_ear", "mouth_left",
    "mouth_right", "left_shoulder", "right_shoulder", "left_elbow", "right_elbow",
    "left_wrist", "right_wrist", "left_pinky", "right_pinky", "left_index",
    "right_index", "left_thumb", "right_thumb", "left_hip", "right_hip", "left_knee",
    "right_knee", "left_ankle", "right_ankle", "left_heel", "right_heel",
    "left_foot_index", "right_foot_index",
)
# fmt: on
"""The 33 BlazePose landmarks; "left" is the person's left."""
NUM_LANDMARKS = len(BLAZEPOSE_NAMES)


def _swapped(name: str) -> str:
    return name.replace("left", "#").replace("right", "left").replace("#", "right")


LEFT_RIGHT_PERM: IndexArray = np.array(
    [BLAZEPOSE_NAMES.index(_swapped(n)) for n in BLAZEPOSE_NAMES], dtype=np.int64
)
"""Landmark i of a relabelled person is landmark ``LEFT_RIGHT_PERM[i]``."""

BODY_LANDMARKS: tuple[str, ...] = tuple(
    f"{s}_{j}"
    for j in ("shoulder", "elbow", "wrist", "hip", "knee", "ankle")
    for s in ("left", "right")
)
"""The 12 landmarks that are Anny joints (same name in ``BodyModel.joint_names``)."""
# Landmarks that are points of the Anny surface: vertices picked on the mean rest body
# (body frame: left is -X, forward +Y, up +Z) by the rules in _surface_vertex.
SURFACE_LANDMARKS = (
    "nose",
    "left_ear",
    "right_ear",
    "left_heel",
    "right_heel",
    "left_foot_index",
    "right_foot_index",
)


def anny_keypoint_names(model: BodyModel) -> tuple[str, ...]:
    """Names of the keypoints of an Anny prior (bundled estimator, synthetic world):
    the model's joints, then the surface landmarks."""
    return (*model.joint_names, *SURFACE_LANDMARKS)


def keypoint_mirror(names: tuple[str, ...]) -> IndexArray:
    """Keypoint i of a person labelled left for right is keypoint ``mirror[i]``."""
    return np.array([names.index(_swapped(n)) for n in names], dtype=np.int64)


def anny_keypoint_mirror(persons: Sequence[PersonPrior]) -> IndexArray | None:
    """The left/right exchange of the keypoints these persons share, when all are
    Anny priors with the same keypoints (the bundled estimator's 24, the synthetic
    world's 17 joints); None otherwise (other templates do not name theirs)."""
    sizes = {len(p.keypoints_xy) for p in persons if p.keypoints_xy is not None}
    if len(sizes) != 1 or any(p.template != TEMPLATE_NAME for p in persons):
        return None
    names = anny_keypoint_names(body_lib.load_bodies())
    (k,) = sizes
    try:
        return keypoint_mirror(names[:k]) if k <= len(names) else None
    except ValueError:  # a counterpart beyond the first k names
        return None


ARM_KEYPOINTS = ("left_elbow", "right_elbow", "left_wrist", "right_wrist")


@functools.lru_cache(maxsize=1)
def _anny_off_arm_keypoints() -> IndexArray:
    names = anny_keypoint_names(body_lib.load_bodies())
    return np.array(
        [i for i, n in enumerate(names) if n not in ARM_KEYPOINTS], dtype=np.int64
    )


def body_axis_points(person: PersonPrior) -> FloatArray:
    """Camera-frame points whose long axis is the person's up: an Anny prior's 3D
    keypoints off the arms (head, trunk, legs: raised or spread arms turn the
    whole mesh's major axis), else the mesh's vertices."""
    k = person.keypoints_cam
    if person.template != TEMPLATE_NAME or k is None:
        return person.vertices_cam
    index = _anny_off_arm_keypoints()
    index = index[index < len(k)]
    return k[index] if len(index) >= 3 else person.vertices_cam


# Bone groups posed by the fit: (name, bones); a chain shares one rotation, split
# evenly among its bones.
GROUPS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("spine", ("spine05", "spine04", "spine03", "spine02", "spine01")),
    ("neck", ("neck01", "neck02", "neck03")),
    ("head", ("head",)),
    *(
        (f"{bone}.{s}", (f"{bone}.{s}",))
        for bone in (
            "clavicle",
            "upperarm01",
            "lowerarm01",
            "upperleg01",
            "lowerleg01",
            "foot",
        )
        for s in ("L", "R")
    ),
)
SEGMENTS = (  # lengths compared by fit.choose_shape
    *((f"{s}_shoulder", f"{s}_elbow") for s in ("left", "right")),
    *((f"{s}_elbow", f"{s}_wrist") for s in ("left", "right")),
    *((f"{s}_hip", f"{s}_knee") for s in ("left", "right")),
    *((f"{s}_knee", f"{s}_ankle") for s in ("left", "right")),
    ("left_shoulder", "right_shoulder"),
    ("left_hip", "right_hip"),
    *((f"{s}_shoulder", f"{s}_hip") for s in ("left", "right")),
)


@dataclass(frozen=True, kw_only=True, slots=True)
class BodyLandmarks:
    """One person's landmarks in BlazePose's 33-point layout."""

    xy_img: FloatArray  # (33, 2) float64 pixels, COLMAP convention
    points_3d: FloatArray  # (33, 3) float64 metres, any rigid frame (e.g. hip-centred)
    visibility: FloatArray  # (33,) float64 in [0, 1]

    def __post_init__(self) -> None:
        for name, shape in (("xy_img", 2), ("points_3d", 3)):
            a = getattr(self, name)
            if a.shape != (NUM_LANDMARKS, shape):
                raise ValueError(f"{name} has shape {a.shape}, expected (33, {shape})")
        if self.visibility.shape != (NUM_LANDMARKS,):
            raise ValueError(
                f"visibility has shape {self.visibility.shape}, want (33,)"
            )

    def relabelled(self) -> BodyLandmarks:
        """The same landmarks with every left/right pair exchanged."""
        p = LEFT_RIGHT_PERM
        return BodyLandmarks(
            xy_img=self.xy_img[p],
            points_3d=self.points_3d[p],
            visibility=self.visibility[p],
        )


@dataclass(frozen=True, slots=True)
class FitTemplate:
    """Data of the Anny body that the fit precomputes once."""

    model: BodyModel
    landmark_idx: IndexArray  # (M,) BlazePose index of each fitted landmark
    vertex_idx: IndexArray  # (U,) vertices the landmarks depend on
    weights: FloatArray  # (M, U) landmark = weights @ vertices[vertex_idx]
    group_bones: tuple[IndexArray, ...]  # (G,) bones of each group
    group_names: tuple[str, ...]
    bone_of_group: IndexArray  # (G,) first bone of each group
    segment_lengths: FloatArray  # (P, S) rest lengths of SEGMENTS per phenotype
    rest_landmarks: FloatArray  # (P, M, 3) rest landmarks per phenotype


def _surface_vertex(
    mean_rest: FloatArray, vpart: IndexArray, model: BodyModel, name: str
) -> int:
    """The vertex of a surface landmark on the mean rest body (rules in the code)."""
    side = "left" if name.startswith("left") else "right"
    sign = -1.0 if side == "left" else 1.0  # the person's left is -X
    if name == "nose":  # most forward vertex of the head
        cand = np.flatnonzero(vpart == model.part_names.index("head"))
        return int(cand[np.argmax(mean_rest[cand, 1])])
    if name.endswith("ear"):  # most lateral vertex of the head
        cand = np.flatnonzero(vpart == model.part_names.index("head"))
        return int(cand[np.argmax(sign * mean_rest[cand, 0])])
    cand = np.flatnonzero(vpart == model.part_names.index(f"foot_{side}"))
    if name.endswith("heel"):  # most backward vertex of the foot
        return int(cand[np.argmin(mean_rest[cand, 1])])
    return int(cand[np.argmax(mean_rest[cand, 1])])  # foot_index: toe tip


@functools.cache
def _default_template() -> FitTemplate:
    return load_template(body_lib.load_bodies())


def load_template(model: BodyModel | None = None) -> FitTemplate:
    """Precompute the fit's view of a body model (default: the committed Anny bodies,
    loaded and prepared once per process)."""
    if model is None:
        return _default_template()
    num_v = model.rest_vertices.shape[1]
    vpart = np.full(num_v, -1, dtype=np.int64)
    for k in range(3):
        vpart[model.faces[:, k]] = model.face_part
    mean_rest = model.rest_vertices.mean(axis=0)
    names = BODY_LANDMARKS + SURFACE_LANDMARKS
    dense = np.zeros((len(names), num_v))
    for m, name in enumerate(names):
        if name in model.joint_names:
            k = model.joint_names.index(name)
            np.add.at(
                dense[m], model.joint_regressor_idx[k], model.joint_regressor_w[k]
            )
        else:
            dense[m, _surface_vertex(mean_rest, vpart, model, name)] = 1.0
    vertex_idx = np.flatnonzero(np.any(dense != 0, axis=0)).astype(np.int64)
    weights = dense[:, vertex_idx]
    rest_landmarks = np.einsum(
        "mu,pui->pmi", weights, model.rest_vertices[:, vertex_idx]
    )
    landmark_idx = np.array([BLAZEPOSE_NAMES.index(n) for n in names], dtype=np.int64)
    pos = {n: i for i, n in enumerate(names)}
    seg = np.array([[pos[a], pos[b]] for a, b in SEGMENTS])
    lengths = np.linalg.norm(
        rest_landmarks[:, seg[:, 0]] - rest_landmarks[:, seg[:, 1]], axis=-1
    )
    bones = {n: i for i, n in enumerate(model.bone_names)}
    group_bones = tuple(
        np.array([bones[b] for b in bs], dtype=np.int64) for _, bs in GROUPS
    )
    return FitTemplate(
        model=model,
        landmark_idx=landmark_idx,
        vertex_idx=vertex_idx,
        weights=weights,
        group_bones=group_bones,
        group_names=tuple(n for n, _ in GROUPS),
        bone_of_group=np.array([g[0] for g in group_bones], dtype=np.int64),
        segment_lengths=lengths,
        rest_landmarks=rest_landmarks,
    )


def rest_shape(
    template: FitTemplate, shape: tuple[int, int, float]
) -> tuple[FloatArray, FloatArray]:
    """(V, 3) rest vertices and (B, 3) rest bone heads of a phenotype blend."""
    p, q, w = shape
    m = template.model
    rest = (1.0 - w) * m.rest_vertices[p] + w * m.rest_vertices[q]
    heads = (1.0 - w) * m.rest_bone_heads[p] + w * m.rest_bone_heads[q]
    return rest, heads


def bone_transforms(
    template: FitTemplate, rest_heads: FloatArray, group_rotvec: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Global bone rotations (..., B, 3, 3) and translations (..., B, 3) of group poses.

    ``group_rotvec`` is (..., G, 3): a batch of poses goes through one FK loop.
    """
    m = template.model
    batch = group_rotvec.shape[:-2]
    rotvec = np.zeros((*batch, len(m.bone_parent), 3))
    for bones, g in zip(
        template.group_bones, range(len(template.group_bones)), strict=True
    ):
        # A chain of n bones turns theta in total.
        rotvec[..., bones, :] = group_rotvec[..., g : g + 1, :] / len(bones)
    local = body_lib.rotvec_to_matrix(rotvec)
    rot = np.zeros_like(local)
    heads = np.zeros((*batch, len(m.bone_parent), 3))
    for c, p in enumerate(m.bone_parent):  # FK over ~40 bones, batched over poses
        if p < 0:
            rot[..., c, :, :], heads[..., c, :] = local[..., c, :, :], rest_heads[c]
        else:
            rot[..., c, :, :] = rot[..., p, :, :] @ local[..., c, :, :]
            heads[..., c, :] = heads[..., p, :] + rot[..., p, :, :] @ (
                rest_heads[c] - rest_heads[p]
            )
    return rot, heads - np.einsum("...bij,bj->...bi", rot, rest_heads)


def _skin(
    template: FitTemplate,
    rest: FloatArray,
    rot: FloatArray,
    trans: FloatArray,
    vertex_idx: IndexArray | slice,
) -> FloatArray:
    """LBS of the vertices ``vertex_idx`` of a (V, 3) rest mesh, batched like rot."""
    m = template.model
    sidx, sw = m.skin_idx[vertex_idx], m.skin_w[vertex_idx]
    moved = np.einsum("...vkij,vj->...vki", rot[..., sidx, :, :], rest[vertex_idx])
    moved += trans[..., sidx, :]
    return np.einsum("vk,...vki->...vi", sw, moved)


@dataclass(frozen=True, slots=True)
class LandmarkBasis:
    """Landmarks as linear functions of the bone transforms, for one rest shape.

    LBS is linear in the bone transforms (R_b, t_b) and the landmarks are linear in
    the vertices, so landmark m = sum_b R_b a[m, b] + c[m, b] t_b.
    """

    a: FloatArray  # (M, B, 3)
    c: FloatArray  # (M, B)
    rest_heads: FloatArray  # (B, 3)


def landmark_basis(
    template: FitTemplate, shape: tuple[int, int, float]
) -> LandmarkBasis:
    """The landmarks of a phenotype blend as linear functions of the bones."""
    rest, rest_heads = rest_shape(template, shape)
    m, u = template.model, template.vertex_idx
    per_bone = np.zeros((len(u), len(m.bone_parent)))  # (U, B) skin weight of bone
    np.add.at(per_bone, (np.arange(len(u))[:, None], m.skin_idx[u]), m.skin_w[u])
    wb = template.weights[:, :, None] * per_bone[None]  # (M, U, B)
    return LandmarkBasis(
        a=np.einsum("mub,ui->mbi", wb, rest[u]), c=wb.sum(axis=1), rest_heads=rest_heads
    )


def pose_landmarks(
    template: FitTemplate, basis: LandmarkBasis, group_rotvec: FloatArray
) -> FloatArray:
    """(..., M, 3) body-frame landmarks of (..., G, 3) group poses."""
    rot, trans = bone_transforms(template, basis.rest_heads, group_rotvec)
    return np.einsum("...bij,mbj->...mi", rot, basis.a) + np.einsum(
        "mb,...bi->...mi", basis.c, trans
    )


def posed_vertices(
    template: FitTemplate, shape: tuple[int, int, float], group_rotvec: FloatArray
) -> FloatArray:
    """(V, 3) body-frame vertices of a phenotype blend in a group pose."""
    rest, rest_heads = rest_shape(template, shape)
    rot, trans = bone_transforms(template, rest_heads, group_rotvec)
    return _skin(template, rest, rot, trans, slice(None))


def landmark_index(name: str) -> int:
    """Row of a landmark name in BLAZEPOSE_NAMES."""
    return BLAZEPOSE_NAMES.index(name)


def project_clamped(camera: pycolmap.Camera, points_cam: FloatArray) -> FloatArray:
    """Pixels (..., 2) of camera-frame points (..., 3); z is clamped to >= 1 mm."""
    p = points_cam.reshape(-1, 3).copy()
    p[:, 2] = np.maximum(p[:, 2], 1e-3)
    xy = np.asarray(camera.img_from_cam(p, check_cheirality=False))
    return xy.reshape(*points_cam.shape[:-1], 2)


def landmarks_from_mesh(
    template: FitTemplate,
    vertices_body: FloatArray,
    cam_from_body: FloatArray,
    camera: pycolmap.Camera,
) -> BodyLandmarks:
    """Exact landmarks of a posed Anny mesh, as an estimator would report them.

    2D: the landmarks projected; 3D: in the camera's orientation, centred between the
    hips (MediaPipe's world frame); visibility 1 for the 19 fitted landmarks and 0
    for the others (eyes, mouth, hands), whose coordinates are copied from the nose
    and the wrists.
    """
    p_body = template.weights @ np.asarray(vertices_body)[template.vertex_idx]
    p_cam = p_body @ cam_from_body[:, :3].T + cam_from_body[:, 3]
    # Fill all 33 rows: unfitted landmarks borrow a nearby fitted one (visibility 0).
    src = {n: n for n in BLAZEPOSE_NAMES}
    src.update({n: "nose" for n in BLAZEPOSE_NAMES[1:11] if "ear" not in n})
    src.update({n: f"{n.split('_')[0]}_wrist" for n in BLAZEPOSE_NAMES[17:23]})
    row = {int(b): m for m, b in enumerate(template.landmark_idx)}
    take = np.array([row[landmark_index(src[n])] for n in BLAZEPOSE_NAMES])
    vis = np.zeros(NUM_LANDMARKS)
    vis[template.landmark_idx] = 1.0
    p3 = p_cam[take]
    hips = 0.5 * (p3[landmark_index("left_hip")] + p3[landmark_index("right_hip")])
    return BodyLandmarks(
        xy_img=camera.img_from_cam(p3, check_cheirality=False),
        points_3d=p3 - hips,
        visibility=vis,
    )
