"""GBA cost: parameter vector, residuals and their analytic Jacobian (docs/gba.md).

Parameter vector ``x`` = [free pose parameters | classic points | VC tuple variables]:

- pose of image i: rotation vector ``w_i`` (``R_i = exp([w_i]x) R0_i``, R0 the
  problem's initial rotation) and translation ``t_i``; the gauge image and (without
  the metric prior) one translation coordinate of a second image are held fixed;
- classic point: X (3), when ``refine_classic_points``;
- VC tuple: hard ``[X1, a, b]`` (5), soft ``[X1, X2]`` (6).

Residual vector = [classic reprojections (O, 2) | VC rows (T, m)], row-major. VC rows:
reprojection of X1 in image 1 (2), of X2 in image 2 (2), soft coplanarity (1), then
with the metric prior: relative depth of X1 (1), of X2 (1), relative X2 - X1
displacement against the prior's thickness (3). Everything is vectorized over
observations and tuples; the only loops run over a handful of row blocks.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse

from ..structs import FloatArray, IndexArray
from .camera import intrinsics_table
from .problem import GbaOptions, GbaProblem, LossType, Parametrization
from .terms import (
    POSE_SIZE,
    Linearization,
    Poses,
    RowBlock,
    Segments,
    classic_terms,
    image_segments,
    make_poses,
    vc_row_blocks,
    vc_terms,
)

__all__ = [
    "POSE_SIZE",
    "Layout",
    "Linearization",
    "Poses",
    "RowBlock",
    "Segments",
    "image_segments",
    "vc_row_blocks",
]


@dataclass(frozen=True, slots=True)
class Layout:
    """Where each unknown lives in ``x`` (fixed by the problem and the options)."""

    pose_col: IndexArray  # (N, 6) column of [w, t] in x, -1 when held fixed
    num_pose_params: int
    point_offset: int
    num_points: int  # classic points in x (0 when they are constant)
    tuple_offset: int
    tuple_size: int  # 5 hard, 6 soft
    num_vcs: int
    num_params: int
    fixed_image_idx: int | None  # gauge: this pose is constant
    scale_fix: tuple[int, int] | None  # gauge: (image, translation coordinate) held


def layout(problem: GbaProblem, options: GbaOptions) -> Layout:
    """Parameter layout and gauge of a problem (deterministic)."""
    n = problem.num_images
    if not 0 <= options.gauge_image_idx < n:
        raise ValueError(f"gauge_image_idx={options.gauge_image_idx} outside [0, {n})")
    free = np.ones((n, POSE_SIZE), bool)
    # Images that nothing observes have no information: hold them.
    seen = np.zeros(n, bool)
    seen[problem.obs_image_idx] = True
    seen[problem.vc_image_idx1] = True
    seen[problem.vc_image_idx2] = True
    free[~seen] = False
    constant_points = not options.refine_classic_points and problem.num_points > 0
    fixed_image: int | None = None
    scale_fix: tuple[int, int] | None = None
    if not constant_points:  # constant points define the frame by themselves
        fixed_image = options.gauge_image_idx
        free[fixed_image] = False
        metric = options.metric_prior_weight > 0 and bool(problem.vc_has_prior.any())
        if not metric:
            # Hold the translation coordinate of the farthest image that moves most
            # under a scaling about the gauge camera (t1 + R1 c0 = R1 (c0 - c1)).
            R, t = problem.cam_from_world[:, :, :3], problem.cam_from_world[:, :, 3]
            c = -np.einsum("nji,nj->ni", R, t)
            dist = np.where(seen, np.linalg.norm(c - c[fixed_image], axis=1), 0.0)
            dist[fixed_image] = 0.0
            second = int(np.argmax(dist))
            if dist[second] > 0:
                moved = R[second] @ (c[fixed_image] - c[second])
                scale_fix = (second, int(np.argmax(np.abs(moved))))
                free[second, 3 + scale_fix[1]] = False
    pose_col = np.full((n, POSE_SIZE), -1, np.int64)
    pose_col[free] = np.arange(int(free.sum()))
    num_pose = int(free.sum())
    num_points = problem.num_points if options.refine_classic_points else 0
    k = 5 if options.parametrization == Parametrization.HARD else 6
    return Layout(
        pose_col=pose_col,
        num_pose_params=num_pose,
        point_offset=num_pose,
        num_points=num_points,
        tuple_offset=num_pose + 3 * num_points,
        tuple_size=k,
        num_vcs=problem.num_vcs,
        num_params=num_pose + 3 * num_points + k * problem.num_vcs,
        fixed_image_idx=fixed_image,
        scale_fix=scale_fix,
    )


def thickness_from_points(
    x1: FloatArray, x2: FloatArray, o1: FloatArray, o2: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Least-squares (a, b) of X2 - X1 = a (X1 - o1) + b (o2 - o1), all (T, 3)."""
    u, v, d = x1 - o1, o2 - o1, x2 - x1
    uu, uv, vv = (np.einsum("ti,ti->t", p, q) for p, q in ((u, u), (u, v), (v, v)))
    ud, vd = np.einsum("ti,ti->t", u, d), np.einsum("ti,ti->t", v, d)
    det = uu * vv - uv * uv
    ok = np.abs(det) > 1e-15 * np.maximum(uu * vv, 1e-300)
    det = np.where(ok, det, 1.0)
    a = np.where(
        ok,
        (vv * ud - uv * vd) / det,
        np.where(uu > 0, ud / np.maximum(uu, 1e-300), 0.0),
    )
    b = np.where(ok, (uu * vd - uv * ud) / det, 0.0)
    return a, b


