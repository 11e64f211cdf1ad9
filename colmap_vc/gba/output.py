"""GBA outputs: refined reconstruction (a copy) and PLY files of the VC tuples."""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import pycolmap

from ..structs import FloatArray, PairVcMatches, VcKeypoints
from .problem import GbaOptions, build_problem
from .solver import GbaResult, solve

logger = logging.getLogger(__name__)


def meeting_points(result: GbaResult) -> FloatArray:
    """(T, 3) midpoints of the closest points of the tuples' two rays (via X1, X2)."""
    R, t = result.cam_from_world[:, :, :3], result.cam_from_world[:, :, 3]
    c = -np.einsum("nji,nj->ni", R, t)
    o1, o2 = c[result.vc_image_idx1], c[result.vc_image_idx2]
    d1, d2 = result.x1_world - o1, result.x2_world - o2
    d1 /= np.maximum(np.linalg.norm(d1, axis=1, keepdims=True), 1e-300)
    d2 /= np.maximum(np.linalg.norm(d2, axis=1, keepdims=True), 1e-300)
    w, b = o1 - o2, np.einsum("ti,ti->t", d1, d2)
    d, e = np.einsum("ti,ti->t", d1, w), np.einsum("ti,ti->t", d2, w)
    den = 1.0 - b * b
    ok = den > 1e-12
    den = np.where(ok, den, 1.0)
    s = np.where(ok, (b * e - d) / den, 0.0)
    u = np.where(ok, (e - b * d) / den, 0.0)
    mid = 0.5 * (o1 + s[:, None] * d1 + o2 + u[:, None] * d2)
    return np.where(ok[:, None], mid, result.x1_world)


def refine_reconstruction(
    rec: pycolmap.Reconstruction,
    vc_keypoints: Sequence[VcKeypoints],
    vc_pairs: Sequence[PairVcMatches],
    options: GbaOptions | None = None,
    *,
    image_id_to_num_classic: Mapping[int, int] | None = None,
    inliers_only: bool = True,
    max_vcs_per_pair: int | None = None,
) -> tuple[pycolmap.Reconstruction, GbaResult]:
    """GBA of a reconstruction and its VCs, written into a copy (input unchanged).

    The copy gets the refined poses and classic points (and, with the metric prior,
    everything else scaled to metres); 3D points COLMAP triangulated
    from VC keypoints move to the mean meeting point of the tuples that use them.
    """
    problem = build_problem(
        rec,
        vc_keypoints,
        vc_pairs,
        image_id_to_num_classic,
        inliers_only=inliers_only,
        max_vcs_per_pair=max_vcs_per_pair,
    )
    result = solve(problem, options)
    out = pycolmap.Reconstruction(rec)
    if result.summary.metric_scale != 1.0:  # the metric prior rescaled the world
        out.transform(
            pycolmap.Sim3d(
                result.summary.metric_scale, pycolmap.Rotation3d(), np.zeros(3)
            )
        )
    for image_id, P in zip(result.image_ids, result.cam_from_world, strict=True):
        image = out.images[int(image_id)]
        assert image.frame is not None  # registered images have a frame
        image.frame.set_cam_from_world(
            image.camera_id, pycolmap.Rigid3d(pycolmap.Rotation3d(P[:, :3]), P[:, 3])
        )
    for point3D_id, xyz in zip(result.point3D_ids, result.points_world, strict=True):
        out.points3D[int(point3D_id)].xyz = xyz
    # VC tracks COLMAP triangulated: mean meeting point of their tuples.
    ids = np.concatenate([result.vc_point3D_id1, result.vc_point3D_id2])
    if (ids >= 0).any():
        mid = np.concatenate([meeting_points(result)] * 2)
        keep = ids >= 0
        uniq, inv = np.unique(ids[keep], return_inverse=True)
        sums = np.zeros((len(uniq), 3))
        np.add.at(sums, inv, mid[keep])
        means = sums / np.bincount(inv)[:, None]
        for point3D_id, xyz in zip(uniq, means, strict=True):  # one write per 3D point
            if out.exists_point3D(int(point3D_id)):
                out.points3D[int(point3D_id)].xyz = xyz
    logger.info(
        "GBA: wrote %d poses and %d points into a copy of the reconstruction",
        len(result.image_ids),
        out.num_points3D(),
    )
    return out, result


def _write_ply(
    path: Path, xyz: FloatArray, rgb: np.ndarray, edges: np.ndarray | None = None
) -> None:
    """Binary little-endian PLY: float64 x y z, uchar red green blue, optional edges."""
    header = [
        "ply",
        "format binary_little_endian 1.0",
        f"element vertex {len(xyz)}",
        "property double x",
        "property double y",
        "property double z",
        "property uchar red",
        "property uchar green",
        "property uchar blue",
    ]
    if edges is not None:
        header += [
            f"element edge {len(edges)}",
            "property int vertex1",
            "property int vertex2",
        ]
    header.append("end_header")
    vertex = np.zeros(
        len(xyz),
        dtype=[
            ("x", "<f8"),
            ("y", "<f8"),
            ("z", "<f8"),
            ("r", "u1"),
            ("g", "u1"),
            ("b", "u1"),
        ],
    )
    vertex["x"], vertex["y"], vertex["z"] = xyz.T
    vertex["r"], vertex["g"], vertex["b"] = rgb.T
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        f.write(vertex.tobytes())
        if edges is not None:
            f.write(np.ascontiguousarray(edges, dtype="<i4").tobytes())


def export_ply(result: GbaResult, path_vc: Path, path_points: Path) -> None:
    """Write the VC tuples and the scene points as PLY (binary, readable by trimesh).

    ``path_vc``: X1 (red) then X2 (blue) of every tuple, with an edge X1-X2 per tuple.
    ``path_points``: classic points (grey) and camera centres (green).
    """
    num = len(result.x1_world)
    xyz = np.concatenate([result.x1_world, result.x2_world]).reshape(-1, 3)
    rgb = np.concatenate(
        [np.tile([230, 40, 40], (num, 1)), np.tile([40, 80, 230], (num, 1))]
    ).astype(np.uint8)
    edges = np.stack([np.arange(num), num + np.arange(num)], axis=1)
    _write_ply(Path(path_vc), xyz, rgb.reshape(-1, 3), edges)
    R, t = result.cam_from_world[:, :, :3], result.cam_from_world[:, :, 3]
    centres = -np.einsum("nji,nj->ni", R, t)
    pts = np.concatenate([result.points_world, centres]).reshape(-1, 3)
    colors = np.concatenate(
        [
            np.tile([160, 160, 160], (len(result.points_world), 1)),
            np.tile([40, 200, 40], (len(centres), 1)),
        ]
    ).astype(np.uint8)
    _write_ply(Path(path_points), pts, colors.reshape(-1, 3))
    logger.info(
        "wrote %d VC tuples to %s and %d points to %s",
        num,
        path_vc,
        len(pts),
        path_points,
    )
