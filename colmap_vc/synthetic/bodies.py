"""Articulated human bodies exported from Anny: loader and numpy poser (no torch).

The bodies live in ``colmap_vc/data/anny_bodies.{npz,json}`` (package data, written by
``scripts/export_bodies.py``, see the README there). All bodies share one triangle
topology, so a surface point named by (face, barycentric coordinates) is the same point
of the body for every phenotype and pose.

Body frame (every array): metres, +Z up, the person faces +Y, so the person's left is
-X. A posed body is grounded: its lowest vertex has z = 0 and its pelvis joint (the
head of the root bone) is at x = y = 0.

Skinning is plain linear blend skinning (LBS) with 4 bones per vertex. A pose is a
local rotation per bone (axis-angle, ``pose_rotvec``): the global rotation of bone c is
``G_c = G_parent @ L_c``, ``L_c`` being expressed in the body frame *at rest*, so all
zeros is the rest pose (Anny's A-pose). Bone c maps a rest point x to
``G_c @ (x - h_c) + g_c``, with ``h_c`` its rest head and ``g_c`` its posed head.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from importlib.resources import files
from pathlib import Path

import numpy as np

from colmap_vc.structs import FloatArray, IndexArray

logger = logging.getLogger(__name__)

DEFAULT_PATH = Path(str(files("colmap_vc") / "data" / "anny_bodies.npz"))
"""The package's own ``colmap_vc/data/anny_bodies.npz`` (package data, so a plain
``pip install`` has it), next to its JSON description."""


@dataclass(frozen=True, kw_only=True, slots=True)
class BodyModel:
    """Phenotypes x poses of the Anny body on one shared topology, with an LBS rig.

    P phenotypes, Q poses, V vertices, F faces, B bones, K joints, S template samples.
    """

    faces: IndexArray  # (F, 3) int64, counter-clockwise seen from outside
    posed_vertices: FloatArray  # (P, Q, V, 3) float64 m, body frame, grounded
    rest_vertices: FloatArray  # (P, V, 3) float64 m, rest (A-)pose, grounded
    face_part: IndexArray  # (F,) int64, index into part_names
    part_names: tuple[str, ...]
    phenotype_names: tuple[str, ...]
    pose_names: tuple[str, ...]
    template_face_idx: IndexArray  # (S,) int64, ~evenly spread surface samples
    template_bary: FloatArray  # (S, 3) float64
    joint_names: tuple[str, ...]  # joint 0 is the pelvis
    joint_regressor_idx: IndexArray  # (K, n) int64 vertex indices
    joint_regressor_w: FloatArray  # (K, n) float64, rows sum to 1
    bone_names: tuple[str, ...]
    skin_idx: IndexArray  # (V, 4) int64 bone indices
    skin_w: FloatArray  # (V, 4) float64, rows sum to 1
    bone_parent: IndexArray  # (B,) int64, -1 for the root; parents come first
    rest_bone_heads: FloatArray  # (P, B, 3) float64 m, rest pose, same frame as rest
    pose_rotvec: FloatArray  # (Q, B, 3) float64 rad, local rotations (see module doc)
    # (B,) suggested scale of a per-joint articulation error: chains (spine, neck) share
    # one joint's error, twist/helper bones and the root get 0 (see the README).
    bone_sigma_scale: FloatArray
    face_mirror: IndexArray  # (F,) int64, the left/right mirror face
    face_mirror_perm: IndexArray  # (F, 3) int64, bary of the mirror = bary[perm]

    def __post_init__(self) -> None:
        num_p, num_q, num_v = self.posed_vertices.shape[:3]
        num_f, num_b = len(self.faces), len(self.bone_parent)
        expected = {
            "faces": (self.faces, (num_f, 3)),
            "posed_vertices": (self.posed_vertices, (num_p, num_q, num_v, 3)),
            "rest_vertices": (self.rest_vertices, (num_p, num_v, 3)),
            "face_part": (self.face_part, (num_f,)),
            "template_bary": (self.template_bary, (len(self.template_face_idx), 3)),
            "joint_regressor_w": (
                self.joint_regressor_w,
                self.joint_regressor_idx.shape,
            ),
            "skin_idx": (self.skin_idx, (num_v, 4)),
            "skin_w": (self.skin_w, (num_v, 4)),
            "rest_bone_heads": (self.rest_bone_heads, (num_p, num_b, 3)),
            "pose_rotvec": (self.pose_rotvec, (num_q, num_b, 3)),
            "bone_sigma_scale": (self.bone_sigma_scale, (num_b,)),
            "face_mirror": (self.face_mirror, (num_f,)),
            "face_mirror_perm": (self.face_mirror_perm, (num_f, 3)),
        }
        for name, (array, shape) in expected.items():
            if array.shape != shape:
                raise ValueError(f"{name} has shape {array.shape}, expected {shape}")
        counts = {
            "part_names": (self.part_names, int(self.face_part.max()) + 1),
            "phenotype_names": (self.phenotype_names, num_p),
            "pose_names": (self.pose_names, num_q),
            "joint_names": (self.joint_names, len(self.joint_regressor_idx)),
            "bone_names": (self.bone_names, num_b),
        }
        for name, (names, count) in counts.items():
            if len(names) < count or (name != "part_names" and len(names) != count):
                raise ValueError(f"{name} has {len(names)} entries, expected {count}")
        if np.any(self.bone_parent >= np.arange(num_b)):
            raise ValueError(f"bone_parent={self.bone_parent} must list parents first")

    @property
    def num_phenotypes(self) -> int:
        """P."""
        return int(self.rest_vertices.shape[0])

    @property
    def num_poses(self) -> int:
        """Q."""
        return int(self.pose_rotvec.shape[0])


def load_bodies(path: Path | None = None) -> BodyModel:
    """Load ``anny_bodies.npz`` and its ``.json`` (default: the committed export).

    Raises:
        FileNotFoundError: if either file is missing.
    """
    path = Path(path) if path is not None else DEFAULT_PATH
    json_path = path.with_suffix(".json")
    for p in (path, json_path):
        if not p.is_file():
            raise FileNotFoundError(
                f"body file {p} not found; regenerate it with `make bodies` "
                "(see data/synthetic/bodies/README.md); a broken install? "
                "reinstall colmap-vc"
            )
    info = json.loads(json_path.read_text())
    with np.load(path, allow_pickle=False) as z:
        a = {k: z[k] for k in z.files}
    scale = float(a["vertices_scale"])
    model = BodyModel(
        faces=a["faces"].astype(np.int64),
        posed_vertices=a["vertices_q"].astype(np.float64) * scale,
        rest_vertices=a["rest_vertices"].astype(np.float64),
        face_part=a["face_part"].astype(np.int64),
        part_names=tuple(info["part_names"]),
        phenotype_names=tuple(p["name"] for p in info["phenotypes"]),
        pose_names=tuple(p["name"] for p in info["poses"]),
        template_face_idx=a["template_face_idx"].astype(np.int64),
        template_bary=a["template_bary"].astype(np.float64),
        joint_names=tuple(info["joint_names"]),
        joint_regressor_idx=a["joint_regressor_idx"].astype(np.int64),
        joint_regressor_w=a["joint_regressor_w"].astype(np.float64),
        bone_names=tuple(info["bone_names"]),
        skin_idx=a["skin_idx"].astype(np.int64),
        skin_w=a["skin_w"].astype(np.float64),
        bone_parent=a["bone_parent"].astype(np.int64),
        rest_bone_heads=a["rest_bone_heads"].astype(np.float64),
        pose_rotvec=a["pose_rotvec"].astype(np.float64),
        bone_sigma_scale=a["bone_sigma_scale"].astype(np.float64),
        face_mirror=a["face_mirror"].astype(np.int64),
        face_mirror_perm=a["face_mirror_perm"].astype(np.int64),
    )
    logger.debug(
        "loaded %d phenotypes x %d poses, %d vertices, %d faces from %s",
        model.num_phenotypes,
        model.num_poses,
        model.rest_vertices.shape[1],
        len(model.faces),
        path,
    )
    return model


def rotvec_to_matrix(rotvec: FloatArray) -> FloatArray:
    """Rodrigues' formula: (..., 3) axis-angle -> (..., 3, 3) rotation matrices."""
    rotvec = np.asarray(rotvec, dtype=np.float64)
    theta = np.linalg.norm(rotvec, axis=-1)[..., None, None]
    k = np.zeros((*rotvec.shape[:-1], 3, 3))
    k[..., 0, 1], k[..., 0, 2] = -rotvec[..., 2], rotvec[..., 1]
    k[..., 1, 0], k[..., 1, 2] = rotvec[..., 2], -rotvec[..., 0]
    k[..., 2, 0], k[..., 2, 1] = -rotvec[..., 1], rotvec[..., 0]
    # sin(t)/t and (1 - cos(t))/t^2 with their Taylor series near 0 (K is unnormalised).
    small = theta < 1e-6
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta**2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(safe)) / safe**2)
    return np.eye(3) + a * k + b * (k @ k)