def centres(cam_from_world: FloatArray) -> FloatArray:
    """(N, 3) camera centres of (N, 3, 4) poses."""
    return -np.einsum("nji,nj->ni", cam_from_world[:, :, :3], cam_from_world[:, :, 3])


def pack(
    problem: GbaProblem, options: GbaOptions, lay: Layout | None = None
) -> FloatArray:
    """The parameter vector of the problem's initial state (rotation vectors 0)."""
    lay = lay or layout(problem, options)
    x = np.zeros(lay.num_params)
    pose = np.zeros((problem.num_images, POSE_SIZE))
    pose[:, 3:] = problem.cam_from_world[:, :, 3]
    free = lay.pose_col >= 0
    x[lay.pose_col[free]] = pose[free]
    if lay.num_points:
        x[lay.point_offset : lay.tuple_offset] = problem.points_world.ravel()
    tup = np.zeros((problem.num_vcs, lay.tuple_size))
    tup[:, :3] = problem.vc_x1_world
    # Both parametrizations start from the same state: X2 projected onto the plane
    # (o1, X1, o2), i.e. (a, b) fitted by least squares (coplanar at the start).
    c = centres(problem.cam_from_world)
    o1, o2 = c[problem.vc_image_idx1], c[problem.vc_image_idx2]
    a, b = thickness_from_points(problem.vc_x1_world, problem.vc_x2_world, o1, o2)
    if options.parametrization == Parametrization.HARD:
        tup[:, 3], tup[:, 4] = a, b
    else:
        x1 = problem.vc_x1_world
        tup[:, 3:] = x1 + a[:, None] * (x1 - o1) + b[:, None] * (o2 - o1)
    x[lay.tuple_offset :] = tup.ravel()
    return x


def pose_vectors(x: FloatArray, problem: GbaProblem, lay: Layout) -> FloatArray:
    """(N, 6) [w, t] of every image, held values filled from the problem."""
    pose = np.zeros((problem.num_images, POSE_SIZE))
    pose[:, 3:] = problem.cam_from_world[:, :, 3]
    free = lay.pose_col >= 0
    pose[free] = x[lay.pose_col[free]]
    return pose


