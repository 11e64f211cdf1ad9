"""Export articulated Anny bodies (phenotypes x poses) to small numpy files (dev only).

Needs torch and anny (kept out of the core venv)::

    make bodies
    # or: .venv-bodies/bin/python scripts/export_bodies.py --out colmap_vc/data

Writes ``anny_bodies.npz`` and ``anny_bodies.json`` (see data/synthetic/bodies/README.md
and colmap_vc/synthetic/bodies.py for the format). Deterministic: the same anny version
gives the same files. Optionally renders a check picture of all bodies (``--check-png``,
needs matplotlib).

Anny conventions used here (anny 0.6.2, rig "anny", pose parameterization "local-ref"):
the identity pose is Anny's *reference* pose, not the rest pose of a phenotype; a bone's
rest orientation R_c (phenotype dependent) differs from its reference orientation U_c.
With A_c = U_c R_c^T, the rest-relative local rotation L_c (this package's convention,
G_c = G_parent L_c) is Anny's delta D_c = A_parent L_c A_c^T (both in Anny's frame).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import logging
import sys
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import ModuleType

import numpy as np

logger = logging.getLogger("export_bodies")

REPO = Path(__file__).resolve().parents[1]
ANNY_VERSION = "0.6.2"
DEFAULT_TOPOLOGY = "notoes_collapse10pc"
VERTICES_SCALE = 1e-4  # metres per int16 unit (0.1 mm): +-3.27 m range
SEED = 0

# Body frame = Anny frame turned 180 degrees about +Z: Anny's bodies face -Y with their
# left on +X; ours face +Y with their left on -X (Z up in both).
BODY_FROM_ANNY = np.diag([-1.0, -1.0, 1.0])

# Anny phenotype parameters are in [0, 1]. gender: 0 male, 1 female. age: anny's
# morphological-age mapping (data/shape_calibration) puts 4 years at 0.215, 11 years at
# 0.415, 18 years at 0.77 and 64 years at 0.83.
PHENOTYPES: tuple[tuple[str, str, float, dict[str, float]], ...] = (
    # name, description, target height (m; anny's "height" is calibrated to it), params
    (
        "woman_tall_slim",
        "adult woman, tall and slim",
        1.76,
        dict(gender=1.0, age=0.79, muscle=0.5, weight=0.15, proportions=0.5),
    ),
    (
        "woman_short_heavy",
        "adult woman, short and heavy",
        1.55,
        dict(gender=1.0, age=0.8, muscle=0.3, weight=1.0, proportions=0.5),
    ),
    (
        "man_average",
        "adult man, average height and weight",
        1.76,
        dict(gender=0.0, age=0.79, muscle=0.5, weight=0.5, proportions=0.5),
    ),
    (
        "man_tall_heavy",
        "adult man, tall and heavy",
        1.92,
        dict(gender=0.0, age=0.79, muscle=0.55, weight=1.0, proportions=0.5),
    ),
    (
        "man_short_slim",
        "adult man, short and slim",
        1.63,
        dict(gender=0.0, age=0.79, muscle=0.4, weight=0.15, proportions=0.5),
    ),
    (
        "child",
        "child of about 9 years (anny age 0.36)",
        1.33,
        dict(gender=0.3, age=0.36, muscle=0.5, weight=0.5, proportions=0.5),
    ),
)
AGE_YEARS = {0.36: 9, 0.79: 33, 0.8: 41}

# The exported skeleton: Anny's "anny" rig without fingers, toes and eyes, whose skin
# weights go to their nearest kept ancestor (wrist, foot, head). Unposed children move
# exactly with their parent, so dropping them changes nothing.
KEPT_BONES = (
    "root",
    *(f"{b}.{s}" for s in "LR" for b in ("pelvis", "upperleg01", "upperleg02",
                                         "lowerleg01", "lowerleg02", "foot")),
    "spine05", "spine04", "spine03", "spine02", "spine01",
    *(f"{b}.{s}" for s in "LR" for b in ("clavicle", "shoulder01", "upperarm01",
                                         "upperarm02", "lowerarm01", "lowerarm02",
                                         "wrist")),
    "neck01", "neck02", "neck03", "head",
)  # fmt: skip


def bone_sigma_scale(bone: str) -> float:
    """Suggested scale of a per-joint articulation error (e.g. a network's) per bone.

    Chains share one anatomical joint's error (spine: 5 bones, neck + head: 4), twist
    and helper bones get none, the root none (it is the global orientation).
    """
    base = bone.partition(".")[0]
    if base.startswith("spine"):
        return 1.0 / np.sqrt(5.0)
    if base.startswith("neck") or base == "head":
        return 0.5
    if base == "clavicle":
        return 0.5
    if base in (
        "upperleg01",
        "lowerleg01",
        "foot",
        "upperarm01",
        "lowerarm01",
        "wrist",
    ):
        return 1.0
    return 0.0  # root, pelvis.L/R, shoulder01, the *02 twist bones


PART_NAMES = (
    "head",
    "torso",
    "upper_arm_left",
    "upper_arm_right",
    "lower_arm_left",
    "lower_arm_right",
    "hand_left",
    "hand_right",
    "upper_leg_left",
    "upper_leg_right",
    "lower_leg_left",
    "lower_leg_right",
    "foot_left",
    "foot_right",
)
_SIDE = {"L": "left", "R": "right"}


def bone_part(bone: str) -> str:
    """Body part of the skin a (kept) bone carries; Anny's .L is the person's left."""
    base, _, side = bone.partition(".")
    base = base.rstrip("0123456789")
    if base in ("neck", "head"):
        return "head"
    if base in ("root", "spine", "pelvis", "clavicle", "shoulder"):
        return "torso"
    part = {
        "upperarm": "upper_arm",
        "lowerarm": "lower_arm",
        "wrist": "hand",
        "upperleg": "upper_leg",
        "lowerleg": "lower_leg",
        "foot": "foot",
    }[base]
    return f"{part}_{_SIDE[side]}"


# Joint centres (COCO-like names) and the rig bone whose head each one is.
JOINTS = (
    ("pelvis", "root"),
    ("spine", "spine03"),
    ("chest", "spine01"),
    ("neck", "neck01"),
    ("head", "head"),
    ("left_shoulder", "upperarm01.L"),
    ("right_shoulder", "upperarm01.R"),
    ("left_elbow", "lowerarm01.L"),
    ("right_elbow", "lowerarm01.R"),
    ("left_wrist", "wrist.L"),
    ("right_wrist", "wrist.R"),
    ("left_hip", "upperleg01.L"),
    ("right_hip", "upperleg01.R"),
    ("left_knee", "lowerleg01.L"),
    ("right_knee", "lowerleg01.R"),
    ("left_ankle", "foot.L"),
    ("right_ankle", "foot.R"),
)
NUM_REGRESSOR_VERTICES = 32
NUM_PERTURBED = 4  # numpy-LBS meshes with perturbed joints per (phenotype, pose)
PERTURB_DEG = 10.0  # sigma of the perturbation, per bone and axis

# Segment of a bone for direction targets: from its head to the head of this bone.
SEGMENT_END = {
    "upperarm01": "lowerarm01",
    "lowerarm01": "wrist",
    "wrist": "finger3-1",
    "upperleg01": "lowerleg01",
    "lowerleg01": "foot",
    "foot": "toe3-1",
    "clavicle": "upperarm01",
    "neck01": "head",
}


# --------------------------------------------------------------------------- poses
def _rot(axis: Sequence[float], deg: float) -> np.ndarray:
    axis = np.asarray(axis, dtype=np.float64)
    axis = axis / np.linalg.norm(axis)
    return _rotvec_to_matrix(axis * np.deg2rad(deg))


def _rotvec_to_matrix(rotvec: np.ndarray) -> np.ndarray:
    theta = np.linalg.norm(rotvec)
    if theta < 1e-12:
        return np.eye(3)
    k = rotvec / theta
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(theta) * kx + (1 - np.cos(theta)) * (kx @ kx)


def _matrix_to_rotvec(r: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) -> axis-angle (..., 3), through quaternions."""
    r = np.asarray(r, dtype=np.float64)
    w = np.sqrt(np.clip(1.0 + np.trace(r, axis1=-2, axis2=-1), 0.0, None)) / 2.0
    x = np.sqrt(np.clip(1.0 + r[..., 0, 0] - r[..., 1, 1] - r[..., 2, 2], 0, None)) / 2
    y = np.sqrt(np.clip(1.0 - r[..., 0, 0] + r[..., 1, 1] - r[..., 2, 2], 0, None)) / 2
    z = np.sqrt(np.clip(1.0 - r[..., 0, 0] - r[..., 1, 1] + r[..., 2, 2], 0, None)) / 2
    x = np.copysign(x, r[..., 2, 1] - r[..., 1, 2])
    y = np.copysign(y, r[..., 0, 2] - r[..., 2, 0])
    z = np.copysign(z, r[..., 1, 0] - r[..., 0, 1])
    v = np.stack([x, y, z], axis=-1)
    s = np.linalg.norm(v, axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(s, w[..., None])
    return np.where(s > 1e-12, v / np.maximum(s, 1e-300) * angle, 0.0)


def _min_rotation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Smallest rotation taking direction a to direction b."""
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    axis = np.cross(a, b)
    s = np.linalg.norm(axis)
    if s < 1e-12:
        return np.eye(3)
    return _rotvec_to_matrix(axis / s * np.arctan2(s, float(a @ b)))


def _mirror_name(bone: str) -> str:
    return bone[:-2] + {".L": ".R", ".R": ".L"}[bone[-2:]]


_MIRROR_VEC = np.array([-1.0, 1.0, 1.0])  # x-reflection of a direction
_MIRROR_AXIS = np.array([1.0, -1.0, -1.0])  # x-reflection of a rotation axis


@dataclass
class Pose:
    """A pose as a list of operations per bone, applied parents first.

    Operations (body frame at rest: x = person's right, y = forward, z = up):
      ("rot", axis, deg): L <- R(axis, deg) L, axis in the parent's rest frame.
      ("twist", deg): L <- L R(d, deg), about the bone's own rest direction d.
      ("dir", target, frame): swing the bone's segment onto ``target``, a direction in
        world axes, or in the current frame of the ancestor bone ``frame``.
      ("pitch", deg): swing the segment onto its rest direction pitched by ``deg`` about
        world X (for feet: 0 keeps the foot flat, > 0 lifts the toes).
    """

    name: str
    description: str
    ops: dict[str, list[tuple]] = field(default_factory=dict)

    def add(self, bone: str, *op: object) -> Pose:
        self.ops.setdefault(bone, []).append(tuple(op))
        return self

    def sym(self, bone: str, kind: str, *args: object) -> Pose:
        """Apply an operation given for the left bone to both sides (mirrored)."""
        self.add(bone, kind, *args)
        right = _mirror_name(bone)
        if kind == "rot":
            axis, deg = args
            self.add(right, "rot", np.asarray(axis) * _MIRROR_AXIS, deg)
        elif kind == "twist":
            self.add(right, "twist", -args[0])
        elif kind == "dir":
            target, *frame = args
            self.add(right, "dir", np.asarray(target) * _MIRROR_VEC, *frame)
        else:
            self.add(right, kind, *args)
        return self

    def spread(self, bones: Sequence[str], axis: Sequence[float], deg: float) -> Pose:
        """Rotate a chain (spine, neck) by ``deg`` in total, evenly over its bones."""
        for b in bones:
            self.add(b, "rot", axis, deg / len(bones))
        return self


SPINE = ("spine05", "spine04", "spine03", "spine02", "spine01")
NECK = ("neck01", "neck02", "neck03", "head")
X, Y, Z = (1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)


def left(lateral: float, forward: float, up: float) -> np.ndarray:
    """A direction for a left limb: ``lateral`` > 0 points away from the body (-X)."""
    return np.array([-lateral, forward, up])


def make_poses() -> list[Pose]:
    """The exported poses. Left-side values; .sym mirrors them to the right side."""
    poses = []

    p = Pose("standing", "relaxed standing, arms down, elbows slightly bent")
    p.sym("upperleg01.L", "dir", left(0.03, 0.0, -1))
    p.sym("lowerleg01.L", "dir", left(0.01, -0.02, -1))
    p.sym("foot.L", "pitch", 0)
    p.sym("upperarm01.L", "dir", left(0.14, 0.02, -1))
    p.sym("lowerarm01.L", "dir", left(0.08, 0.25, -1))
    poses.append(p)

    p = Pose("walking", "mid-stride, left foot forward, arms swinging opposite")
    p.add("root", "rot", Z, -5).spread(SPINE, Z, 10)
    p.add("upperleg01.L", "dir", left(0.03, 0.42, -0.9))
    p.add("lowerleg01.L", "dir", left(0.0, 0.2, -1))
    p.add("foot.L", "pitch", 8)
    p.add("upperleg01.R", "dir", left(0.03, -0.3, -1) * _MIRROR_VEC)
    p.add("lowerleg01.R", "dir", left(0.0, -0.75, -1) * _MIRROR_VEC)
    p.add("foot.R", "pitch", -22)
    p.add("upperarm01.R", "dir", left(0.12, 0.35, -0.94) * _MIRROR_VEC)
    p.add("lowerarm01.R", "dir", left(0.06, 0.8, -0.7) * _MIRROR_VEC)
    p.add("upperarm01.L", "dir", left(0.12, -0.3, -0.95))
    p.add("lowerarm01.L", "dir", left(0.08, -0.05, -1))
    poses.append(p)

    p = Pose("arms_raised", "both arms raised above the head, in a V")
    p.sym("upperleg01.L", "dir", left(0.04, 0.0, -1))
    p.sym("lowerleg01.L", "dir", left(0.02, -0.02, -1))
    p.sym("foot.L", "pitch", 0)
    p.sym("clavicle.L", "rot", Y, 18)
    p.sym("upperarm01.L", "dir", left(0.38, 0.08, 0.92))
    p.sym("lowerarm01.L", "dir", left(0.25, 0.12, 0.96))
    poses.append(p)

    p = Pose(
        "sitting",
        "sitting as if on a stool (seat at about knee height; no stool in the mesh), "
        "thighs horizontal, hands near the knees",
    )
    p.sym("upperleg01.L", "dir", left(0.1, 1, -0.04))
    p.sym("lowerleg01.L", "dir", left(0.04, 0.05, -1))
    p.sym("foot.L", "pitch", 0)
    p.spread(SPINE, X, -6)
    p.sym("upperarm01.L", "dir", left(0.12, 0.35, -0.93))
    p.sym("lowerarm01.L", "dir", left(0.0, 1, -0.35))
    poses.append(p)

    p = Pose(
        "crouching", "deep squat on flat feet, trunk leaning forward, arms forward"
    )
    p.add("root", "rot", X, -25).spread(SPINE, X, -15).spread(NECK, X, 25)
    p.sym("upperleg01.L", "dir", left(0.3, 0.95, -0.15))
    p.sym("lowerleg01.L", "dir", left(0.08, -0.6, -0.8))
    p.sym("foot.L", "pitch", 0)
    p.sym("upperarm01.L", "dir", left(0.1, 0.5, -0.86))
    p.sym("lowerarm01.L", "dir", left(-0.15, 0.95, -0.2))
    poses.append(p)

    p = Pose("turning", "standing, trunk twisted 45 degrees to the left, head further")
    p.add("root", "rot", Z, 10).spread(SPINE, Z, 35).spread(NECK, Z, 25)
    # Keep the feet pointing forward under the turned pelvis.
    p.add("upperleg01.L", "rot", Z, -10).add("upperleg01.R", "rot", Z, -10)
    p.sym("upperarm01.L", "dir", left(0.14, 0.02, -1), "spine01")
    p.sym("lowerarm01.L", "dir", left(0.08, 0.3, -1), "spine01")
    poses.append(p)

    p = Pose("dancing", "on the right foot, left knee up, right arm high, left arm out")
    p.add("root", "rot", Y, -4).spread(SPINE, Y, 12).spread(NECK, Y, -10)
    p.add("clavicle.R", "rot", np.array(Y) * _MIRROR_AXIS, 15)
    p.add("upperarm01.R", "dir", left(0.4, 0.15, 0.9) * _MIRROR_VEC)
    p.add("lowerarm01.R", "dir", left(-0.25, 0.2, 0.95) * _MIRROR_VEC)
    p.add("upperarm01.L", "dir", left(1, 0.15, 0.05))
    p.add("lowerarm01.L", "dir", left(0.25, 0.35, 0.9))
    p.add("upperleg01.L", "dir", left(0.15, 0.72, -0.68))
    p.add("lowerleg01.L", "dir", left(0.05, -0.3, -0.95))
    p.add("foot.L", "pitch", -25)
    p.add("upperleg01.R", "dir", left(0.06, 0.08, -1) * _MIRROR_VEC)
    p.add("lowerleg01.R", "dir", left(0.02, -0.08, -1) * _MIRROR_VEC)
    p.add("foot.R", "pitch", 0)
    poses.append(p)

    p = Pose("reaching", "reaching forward and up with the right arm, leaning forward")
    p.spread(SPINE, Z, 15).spread(SPINE, X, -12).spread(NECK, X, 10)
    p.add("clavicle.R", "rot", np.array(Z) * _MIRROR_AXIS, -10)
    p.add("upperarm01.R", "dir", left(0.1, 0.85, 0.5) * _MIRROR_VEC)
    p.add("lowerarm01.R", "dir", left(0.08, 0.88, 0.47) * _MIRROR_VEC)
    p.add("upperarm01.L", "dir", left(0.15, -0.1, -1))
    p.add("lowerarm01.L", "dir", left(0.1, 0.2, -1))
    p.add("upperleg01.L", "dir", left(0.05, -0.12, -1))
    p.add("foot.L", "pitch", -8)
    poses.append(p)
    return poses


def build_local_rotations(
    pose: Pose, names: list[str], parents: list[int], heads: np.ndarray
) -> np.ndarray:
    """(B, 3, 3) local rotations L of a pose on the full rig (body frame at rest)."""
    index = {n: i for i, n in enumerate(names)}
    unknown = set(pose.ops) - set(index)
    if unknown:
        raise ValueError(f"pose {pose.name}: unknown bones {sorted(unknown)}")

    def rest_dir(bone: str) -> np.ndarray:
        base, _, side = bone.partition(".")
        end = SEGMENT_END[base] + (f".{side}" if side else "")
        d = heads[index[end]] - heads[index[bone]]
        return d / np.linalg.norm(d)

    num_b = len(names)
    local = np.tile(np.eye(3), (num_b, 1, 1))
    glob = np.tile(np.eye(3), (num_b, 1, 1))
    for c, name in enumerate(names):
        p = parents[c]
        g_parent = glob[p] if p >= 0 else np.eye(3)
        lc = np.eye(3)
        for op in pose.ops.get(name, []):
            kind = op[0]
            if kind == "rot":
                lc = _rot(op[1], op[2]) @ lc
            elif kind == "twist":
                lc = lc @ _rot(rest_dir(name), op[1])
            elif kind in ("dir", "pitch"):
                g = g_parent @ lc
                if kind == "dir":
                    target = np.asarray(op[1], dtype=np.float64)
                    if len(op) > 2:  # in the current frame of an ancestor bone
                        target = glob[index[op[2]]] @ target
                else:
                    target = _rot(X, op[1]) @ rest_dir(name)
                g = _min_rotation(g @ rest_dir(name), target) @ g
                lc = g_parent.T @ g
            else:
                raise ValueError(f"unknown pose operation {op!r}")
        local[c] = lc
        glob[c] = g_parent @ lc
    return local


# --------------------------------------------------------------------------- helpers
def load_bodies_module() -> ModuleType:
    """Import colmap_vc/synthetic/bodies.py by path (the package __init__ needs
    pycolmap, which this venv does not have)."""
    sys.path.insert(0, str(REPO))
    path = REPO / "colmap_vc" / "synthetic" / "bodies.py"
    spec = importlib.util.spec_from_file_location("colmap_vc_bodies", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up
    spec.loader.exec_module(module)
    return module


def nnls(a: np.ndarray, b: np.ndarray, max_iter: int = 200) -> np.ndarray:
    """Lawson-Hanson non-negative least squares, min |a x - b| s.t. x >= 0."""
    n = a.shape[1]
    x = np.zeros(n)
    passive = np.zeros(n, dtype=bool)
    for _ in range(max_iter):
        grad = a.T @ (b - a @ x)
        if passive.all() or grad[~passive].max() <= 1e-12:
            break
        passive[np.flatnonzero(~passive)[np.argmax(grad[~passive])]] = True
        while True:
            z = np.zeros(n)
            z[passive] = np.linalg.lstsq(a[:, passive], b, rcond=None)[0]
            if z[passive].min() > 0:
                x = z
                break
            neg = passive & (z <= 0)
            alpha = np.min(x[neg] / (x[neg] - z[neg]))
            x = x + alpha * (z - x)
            passive &= x > 1e-12
            x[~passive] = 0.0
    return x


def fit_skin_weights(
    bone_points: np.ndarray, targets: np.ndarray, merged: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Four bones and weights per vertex that best reproduce Anny's skinning.

    Anny skins with up to ~9 bones per vertex. Where more than 4 carry weight, every
    4-subset of the 6 heaviest is fitted (non-negative, summing to one) to the vertex's
    positions over all posed meshes, and the best subset is kept.

    Args:
        bone_points: (N, V, B, 3) the vertex moved rigidly by each bone, N meshes.
        targets: (N, V, 3) Anny's skinned vertices.
        merged: (V, B) Anny's weights on the exported bones.
    """
    from itertools import combinations

    num_v = merged.shape[0]
    idx = np.argsort(-merged, axis=1, kind="stable")[:, :4]
    w = np.take_along_axis(merged, idx, axis=1)
    w /= w.sum(axis=1, keepdims=True)
    big = 10.0  # weight of the sum-to-one row (positions are in metres)
    for v in np.flatnonzero((merged > 1e-6).sum(axis=1) > 4):
        cand = np.argsort(-merged[v], kind="stable")[:6]
        best = (np.inf, idx[v], w[v])
        for subset in combinations(cand.tolist(), 4):
            a = bone_points[:, v, list(subset)].transpose(0, 2, 1).reshape(-1, 4)
            a = np.vstack([a, big * np.ones((1, 4))])
            rhs = np.r_[targets[:, v].reshape(-1), big]
            x = nnls(a, rhs)
            err = np.linalg.norm(a @ x - rhs)
            if err < best[0]:
                best = (err, np.array(subset), x / x.sum())
        idx[v], w[v] = best[1], best[2]
    order = np.argsort(-w, axis=1, kind="stable")
    logger.info(
        "refitted the 4 skin weights of %d / %d vertices",
        int(((merged > 1e-6).sum(axis=1) > 4).sum()),
        num_v,
    )
    return np.take_along_axis(idx, order, 1), np.take_along_axis(w, order, 1)


def fit_joint_regressor(
    verts: np.ndarray,
    targets: np.ndarray,
    rest_mean: np.ndarray,
    rest_joint: np.ndarray,
    num: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Affine vertex weights (summing to one) that reproduce one joint on many meshes.

    Candidates are the 3 * num vertices nearest to the joint at rest; the num with the
    largest weights are kept and refitted. A small ridge towards equal weights keeps
    the weights moderate (negative weights are allowed: the joint is not a convex
    combination of nearby surface points once the limb bends).

    Args:
        verts: (N, V, 3) meshes; targets: (N, 3) the joint on each.
        rest_mean: (V, 3) mean rest mesh; rest_joint: (3,) the joint on it.
        num: number of vertices used.
    """

    def solve(cand: np.ndarray) -> np.ndarray:
        a = verts[:, cand].transpose(0, 2, 1).reshape(-1, len(cand))
        n = len(cand)
        lam = 3e-3 * np.trace(a.T @ a) / n / len(a) * 3  # ~3e-3 of a squared radius
        kkt = np.zeros((n + 1, n + 1))
        kkt[:n, :n] = a.T @ a + lam * np.eye(n)
        kkt[:n, n] = kkt[n, :n] = 1.0
        rhs = np.r_[a.T @ targets.reshape(-1) + lam / n, 1.0]
        return np.linalg.solve(kkt, rhs)[:n]

    near = np.argsort(np.linalg.norm(rest_mean - rest_joint, axis=1))[: 3 * num]
    w = solve(near)
    cand = near[np.sort(np.argsort(-np.abs(w))[:num])]
    return cand, solve(cand)


def farthest_point_sampling(points: np.ndarray, num: int, start: int = 0) -> np.ndarray:
    """Indices of ``num`` points spread evenly (greedy farthest point sampling)."""
    chosen = np.zeros(num, dtype=np.int64)
    chosen[0] = start
    dist = np.linalg.norm(points - points[start], axis=1)
    for i in range(1, num):
        chosen[i] = int(np.argmax(dist))
        dist = np.minimum(dist, np.linalg.norm(points - points[chosen[i]], axis=1))
    return chosen


def vertex_mirror(template: np.ndarray) -> tuple[np.ndarray, float]:
    """Index of the x-reflection of every vertex (brute-force nearest neighbour)."""
    reflected = template * _MIRROR_VEC
    mirror = np.zeros(len(template), dtype=np.int64)
    err = np.zeros(len(template))
    for start in range(0, len(template), 1024):
        d = np.linalg.norm(
            reflected[start : start + 1024, None] - template[None], axis=-1
        )
        mirror[start : start + 1024] = d.argmin(axis=1)
        err[start : start + 1024] = d.min(axis=1)
    return mirror, float(err.max())


def face_mirror_map(
    faces: np.ndarray, vmirror: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Mirror face fm of each face f and perm with faces[fm][j] = m[faces[f][perm[j]]].

    m is the vertex mirror ``vmirror``; a mirrored triangle has the reverse winding.
    """
    key = {tuple(sorted(f)): i for i, f in enumerate(faces.tolist())}
    face_mirror = np.full(len(faces), -1, dtype=np.int64)
    perm = np.zeros((len(faces), 3), dtype=np.int64)
    for f, corners in enumerate(vmirror[faces].tolist()):
        fm = key.get(tuple(sorted(corners)))
        if fm is None:
            continue
        face_mirror[f] = fm
        perm[f] = [corners.index(v) for v in faces[fm].tolist()]
    return face_mirror, perm


def sample_surface(
    vertices: np.ndarray, faces: np.ndarray, num: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Area-weighted random surface points: (num,) faces, (num, 3) barycentrics."""
    tri = vertices[faces]
    area = 0.5 * np.linalg.norm(
        np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1
    )
    face = rng.choice(len(faces), size=num, p=area / area.sum())
    s, r2 = np.sqrt(rng.random(num)), rng.random(num)
    return face, np.stack([1 - s, s * (1 - r2), s * r2], axis=1)


def ray_parity_inside(
    vertices: np.ndarray, faces: np.ndarray, points: np.ndarray
) -> np.ndarray:
    """Whether points are inside a closed mesh (odd number of crossings of a ray)."""
    direction = np.array([0.0123, 0.0371, 1.0])
    direction /= np.linalg.norm(direction)
    tri = vertices[faces]
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    h = np.cross(direction, e2)
    det = np.einsum("fi,fi->f", e1, h)
    s = points[:, None] - tri[None, :, 0]  # (N, F, 3)
    u = np.einsum("nfi,fi->nf", s, h) / det
    q = np.cross(s, e1)
    v = (q @ direction) / det
    t = np.einsum("fi,nfi->nf", e2, q) / det
    hits = (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
    return hits.sum(axis=1) % 2 == 1


# --------------------------------------------------------------------------- main
@dataclass
class AnnyRig:
    """What the export needs of an Anny model."""

    model: object
    names: list[str]
    parents: list[int]
    faces: np.ndarray

    def rest(self, params: np.ndarray) -> dict[str, np.ndarray]:
        """Rest model of phenotypes (P, num params), Anny frame."""
        import torch

        with torch.no_grad():
            out = self.model(phenotype_kwargs=torch.from_numpy(params))
        rest_rot = out["rest_bone_poses"][..., :3, :3].numpy()
        ref = self.model.reference_bone_orientations
        ref_rot = np.broadcast_to(
            np.eye(3) if ref is None else ref.numpy(), rest_rot.shape
        )
        return {
            "vertices": out["rest_vertices"].numpy(),
            "heads": out["rest_bone_heads"].numpy(),
            "rest_rot": rest_rot,  # R
            "ref_rot": ref_rot,  # U
        }

    def pose(
        self, params: np.ndarray, rest: dict[str, np.ndarray], local_body: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Vertices (P, Q, V, 3) and bone heads (P, Q, B, 3), body frame, ungrounded,
        of every phenotype in every pose given as local rotations (Q, B, 3, 3)."""
        import torch

        num_p, (num_q, num_b) = len(params), local_body.shape[:2]
        a_rot = rest["ref_rot"] @ np.swapaxes(rest["rest_rot"], -1, -2)  # A = U R^T
        if not (
            np.allclose(a_rot[:, 0], np.eye(3))
            and np.allclose(rest["ref_rot"][:, 0], np.eye(3))
        ):
            raise RuntimeError(
                "expected identity rest/reference orientations of the root"
            )
        local_a = BODY_FROM_ANNY @ local_body @ BODY_FROM_ANNY
        a_parent = a_rot[:, [max(p, 0) for p in self.parents]]
        a_parent[:, 0] = np.eye(3)  # the root's delta is its own global rotation
        deltas = np.einsum("pbij,qbjk,pblk->pqbil", a_parent, local_a, a_rot)
        pose = torch.zeros((num_p * num_q, num_b, 4, 4), dtype=torch.float64)
        pose[..., :3, :3] = torch.from_numpy(deltas.reshape(-1, num_b, 3, 3))
        pose[..., 3, 3] = 1.0
        with torch.no_grad():
            out = self.model(
                pose_parameters=pose,
                phenotype_kwargs=torch.from_numpy(params).repeat_interleave(
                    num_q, dim=0
                ),
            )
        verts = out["vertices"].numpy() @ BODY_FROM_ANNY
        heads = out["bone_poses"][..., :3, 3].numpy() @ BODY_FROM_ANNY
        return verts.reshape(num_p, num_q, -1, 3), heads.reshape(num_p, num_q, num_b, 3)


def load_anny(topology: str) -> AnnyRig:
    import anny
    import torch

    if anny.__version__ != ANNY_VERSION:
        logger.warning(
            "anny %s installed, the export expects %s", anny.__version__, ANNY_VERSION
        )
    torch.manual_seed(SEED)
    logger.info(
        "loading Anny (topology %s); a first run builds caches for minutes", topology
    )
    model = anny.Anny(
        topology=topology, skinning_method="lbs", pose_parameterization="local-ref"
    )
    faces = model.faces.numpy().astype(np.int64)
    if faces.shape[1] != 3:
        raise RuntimeError(f"expected triangles, got faces of shape {faces.shape}")
    return AnnyRig(
        model=model,
        names=list(model.bone_labels),
        parents=[int(p) for p in model.bone_parents],
        faces=faces,
    )


def calibrate_heights(rig: AnnyRig) -> np.ndarray:
    """Phenotype parameters (P, n) with anny's "height" bisected to the target heights
    (rest pose, top of the head to the soles)."""
    labels = list(rig.model.phenotype_labels)
    params = np.array(
        [[{**p, "height": 0.5}[k] for k in labels] for _, _, _, p in PHENOTYPES]
    )
    target = np.array([h for _, _, h, _ in PHENOTYPES])
    lo, hi = np.zeros(len(params)), np.ones(len(params))
    col = labels.index("height")
    for _ in range(30):
        params[:, col] = (lo + hi) / 2
        z = rig.rest(params)["vertices"][..., 2]
        too_tall = np.ptp(z, axis=1) > target
        hi = np.where(too_tall, params[:, col], hi)
        lo = np.where(too_tall, lo, params[:, col])
    params[:, col] = np.round((lo + hi) / 2, 4)
    return params


def placeholder_fields(
    num_p: int, num_q: int, num_v: int, faces: np.ndarray, num_b: int
) -> dict[str, object]:
    """BodyModel fields that numpy LBS does not read, filled with valid dummies."""
    num_f = len(faces)
    return {
        "faces": faces,
        "posed_vertices": np.zeros((num_p, num_q, num_v, 3)),
        "face_part": np.zeros(num_f, dtype=np.int64),
        "part_names": PART_NAMES,
        "phenotype_names": tuple(str(i) for i in range(num_p)),
        "pose_names": tuple(str(i) for i in range(num_q)),
        "template_face_idx": np.zeros(0, dtype=np.int64),
        "template_bary": np.zeros((0, 3)),
        "joint_names": (),
        "joint_regressor_idx": np.zeros((0, 1), dtype=np.int64),
        "joint_regressor_w": np.zeros((0, 1)),
        "bone_names": KEPT_BONES,
        "bone_sigma_scale": np.zeros(num_b),
        "face_mirror": np.zeros(num_f, dtype=np.int64),
        "face_mirror_perm": np.zeros((num_f, 3), dtype=np.int64),
    }


def _ground_shift(vertices: np.ndarray, pelvis: np.ndarray) -> np.ndarray:
    """(..., 3) shift putting the lowest vertex at z = 0 and the pelvis at x = y = 0."""
    return np.concatenate(
        [pelvis[..., :2], vertices[..., 2].min(axis=-1)[..., None]], -1
    )


def export(
    out_dir: Path, topology: str, num_samples: int, check_png: Path | None
) -> dict:
    rig = load_anny(topology)
    names, parents, faces = rig.names, rig.parents, rig.faces
    root = names.index("root")
    kept = [names.index(b) for b in KEPT_BONES]
    kept_index = {c: i for i, c in enumerate(kept)}

    # ---- phenotypes: rest shapes (body frame)
    params = calibrate_heights(rig)
    num_p = len(params)
    rest = rig.rest(params)
    rest_b = rest["vertices"] @ BODY_FROM_ANNY
    heads_b = rest["heads"] @ BODY_FROM_ANNY

    # ---- poses: local rotations on the mean skeleton, rounded through float32 rotvecs
    poses = make_poses()
    num_q = len(poses)
    local = np.stack(
        [build_local_rotations(p, names, parents, heads_b.mean(axis=0)) for p in poses]
    )
    not_kept = [c for c in range(len(names)) if c not in kept_index]
    if not np.allclose(local[:, not_kept], np.eye(3)):
        raise RuntimeError("a pose rotates bones that are not exported")
    pose_rotvec = _matrix_to_rotvec(local[:, kept]).astype(np.float32)
    local[:, kept] = np.stack(
        [[_rotvec_to_matrix(r) for r in q] for q in pose_rotvec.astype(np.float64)]
    )
    posed_b, posed_heads_b = rig.pose(params, rest, local)

    # ---- grounding (every mesh: lowest vertex z = 0, pelvis x = y = 0)
    shift = _ground_shift(posed_b, posed_heads_b[..., root, :])
    posed_b -= shift[..., None, :]
    posed_heads_b -= shift[..., None, :]
    rest_shift = _ground_shift(rest_b, heads_b[:, root])
    rest_b -= rest_shift[:, None]
    heads_b -= rest_shift[:, None]

    # ---- skinning: Anny's weights merged onto the kept bones, then 4 bones refitted
    model = rig.model
    num_v = rest_b.shape[1]
    target = np.zeros(len(names), dtype=np.int64)
    for c in range(len(names)):
        a = c
        while a not in kept_index:
            a = parents[a]
        target[c] = kept_index[a]
    merged = np.zeros((num_v, len(kept)))
    np.add.at(
        merged,
        (np.arange(num_v)[:, None], target[model.vertex_bone_indices.numpy()]),
        model.vertex_bone_weights.numpy(),
    )
    bone_parent = np.array(
        [kept_index[parents[c]] if parents[c] >= 0 else -1 for c in kept]
    )
    bodies = load_bodies_module()
    bone_points = np.zeros((num_p, num_q, num_v, len(kept), 3))
    posed_centred = posed_b - posed_heads_b[..., root, None, :]
    for p in range(num_p):
        for q in range(num_q):
            rot, head = bodies.forward_kinematics(
                bone_parent, heads_b[p, kept], local[q, kept]
            )
            moved = np.einsum("bij,vj->vbi", rot, rest_b[p]) + (
                head - np.einsum("bij,bj->bi", rot, heads_b[p, kept])
            )
            bone_points[p, q] = moved - head[0]
    skin_idx, skin_w = fit_skin_weights(
        bone_points.reshape(-1, num_v, len(kept), 3),
        posed_centred.reshape(-1, num_v, 3),
        merged,
    )
    del bone_points

    # ---- body parts per face: the part with the most skin weight over its corners
    part_of_bone = np.array([PART_NAMES.index(bone_part(b)) for b in KEPT_BONES])
    part_w = np.zeros((num_v, len(PART_NAMES)))
    np.add.at(part_w, (slice(None), part_of_bone), merged)
    face_part = part_w[faces].sum(axis=1).argmax(axis=1).astype(np.uint8)

    # ---- left/right mirror on the (symmetric) template
    vmirror, vmirror_err = vertex_mirror(model.template_vertices.numpy())
    if vmirror_err > 1e-5 or not np.array_equal(vmirror[vmirror], np.arange(num_v)):
        raise RuntimeError(f"template is not left/right symmetric ({vmirror_err=})")
    face_mirror, face_perm = face_mirror_map(faces, vmirror)
    if (face_mirror < 0).any():
        raise RuntimeError(f"{(face_mirror < 0).sum()} faces have no mirror face")

    # ---- template samples: farthest point sampling on the mean rest mesh
    rng = np.random.default_rng(SEED)
    rest_mean = rest_b.mean(axis=0)
    cand_face, cand_bary = sample_surface(rest_mean, faces, 30 * num_samples, rng)
    cand_pts = np.einsum("nj,nji->ni", cand_bary, rest_mean[faces[cand_face]])
    pick = farthest_point_sampling(cand_pts, num_samples)

    # ---- joint regressor, fitted on the Anny meshes and on numpy-LBS meshes with
    # perturbed joints (the synthetic priors perturb them, see synthetic/noise.py)
    joint_bones = [names.index(b) for _, b in JOINTS]
    fit_verts = [posed_b.reshape(-1, num_v, 3), rest_b]
    fit_joints = [
        posed_heads_b.reshape(-1, len(names), 3)[:, joint_bones],
        heads_b[:, joint_bones],
    ]
    lbs_model = bodies.BodyModel(
        **{**placeholder_fields(num_p, num_q, num_v, faces, len(kept)),
           "rest_vertices": rest_b, "rest_bone_heads": heads_b[:, kept],
           "skin_idx": skin_idx, "skin_w": skin_w, "bone_parent": bone_parent,
           "pose_rotvec": pose_rotvec.astype(np.float64)}
    )  # fmt: skip
    kept_joint = [kept_index[b] for b in joint_bones]
    for p in range(num_p):
        for q in range(num_q):
            for _ in range(NUM_PERTURBED):
                delta = rng.normal(0.0, np.deg2rad(PERTURB_DEG), (len(kept), 3))
                delta[0] = 0.0
                v, h = bodies.pose_skeleton(lbs_model, p, q, delta_rotvec=delta)
                fit_verts.append(v[None])
                fit_joints.append(h[None, kept_joint])
    fit_verts_all = np.concatenate(fit_verts)
    fit_joints_all = np.concatenate(fit_joints)
    reg_idx = np.zeros((len(JOINTS), NUM_REGRESSOR_VERTICES), dtype=np.int64)
    reg_w = np.zeros((len(JOINTS), NUM_REGRESSOR_VERTICES))
    for k, b in enumerate(joint_bones):
        reg_idx[k], reg_w[k] = fit_joint_regressor(
            fit_verts_all,
            fit_joints_all[:, k],
            rest_mean,
            heads_b[:, b].mean(axis=0),
            NUM_REGRESSOR_VERTICES,
        )
    perturbed_err = np.linalg.norm(
        np.einsum(
            "kn,sknd->skd", reg_w, fit_verts_all[num_p * num_q + num_p :][:, reg_idx]
        )
        - fit_joints_all[num_p * num_q + num_p :],
        axis=-1,
    )

    # ---- quantize and write the npz
    if np.abs(posed_b).max() / VERTICES_SCALE > 32000:
        raise RuntimeError("posed vertices exceed the int16 range")
    out_dir.mkdir(parents=True, exist_ok=True)
    npz_path = out_dir / "anny_bodies.npz"
    np.savez_compressed(
        npz_path,
        faces=faces.astype(np.int32),
        vertices_q=np.round(posed_b / VERTICES_SCALE).astype(np.int16),
        vertices_scale=np.float64(VERTICES_SCALE),
        rest_vertices=rest_b.astype(np.float32),
        face_part=face_part,
        template_face_idx=cand_face[pick].astype(np.int32),
        template_bary=cand_bary[pick].astype(np.float32),
        joint_regressor_idx=reg_idx.astype(np.int32),
        joint_regressor_w=reg_w.astype(np.float32),
        skin_idx=skin_idx.astype(np.int16),
        skin_w=skin_w.astype(np.float32),
        bone_parent=bone_parent.astype(np.int32),
        rest_bone_heads=heads_b[:, kept].astype(np.float32),
        pose_rotvec=pose_rotvec,
        bone_sigma_scale=np.array([bone_sigma_scale(b) for b in KEPT_BONES]),
        face_mirror=face_mirror.astype(np.int32),
        face_mirror_perm=face_perm.astype(np.int8),
    )

    # ---- JSON, then validation with the numpy module itself
    import anny

    labels = list(model.phenotype_labels)
    info: dict = {
        "template": "anny",
        "anny_version": anny.__version__,
        "anny_rig": "anny without fingers, toes, eyes (skin merged to the parent)",
        "anny_pose_parameterization": "local-ref (converted, see pose_convention)",
        "topology": topology,
        "frame": (
            "metres; +Z up; the person faces +Y, so the person's left is -X; every "
            "body (posed and rest) is grounded: lowest vertex z = 0, pelvis joint "
            "(root bone head) at x = y = 0; this is Anny's frame turned 180 deg about Z"
        ),
        "pose_convention": (
            "pose_rotvec[q, c] is the axis-angle of L_c, bone c's rotation relative to "
            "the rest pose in body-frame axes at rest: G_c = G_parent L_c. Bone c maps "
            "a rest point x to G_c (x - h_c) + g_c, with g_c = g_parent + G_parent "
            "(h_c - h_parent) and the root's head fixed, then the mesh is grounded."
        ),
        "vertices_scale": VERTICES_SCALE,
        "counts": {
            "phenotypes": num_p,
            "poses": num_q,
            "vertices": num_v,
            "faces": len(faces),
            "bones": len(kept),
            "joints": len(JOINTS),
            "template_samples": num_samples,
            "regressor_vertices_per_joint": NUM_REGRESSOR_VERTICES,
        },
        "phenotypes": [
            {
                "name": name,
                "description": desc,
                "anny_params": {k: float(v) for k, v in zip(labels, row, strict=True)},
                "age_years_approx": AGE_YEARS.get(float(row[labels.index("age")])),
                "height_m": round(float(np.ptp(rest_b[p, :, 2])), 3),
            }
            for p, ((name, desc, _, _), row) in enumerate(
                zip(PHENOTYPES, params, strict=True)
            )
        ],
        "poses": [{"name": p.name, "description": p.description} for p in poses],
        "part_names": list(PART_NAMES),
        "joint_names": [j for j, _ in JOINTS],
        "joint_rig_bones": {j: f"head of {b}" for j, b in JOINTS},
        "bone_names": list(KEPT_BONES),
        "seed": SEED,
    }
    json_path = out_dir / "anny_bodies.json"
    json_path.write_text(json.dumps(info, indent=1) + "\n")
    info["validation"], info["sitting_seat_height_m"], reg = validate(
        bodies, npz_path, posed_b, posed_heads_b[..., joint_bones, :], poses
    )
    info["validation"]["template_vertex_mirror_error_m"] = vmirror_err
    info["validation"]["joint_regressor_mm"]["perturbed_lbs"] = {
        "max": round(float(perturbed_err.max() * 1e3), 2),
        "mean": round(float(perturbed_err.mean() * 1e3), 3),
        "note": f"{NUM_PERTURBED} numpy-LBS meshes per body, joints perturbed by "
        f"{PERTURB_DEG:g} deg (sigma per axis), also used in the fit",
    }
    json_path.write_text(json.dumps(info, indent=1) + "\n")
    logger.info("validation: %s", json.dumps(info["validation"], indent=1))
    logger.info("heights: %s", [(p["name"], p["height_m"]) for p in info["phenotypes"]])
    logger.info("sizes: %s", {f.name: f.stat().st_size for f in out_dir.iterdir()})
    if check_png is not None:
        render_check(check_png, posed_b, faces, face_part, reg, info)
    return info


def validate(
    bodies: ModuleType,
    npz_path: Path,
    posed: np.ndarray,
    rig_joints: np.ndarray,
    poses: list[Pose],
) -> tuple[dict, dict, np.ndarray]:
    """Compare the exported files, read by colmap_vc.synthetic.bodies, with Anny."""
    model = bodies.load_bodies(npz_path)
    num_p, num_q = posed.shape[:2]
    lbs = np.stack(
        [[bodies.pose_body(model, p, q) for q in range(num_q)] for p in range(num_p)]
    )
    lbs_err = np.linalg.norm(lbs - posed, axis=-1) * 1e3
    lbs_err_stored = np.linalg.norm(lbs - model.posed_vertices, axis=-1) * 1e3
    reg = bodies.joints(model, posed)
    reg_err = np.linalg.norm(reg - rig_joints, axis=-1) * 1e3
    per_joint = reg_err.reshape(-1, len(JOINTS)).max(axis=0)
    man = [n for n, *_ in PHENOTYPES].index("man_average")
    rest = model.rest_vertices[man]
    pts = bodies.template_points(model, rest)
    mf, mb = bodies.mirror_surface(model, model.template_face_idx, model.template_bary)
    mirrored = bodies.surface_points(model, rest, mf, mb)
    mirror_err = np.linalg.norm(mirrored - pts * _MIRROR_VEC, axis=-1) * 1e3
    standing = [p.name for p in poses].index("standing")
    inside = np.stack(
        [
            ray_parity_inside(posed[p, standing], model.faces, reg[p, standing])
            for p in range(num_p)
        ]
    )
    if not inside.all():
        logger.warning(
            "joints outside the standing body: %s", np.argwhere(~inside).tolist()
        )
    sit = [p.name for p in poses].index("sitting")
    seat = np.isin(
        model.face_part,
        [PART_NAMES.index(n) for n in ("upper_leg_left", "upper_leg_right", "torso")],
    )
    seat_z = posed[:, sit][:, np.unique(model.faces[seat]), 2].min(axis=1)
    validation = {
        "lbs_vs_anny_mm": {
            "max": round(float(lbs_err.max()), 3),
            "mean": round(float(lbs_err.mean()), 4),
            "max_vs_stored_int16": round(float(lbs_err_stored.max()), 3),
            "note": "numpy LBS (4 fitted weights) vs Anny's LBS (all weights)",
        },
        "joint_regressor_mm": {
            "max": round(float(reg_err.max()), 2),
            "mean": round(float(reg_err.mean()), 3),
            "max_per_joint": {
                j: round(float(e), 2)
                for (j, _), e in zip(JOINTS, per_joint, strict=True)
            },
            "max_abs_weight": round(float(np.abs(model.joint_regressor_w).max()), 3),
            "note": "regressed joints vs the rig's bone heads, all posed meshes",
        },
        "joints_inside_standing_body": bool(inside.all()),
        "mirror_mm": {
            "max": round(float(mirror_err.max()), 4),
            "mean": round(float(mirror_err.mean()), 5),
            "note": "mirrored template samples vs x-reflected ones, rest man_average",
        },
    }
    seat_height = {
        n: round(float(h), 3) for (n, *_), h in zip(PHENOTYPES, seat_z, strict=True)
    }
    return validation, seat_height, reg


def render_check(
    path: Path,
    posed: np.ndarray,
    faces: np.ndarray,
    face_part: np.ndarray,
    joints: np.ndarray,
    info: dict,
) -> None:
    """Front and side views of every body, coloured by part (needs matplotlib)."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        from matplotlib.collections import PolyCollection
    except ImportError:
        logger.warning("matplotlib missing: no check picture")
        return
    num_p, num_q = posed.shape[:2]
    colours = plt.get_cmap("tab20")(np.arange(len(PART_NAMES)))[:, :3]
    fig, axes = plt.subplots(num_p, 2 * num_q, figsize=(2.0 * num_q * 2, 2.6 * num_p))
    for p in range(num_p):
        for q in range(num_q):
            v = posed[p, q]
            for k, (view, cam) in enumerate(
                (("front", [0, 1, 0.3]), ("side", [1, 0, 0.3]))
            ):
                ax = axes[p, 2 * q + k]
                cam = np.asarray(cam, dtype=np.float64) / np.linalg.norm(cam)
                if view == "front":  # camera on +Y looking back: image x = -X
                    xy, depth = np.stack([-v[:, 0], v[:, 2]], 1), v[:, 1]
                    jxy = np.stack([-joints[p, q, :, 0], joints[p, q, :, 2]], 1)
                else:  # camera on +X (the person's right side)
                    xy, depth = np.stack([v[:, 1], v[:, 2]], 1), v[:, 0]
                    jxy = np.stack([joints[p, q, :, 1], joints[p, q, :, 2]], 1)
                n = np.cross(
                    v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]]
                )
                n /= np.linalg.norm(n, axis=1, keepdims=True) + 1e-12
                shade = 0.25 + 0.75 * np.clip(n @ cam, 0, 1)
                order = np.argsort(depth[faces].mean(1))
                ax.add_collection(
                    PolyCollection(
                        xy[faces][order],
                        facecolors=colours[face_part][order] * shade[order, None],
                        edgecolors="none",
                    )
                )
                ax.scatter(jxy[:, 0], jxy[:, 1], s=2, c="k")
                ax.set_xlim(-1.1, 1.1)
                ax.set_ylim(-0.05, 2.2)
                ax.set_aspect("equal")
                ax.axis("off")
                if p == 0 and k == 0:
                    ax.set_title(info["poses"][q]["name"], fontsize=8)
                if q == 0 and k == 0:
                    ax.text(-1.1, 2.1, info["phenotypes"][p]["name"], fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    logger.info("check picture: %s", path)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument(
        "--out", type=Path, default=REPO / "data" / "synthetic" / "bodies"
    )
    parser.add_argument("--topology", default=DEFAULT_TOPOLOGY)
    parser.add_argument("--num-samples", type=int, default=2000)
    parser.add_argument("--check-png", type=Path, default=None)
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.INFO, format="%(levelname)s %(name)s: %(message)s"
    )
    for noisy in ("anny", "warp"):
        logging.getLogger(noisy).setLevel(logging.WARNING)
    export(args.out, args.topology, args.num_samples, args.check_png)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