def forward_kinematics(
    bone_parent: IndexArray, rest_heads: FloatArray, local_rotations: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Global bone rotations and posed heads; the root's head stays in place.

    Args:
        bone_parent: (B,) parent index, -1 for the root, parents first.
        rest_heads: (B, 3) rest heads h.
        local_rotations: (B, 3, 3) local rotations L (see module doc).

    Returns:
        (B, 3, 3) global rotations G and (B, 3) posed heads g, with
        G_c = G_p L_c and g_c = g_p + G_p (h_c - h_p).
    """
    num_b = len(bone_parent)
    rot = np.zeros((num_b, 3, 3))
    heads = np.zeros((num_b, 3))
    for c in range(num_b):  # a loop over ~40 bones, not over vertices
        p = bone_parent[c]
        if p < 0:
            rot[c], heads[c] = local_rotations[c], rest_heads[c]
        else:
            rot[c] = rot[p] @ local_rotations[c]
            heads[c] = heads[p] + rot[p] @ (rest_heads[c] - rest_heads[p])
    return rot, heads


def skin(
    model: BodyModel,
    rest_vertices: FloatArray,
    rest_heads: FloatArray,
    rotations: FloatArray,
    heads: FloatArray,
) -> FloatArray:
    """Linear blend skinning of (V, 3) rest vertices with (B, 3, 3) / (B, 3) bones."""
    # Bone c: x -> G_c x + t_c with t_c = g_c - G_c h_c.
    trans = heads - np.einsum("bij,bj->bi", rotations, rest_heads)
    moved = np.einsum("vkij,vj->vki", rotations[model.skin_idx], rest_vertices)
    moved += trans[model.skin_idx]
    return np.einsum("vk,vki->vi", model.skin_w, moved)


def pose_skeleton(
    model: BodyModel,
    phenotype: int,
    pose: int,
    delta_rotvec: FloatArray | None = None,
    shape_blend: tuple[int, float] | None = None,
) -> tuple[FloatArray, FloatArray]:
    """Like :func:`pose_body`, also returning the posed bone heads.

    Returns:
        (V, 3) vertices and (B, 3) bone heads, float64, body frame, grounded alike.
    """
    if not (0 <= phenotype < model.num_phenotypes and 0 <= pose < model.num_poses):
        raise ValueError(
            f"phenotype={phenotype} / pose={pose} out of range "
            f"({model.num_phenotypes} phenotypes, {model.num_poses} poses)"
        )
    rest = model.rest_vertices[phenotype]
    rest_heads = model.rest_bone_heads[phenotype]
    if shape_blend is not None:
        other, w = shape_blend
        if not 0 <= other < model.num_phenotypes:
            raise ValueError(f"shape_blend phenotype {other} out of range")
        rest = (1.0 - w) * rest + w * model.rest_vertices[other]
        rest_heads = (1.0 - w) * rest_heads + w * model.rest_bone_heads[other]
    local = rotvec_to_matrix(model.pose_rotvec[pose])
    if delta_rotvec is not None:
        delta_rotvec = np.asarray(delta_rotvec, dtype=np.float64)
        if delta_rotvec.shape != model.pose_rotvec.shape[1:]:
            raise ValueError(
                f"delta_rotvec has shape {delta_rotvec.shape}, "
                f"expected {model.pose_rotvec.shape[1:]}"
            )
        local = rotvec_to_matrix(delta_rotvec) @ local
    rotations, heads = forward_kinematics(model.bone_parent, rest_heads, local)
    vertices = skin(model, rest, rest_heads, rotations, heads)
    root = int(np.flatnonzero(model.bone_parent < 0)[0])
    # Ground: lowest vertex at z = 0, pelvis (root head) at x = y = 0.
    shift = np.array([heads[root, 0], heads[root, 1], vertices[:, 2].min()])
    return vertices - shift, heads - shift


def pose_body(
    model: BodyModel,
    phenotype: int,
    pose: int,
    delta_rotvec: FloatArray | None = None,
    shape_blend: tuple[int, float] | None = None,
) -> FloatArray:
    """Pose a body by numpy LBS, optionally with articulation and shape errors.

    Without perturbation this reproduces ``model.posed_vertices[phenotype, pose]``
    (to the LBS error stated in ``anny_bodies.json``).

    Args:
        model: the body model.
        phenotype: row of ``model.phenotype_names``.
        pose: row of ``model.pose_names``.
        delta_rotvec: (B, 3) rad, extra local rotation per bone, applied after the
            pose's own (``L_c <- exp(delta_c) L_c``, body-frame axes at rest). A
            non-zero root entry rotates the whole body about the pelvis.
        shape_blend: (other_phenotype, w): rest shape and skeleton become
            ``(1 - w) * phenotype + w * other`` (Anny's shape space is linear).

    Returns:
        (V, 3) float64 vertices in the body frame, grounded like the export.
    """
    return pose_skeleton(model, phenotype, pose, delta_rotvec, shape_blend)[0]


def joints(model: BodyModel, vertices: FloatArray) -> FloatArray:
    """(K, 3) joint centres of a mesh: fixed linear combinations of its vertices.

    ``vertices`` may carry leading batch dimensions: (..., V, 3) -> (..., K, 3).
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    picked = vertices[..., model.joint_regressor_idx, :]  # (..., K, n, 3)
    return np.einsum("kn,...kni->...ki", model.joint_regressor_w, picked)


def surface_points(
    model: BodyModel, vertices: FloatArray, face_idx: IndexArray, bary: FloatArray
) -> FloatArray:
    """(N, 3) points of a mesh given by faces and barycentric coordinates."""
    face_idx = np.asarray(face_idx)
    bary = np.asarray(bary, dtype=np.float64)
    if bary.shape != (len(face_idx), 3):
        raise ValueError(f"bary has shape {bary.shape}, expected ({len(face_idx)}, 3)")
    corners = np.asarray(vertices, dtype=np.float64)[model.faces[face_idx]]  # (N, 3, 3)
    return np.einsum("nj,nji->ni", bary, corners)


def mirror_surface(
    model: BodyModel, face_idx: IndexArray, bary: FloatArray
) -> tuple[IndexArray, FloatArray]:
    """The left/right mirror of surface points, on the same topology.

    Returns:
        (N,) int64 faces and (N, 3) float64 barycentric coordinates. On a symmetric
        rest body the mirrored points are the x-reflections of the inputs.
    """
    face_idx = np.asarray(face_idx, dtype=np.int64)
    bary = np.asarray(bary, dtype=np.float64)
    if bary.shape != (len(face_idx), 3):
        raise ValueError(f"bary has shape {bary.shape}, expected ({len(face_idx)}, 3)")
    perm = model.face_mirror_perm[face_idx]
    return model.face_mirror[face_idx], np.take_along_axis(bary, perm, axis=1)


def template_points(model: BodyModel, vertices: FloatArray) -> FloatArray:
    """(S, 3) the template surface samples on a mesh of the shared topology."""
    return surface_points(model, vertices, model.template_face_idx, model.template_bary)


def bone_subtree(model: BodyModel, bone: int) -> IndexArray:
    """Indices of ``bone`` and all its descendants."""
    inside = np.zeros(len(model.bone_parent), dtype=bool)
    inside[bone] = True
    for c in range(bone + 1, len(model.bone_parent)):  # parents come first
        p = model.bone_parent[c]
        inside[c] = p >= 0 and inside[p]
    return np.flatnonzero(inside).astype(np.int64)