def poses_at(x: FloatArray, problem: GbaProblem, lay: Layout) -> Poses:
    """Rotations, translations, centres and their derivatives at x."""
    return make_poses(pose_vectors(x, problem, lay), problem.cam_from_world[:, :, :3])


def points_and_tuples(
    x: FloatArray, problem: GbaProblem, options: GbaOptions, lay: Layout
) -> tuple[FloatArray, FloatArray]:
    """(P, 3) classic points and (T, k) tuple variables at x."""
    if lay.num_points:
        points = x[lay.point_offset : lay.tuple_offset].reshape(-1, 3)
    else:
        points = problem.points_world
    return points, x[lay.tuple_offset :].reshape(-1, lay.tuple_size)


def linearize(
    x: FloatArray,
    problem: GbaProblem,
    options: GbaOptions,
    lay: Layout | None = None,
    intrinsics: FloatArray | None = None,
    jac: bool = True,
    segments: tuple[Segments, Segments] | None = None,
) -> Linearization:
    """Residual blocks (and Jacobian blocks with ``jac``) at x, unweighted by the loss.

    ``segments``: runs of VC tuples sharing image 1 and image 2 (tuples sorted by
    pair, see :func:`image_segments`), for faster per-image products.
    """
    lay = lay or layout(problem, options)
    if x.shape != (lay.num_params,):
        raise ValueError(f"x has shape {x.shape}, expected ({lay.num_params},)")
    K = intrinsics if intrinsics is not None else intrinsics_table(problem.cameras)
    poses = poses_at(x, problem, lay)
    points, tup = points_and_tuples(x, problem, options, lay)
    obs = classic_terms(points, problem, poses, K, jac)
    vc = vc_terms(
        np.ascontiguousarray(tup.T), problem, options, poses, K, jac, segments
    )
    return Linearization(
        obs_r=obs[0],
        obs_jpose=obs[1],
        obs_jpoint=obs[2],
        vc_r=vc[0],
        vc_jpose=vc[1],
        vc_jvar=vc[2],
    )


def residuals(
    x: FloatArray, problem: GbaProblem, options: GbaOptions | None = None
) -> FloatArray:
    """(M,) float64 residuals at x: classic reprojections, then VC rows (module doc).

    Pixels for reprojections, ~pixels for coplanarity, weighted relative errors for
    the prior; the robust loss is not applied (the solver applies it per block).
    """
    options = options or GbaOptions()
    lin = linearize(x, problem, options, jac=False)
    return np.concatenate([lin.obs_r.ravel(), lin.vc_r.T.ravel()])


def jacobian(
    x: FloatArray, problem: GbaProblem, options: GbaOptions | None = None
) -> scipy.sparse.csr_matrix:
    """Analytic Jacobian of :func:`residuals` at x, (M, len(x)) CSR."""
    options = options or GbaOptions()
    lay = layout(problem, options)
    lin = linearize(x, problem, options, lay=lay)
    return assemble_jacobian(lin, problem, lay)


