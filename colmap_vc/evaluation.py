"""Relative-pose evaluation against ground truth, as in the paper (and SuperGlue).

The error of an image pair is max(rotation error, translation-direction error) of its
relative pose, in degrees; a pair with an image the reconstruction did not register
counts as 180 degrees. The translation-direction error is the plain angle between the
two directions (a reconstruction fixes the sign, so no folding at 90 degrees). The
AUC at a threshold is the area under the cumulative error curve up to it, divided by
the threshold (SuperGlue's ``pose_auc``), reported in percent.
"""

from __future__ import annotations

import itertools
import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
import pycolmap

from .structs import FloatArray

logger = logging.getLogger(__name__)

THRESHOLDS_DEG = (15.0, 30.0, 45.0)
UNREGISTERED_ERROR_DEG = 180.0


def rotation_angle_deg(R: FloatArray) -> float:
    """Angle of a rotation matrix (3, 3), degrees."""
    # atan2 of (sin, cos) stays accurate near 0 and 180 degrees, unlike acos.
    s = np.linalg.norm([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / 2.0
    c = (np.trace(R) - 1.0) / 2.0
    return math.degrees(math.atan2(float(s), float(c)))


def vector_angle_deg(a: FloatArray, b: FloatArray) -> float:
    """Angle between two vectors (3,), degrees; 0 if either is zero-length."""
    na, nb = np.linalg.norm(a), np.linalg.norm(b)
    if na < 1e-12 or nb < 1e-12:
        return 0.0 if (na < 1e-12 and nb < 1e-12) else 90.0
    return math.degrees(math.atan2(float(np.linalg.norm(np.cross(a, b))), float(a @ b)))


def relative_pose(
    cam1_from_world: FloatArray, cam2_from_world: FloatArray
) -> FloatArray:
    """cam2_from_cam1 (3, 4) from two (3, 4) cam_from_world poses."""
    R1, t1 = cam1_from_world[:, :3], cam1_from_world[:, 3]
    R2, t2 = cam2_from_world[:, :3], cam2_from_world[:, 3]
    R = R2 @ R1.T
    return np.concatenate([R, (t2 - R @ t1)[:, None]], axis=1)


def relative_pose_error(
    pred_cam2_from_cam1: FloatArray, gt_cam2_from_cam1: FloatArray
) -> tuple[float, float]:
    """(rotation error, translation-direction error) in degrees of a relative pose."""
    dR = pred_cam2_from_cam1[:, :3] @ gt_cam2_from_cam1[:, :3].T
    return rotation_angle_deg(dR), vector_angle_deg(
        pred_cam2_from_cam1[:, 3], gt_cam2_from_cam1[:, 3]
    )


def pose_disagreement_deg(p: FloatArray, q: FloatArray) -> float:
    """max(rotation angle, translation-direction angle) between two (3, 4) poses:
    the pose error of the evaluation, between any two estimates."""
    return max(relative_pose_error(p, q))


def camera_distance_ratio(
    pred: Mapping[str, FloatArray], gt: Mapping[str, FloatArray]
) -> float:
    """Median over image pairs of (predicted / true) distance between the two camera
    centres: 1 for a model in the ground truth's units. NaN with fewer than two
    images in common (or coincident true centres).

    Args:
        pred, gt: (3, 4) cam_from_world by image name.
    """
    names = sorted(set(pred) & set(gt))

    def centres(poses: Mapping[str, FloatArray]) -> FloatArray:
        T = np.array([poses[n] for n in names]).reshape(-1, 3, 4)
        return -np.einsum("nji,nj->ni", T[:, :, :3], T[:, :, 3])

    if len(names) < 2:
        return math.nan
    cp, cg = centres(pred), centres(gt)
    i, j = np.triu_indices(len(names), k=1)
    dg = np.linalg.norm(cg[i] - cg[j], axis=1)
    ok = dg > 1e-9
    if not ok.any():
        return math.nan
    return float(np.median(np.linalg.norm(cp[i] - cp[j], axis=1)[ok] / dg[ok]))


def pose_auc(
    errors_deg: Sequence[float] | FloatArray, thresholds_deg: Sequence[float]
) -> list[float]:
    """Area under the cumulative error curve up to each threshold, in [0, 1].

    Same definition as SuperGlue's ``pose_auc``: the recall curve starts at (0, 0),
    steps up by 1/N at each sorted error, and is integrated with the trapezoid rule
    up to the threshold, then normalised by the threshold.
    """
    errors = np.sort(np.asarray(errors_deg, dtype=np.float64))
    if len(errors) == 0:
        return [0.0 for _ in thresholds_deg]
    recall = (np.arange(len(errors)) + 1) / len(errors)
    errors = np.r_[0.0, errors]
    recall = np.r_[0.0, recall]
    aucs = []
    for t in thresholds_deg:
        last = int(np.searchsorted(errors, t))
        r = np.r_[recall[:last], recall[last - 1]]
        e = np.r_[errors[:last], t]
        aucs.append(float(np.trapezoid(r, x=e) / t))
    return aucs


@dataclass(frozen=True, kw_only=True, slots=True)
class PairError:
    """Error of one image pair."""

    image_name1: str
    image_name2: str
    rotation_deg: float
    translation_deg: float
    gt_angle_deg: float  # angle between the two GT viewing directions
    registered: bool

    @property
    def error_deg(self) -> float:
        """max(rotation, translation) error; 180 when not registered."""
        if not self.registered:
            return UNREGISTERED_ERROR_DEG
        return max(self.rotation_deg, self.translation_deg)


@dataclass(frozen=True, kw_only=True, slots=True)
class Metrics:
    """Pose accuracy of one reconstruction against ground truth (JSON-friendly)."""

    num_images: int
    num_registered: int
    auc: dict[str, float]  # "15" -> percent
    median_error_deg: float
    p80_error_deg: float
    pairs: list[PairError] = field(default_factory=list)

    def to_dict(self, with_pairs: bool = True) -> dict:
        """A JSON-serialisable dictionary."""
        out = {
            "num_images": self.num_images,
            "num_registered": self.num_registered,
            "auc": self.auc,
            "median_error_deg": self.median_error_deg,
            "p80_error_deg": self.p80_error_deg,
        }
        if with_pairs:
            out["pairs"] = [
                {
                    "image1": p.image_name1,
                    "image2": p.image_name2,
                    "rotation_deg": p.rotation_deg,
                    "translation_deg": p.translation_deg,
                    "error_deg": p.error_deg,
                    "gt_angle_deg": p.gt_angle_deg,
                    "registered": p.registered,
                }
                for p in self.pairs
            ]
        return out


def poses_by_name(rec: pycolmap.Reconstruction) -> dict[str, FloatArray]:
    """(3, 4) cam_from_world of every registered image, by name."""
    out = {}
    for image in rec.images.values():
        if image.has_pose:
            out[image.name] = image.cam_from_world().matrix()
    return out


def tilt_errors_deg(
    pred: Mapping[str, FloatArray],
    gt: Mapping[str, FloatArray],
    up_world: FloatArray,
) -> dict[str, float]:
    """Each predicted camera's tilt error: the angle between the world's up as
    it sees it and as the ground truth's camera sees it (``up_world``, in the
    ground truth's world), after the one world rotation that best aligns the
    predicted rotations to the ground truth's (chordal mean). It is what a
    camera's measured up fixes and the people alone fix worst
    (docs/real-data.md, "Static cameras"); 0 for a model off by a rotation of
    the whole world. Cameras in both, two or more; fewer: {}."""
    names = sorted(n for n in pred if n in gt)
    if len(names) < 2:
        return {}
    Rp = np.stack([np.asarray(pred[n])[:, :3] for n in names])
    Rg = np.stack([np.asarray(gt[n])[:, :3] for n in names])
    # Rg_i ~ Rp_i A: A from the SVD of sum Rp_i^T Rg_i (orthogonal Procrustes).
    U, _, Vt = np.linalg.svd(np.einsum("nji,njk->ik", Rp, Rg))
    A = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    seen = np.einsum("nij,j->ni", Rp, A @ up_world)
    truth = np.einsum("nij,j->ni", Rg, up_world)
    cos = np.einsum("ni,ni->n", seen, truth) / (
        np.linalg.norm(seen, axis=1) * np.linalg.norm(truth, axis=1)
    )
    angle = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    return dict(zip(names, angle.tolist(), strict=True))


def evaluate_poses(
    pred: Mapping[str, FloatArray],
    gt: Mapping[str, FloatArray],
    thresholds_deg: Sequence[float] = THRESHOLDS_DEG,
) -> Metrics:
    """Compare predicted cam_from_world poses to ground truth over all GT pairs.

    Args:
        pred: (3, 4) cam_from_world by image name; images missing are unregistered.
        gt: (3, 4) cam_from_world by image name.
        thresholds_deg: AUC thresholds.
    """
    names = sorted(gt)
    pairs = []
    for n1, n2 in itertools.combinations(names, 2):
        gt_rel = relative_pose(gt[n1], gt[n2])
        gt_angle = rotation_angle_deg(gt_rel[:, :3])
        if n1 in pred and n2 in pred:
            r, t = relative_pose_error(relative_pose(pred[n1], pred[n2]), gt_rel)
            pairs.append(
                PairError(
                    image_name1=n1,
                    image_name2=n2,
                    rotation_deg=r,
                    translation_deg=t,
                    gt_angle_deg=gt_angle,
                    registered=True,
                )
            )
        else:
            pairs.append(
                PairError(
                    image_name1=n1,
                    image_name2=n2,
                    rotation_deg=math.nan,
                    translation_deg=math.nan,
                    gt_angle_deg=gt_angle,
                    registered=False,
                )
            )
    errors = np.array([p.error_deg for p in pairs])
    aucs = pose_auc(errors, thresholds_deg)
    return Metrics(
        num_images=len(names),
        num_registered=sum(n in pred for n in names),
        auc={f"{t:g}": 100.0 * a for t, a in zip(thresholds_deg, aucs, strict=True)},
        median_error_deg=float(np.median(errors)) if len(errors) else math.nan,
        p80_error_deg=float(np.percentile(errors, 80)) if len(errors) else math.nan,
        pairs=pairs,
    )


def evaluate_reconstruction(
    pred: pycolmap.Reconstruction | None,
    gt: pycolmap.Reconstruction,
    thresholds_deg: Sequence[float] = THRESHOLDS_DEG,
) -> Metrics:
    """Evaluate a COLMAP reconstruction (None: nothing registered) against GT."""
    return evaluate_poses(
        {} if pred is None else poses_by_name(pred), poses_by_name(gt), thresholds_deg
    )


def format_table(
    rows: Mapping[str, Metrics], thresholds_deg: Sequence[float] = THRESHOLDS_DEG
) -> str:
    """A Markdown table: one row per method."""
    auc_cols = [f"AUC@{t:g}" for t in thresholds_deg]
    header = ["method", "registered", *auc_cols, "median (deg)", "p80 (deg)"]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for name, m in rows.items():
        cells = [
            name,
            f"{m.num_registered}/{m.num_images}",
            *(f"{m.auc[f'{t:g}']:.1f}" for t in thresholds_deg),
            f"{m.median_error_deg:.1f}",
            f"{m.p80_error_deg:.1f}",
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)