def assemble_jacobian(
    lin: Linearization, problem: GbaProblem, lay: Layout
) -> scipy.sparse.csr_matrix:
    """CSR matrix of the Jacobian blocks (held parameters dropped)."""
    assert lin.obs_jpose is not None and lin.obs_jpoint is not None
    assert lin.vc_jpose is not None and lin.vc_jvar is not None
    num_obs, (m, num_vc) = len(lin.obs_r), lin.vc_r.shape
    rows, cols, vals = [], [], []

    def add(row: IndexArray, col: IndexArray, val: FloatArray) -> None:
        row, col = np.broadcast_arrays(row, col)
        keep = col >= 0
        rows.append(row[keep])
        cols.append(col[keep])
        vals.append(val[keep])

    obs_rows = (2 * np.arange(num_obs))[:, None, None] + np.arange(2)[None, :, None]
    add(obs_rows, lay.pose_col[problem.obs_image_idx][:, None, :], lin.obs_jpose)
    if lay.num_points:
        pcol = (
            lay.point_offset + 3 * problem.obs_point_idx[:, None, None] + np.arange(3)
        )
        add(obs_rows, pcol, lin.obs_jpoint)
    vc_rows = (
        2 * num_obs
        + (m * np.arange(num_vc))[:, None, None]
        + np.arange(m)[None, :, None]
    )
    pose_cols = np.concatenate(
        [lay.pose_col[problem.vc_image_idx1], lay.pose_col[problem.vc_image_idx2]],
        axis=1,
    )
    add(vc_rows, pose_cols[:, None, :], lin.vc_jpose.transpose(2, 1, 0))
    k = lay.tuple_size
    var_cols = lay.tuple_offset + (k * np.arange(num_vc))[:, None, None] + np.arange(k)
    add(vc_rows, var_cols, lin.vc_jvar.transpose(2, 1, 0))
    shape = (2 * num_obs + m * num_vc, lay.num_params)
    return scipy.sparse.csr_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
        shape=shape,
    )


def robust(
    s: FloatArray, loss: LossType, scale: float
) -> tuple[FloatArray, FloatArray]:
    """rho(s) and rho'(s) of squared norms s (Ceres' convention: cost = rho / 2)."""
    if loss == LossType.LINEAR:
        return s, np.ones_like(s)
    d2 = scale * scale
    if loss == LossType.HUBER:
        root = np.sqrt(s)
        inlier = s <= d2
        rho = np.where(inlier, s, 2.0 * scale * root - d2)
        return rho, np.where(inlier, 1.0, scale / np.maximum(root, 1e-300))
    if loss == LossType.CAUCHY:
        return d2 * np.log1p(s / d2), 1.0 / (1.0 + s / d2)
    raise ValueError(f"unknown loss {loss!r}")


def block_costs(
    lin: Linearization, options: GbaOptions
) -> tuple[float, FloatArray, FloatArray]:
    """Total cost and per-block sqrt(rho') weights: (O,) classic, (m, T) VC rows."""
    s = np.einsum("oi,oi->o", lin.obs_r, lin.obs_r)
    rho, d1 = robust(s, options.loss, options.loss_scale_px)
    total = 0.5 * float(rho.sum())
    w_vc = np.ones_like(lin.vc_r)
    for block in vc_row_blocks(options):
        sub = lin.vc_r[block.start : block.stop]
        sb = (sub * sub).sum(0)
        if block.robust:
            rb, db = robust(sb, options.loss, options.loss_scale_px)
            w_vc[block.start : block.stop] = np.sqrt(db)
        else:
            rb = sb
        total += 0.5 * float(rb.sum())
    return total, np.sqrt(d1), w_vc


def cost(
    x: FloatArray,
    problem: GbaProblem,
    options: GbaOptions,
    lay: Layout,
    intrinsics: FloatArray,
    segments: tuple[Segments, Segments] | None = None,
) -> tuple[float, FloatArray]:
    """Robust cost 1/2 sum rho(|r_block|^2) at x (inf if not finite), and the
    reprojection errors (2D norms, pixels) of all observations, classic then VC."""
    lin = linearize(
        x,
        problem,
        options,
        lay=lay,
        intrinsics=intrinsics,
        jac=False,
        segments=segments,
    )
    value = block_costs(lin, options)[0]
    sq = np.concatenate(
        [
            (lin.obs_r**2).sum(1),
            (lin.vc_r[0:2] ** 2).sum(0),
            (lin.vc_r[2:4] ** 2).sum(0),
        ]
    )
    return (value if np.isfinite(value) else np.inf), np.sqrt(sq)


def vc_num_rows(options: GbaOptions) -> int:
    """Residual rows per VC tuple."""
    return max(b.stop for b in vc_row_blocks(options))
