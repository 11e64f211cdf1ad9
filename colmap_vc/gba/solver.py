"""Solving GBA: Levenberg-Marquardt with a Schur complement on the poses, or scipy.

The LM solver eliminates every point block (classic point: 3 unknowns; VC tuple: 5 or
6) and solves the dense reduced system of the poses (6 per image), like Ceres'
DENSE_SCHUR. Per-tuple work is batched over tuples; the sums over the tuples of one
image pair are single BLAS products (tuples are sorted by pair first). The robust loss
is applied per residual block by reweighting (IRLS), Ceres' damping and trust-region
updates are mirrored so iteration counts compare. ``Solver.SCIPY`` runs
``scipy.optimize.least_squares`` (trf, sparse analytic Jacobian) as a reference.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass

import numpy as np
import scipy.optimize
import scipy.sparse

from ..structs import FloatArray, IndexArray
from . import model
from .camera import intrinsics_table
from .model import Layout
from .problem import GbaOptions, GbaProblem, Parametrization, Solver
from .schur import Schur, System, damped_step, normal_equations

logger = logging.getLogger(__name__)

_MIN_RELATIVE_DECREASE = 1e-3  # Ceres' min_relative_decrease
_MIN_DAMPING, _MAX_DAMPING = 1e-12, 1e16


@dataclass(frozen=True, kw_only=True, slots=True)
class GbaSummary:
    """What one GBA run did (JSON-friendly via dataclasses.asdict)."""

    parametrization: str
    solver: str
    num_images: int
    num_points: int
    num_observations: int
    num_vcs: int
    num_residuals: int
    num_parameters: int
    initial_cost: float
    final_cost: float
    initial_rms_px: float  # RMS reprojection error (2D norm) of all observations
    final_rms_px: float
    final_median_px: float  # median reprojection error
    num_outliers: int  # observations left > 10 x loss_scale_px off (robust loss)
    num_iterations: int  # step attempts (Ceres' count)
    num_successful_iterations: int
    termination: str  # function | gradient | parameter | max_iterations | no_progress
    time_s: float
    metric_scale: float  # initial scale applied for the metric prior (1: none)
    fixed_image_idx: int | None
    scale_fix: tuple[int, int] | None


@dataclass(frozen=True, kw_only=True, slots=True)
class GbaResult:
    """Refined geometry (rows as in the problem) and the run summary."""

    image_ids: IndexArray  # (N,) int64
    image_names: tuple[str, ...]
    cam_from_world: FloatArray  # (N, 3, 4)
    point3D_ids: IndexArray  # (P,) int64
    points_world: FloatArray  # (P, 3)
    vc_image_idx1: IndexArray  # (T,) int64
    vc_image_idx2: IndexArray  # (T,) int64
    x1_world: FloatArray  # (T, 3) first hit on ray 1
    x2_world: FloatArray  # (T, 3) first hit on ray 2
    a: FloatArray  # (T,) thickness: X2 = X1 + a (X1 - o1) + b (o2 - o1)
    b: FloatArray  # (T,)
    vc_point3D_id1: IndexArray  # (T,) int64, -1: none
    vc_point3D_id2: IndexArray  # (T,) int64
    summary: GbaSummary


@dataclass(slots=True)
class _Stats:
    initial_cost: float = 0.0
    final_cost: float = 0.0
    iterations: int = 0
    successful: int = 0
    termination: str = "max_iterations"
    initial_errors: FloatArray = dataclasses.field(default_factory=lambda: np.zeros(0))
    final_errors: FloatArray = dataclasses.field(default_factory=lambda: np.zeros(0))


def _apply(
    x: FloatArray,
    dc: FloatArray,
    dv: FloatArray,
    dp: FloatArray | None,
    st: Schur,
    lay: Layout,
) -> FloatArray:
    out = x.copy()
    out[: lay.num_pose_params] += dc[st.full_of_col]
    if dp is not None:
        out[lay.point_offset : lay.tuple_offset] += dp.ravel()
    out[lay.tuple_offset :] += dv.T.ravel()
    return out


def _recentred(
    x: FloatArray, problem: GbaProblem, lay: Layout
) -> tuple[FloatArray, GbaProblem]:
    """Fold the rotation vectors into the problem's rotations (x then has w = 0).

    The Jacobian at w = 0 needs no left Jacobian of SO(3), and rotation updates stay
    small, so the linearization is as accurate as a local parametrization's.
    """
    poses = model.poses_at(x, problem, lay)
    cam = np.concatenate([poses.R, poses.t[:, :, None]], axis=2)
    rot_cols = lay.pose_col[:, :3][lay.pose_col[:, :3] >= 0]
    out = x.copy()
    out[rot_cols] = 0.0
    return out, dataclasses.replace(problem, cam_from_world=cam)


def _lm(
    problem: GbaProblem, options: GbaOptions, lay: Layout, K: FloatArray
) -> tuple[FloatArray, GbaProblem, _Stats]:
    """Levenberg-Marquardt from the problem's initial state (Ceres' update rules).

    Returns the solution as x relative to the returned (re-centred) problem.
    """
    st = Schur(problem, lay)
    x = model.pack(problem, options, lay)
    stats = _Stats()
    cost, stats.initial_errors = model.cost(x, problem, options, lay, K, st.segments)
    stats.initial_cost = stats.final_cost = cost
    stats.final_errors = stats.initial_errors
    lam, nu = options.initial_damping, 2.0
    sys: System | None = None
    while stats.iterations < options.max_iterations:
        if sys is None:  # linearize lazily: not after the last step
            lin = model.linearize(
                x, problem, options, lay=lay, intrinsics=K, segments=st.segments
            )
            _, w_obs, w_vc = model.block_costs(lin, options)
            sys = normal_equations(lin, w_obs, w_vc, st)
            del lin
        grad = max(
            np.abs(sys.g[st.free]).max(initial=0.0),
            np.abs(sys.gv).max(initial=0.0),
            0.0 if sys.gp is None else np.abs(sys.gp).max(initial=0.0),
        )
        if grad <= options.gradient_tolerance:
            stats.termination = "gradient"
            break
        stats.iterations += 1
        dc, dv, dp, pred = damped_step(sys, st, lam)
        x_new = _apply(x, dc, dv, dp, st, lay)
        cost_new, errors_new = model.cost(x_new, problem, options, lay, K, st.segments)
        rho = (cost - cost_new) / pred if pred > 0 else -1.0
        step = np.sqrt(
            float(dc @ dc)
            + float((dv * dv).sum())
            + (0.0 if dp is None else float((dp * dp).sum()))
        )
        if np.isfinite(cost_new) and rho > _MIN_RELATIVE_DECREASE:
            stats.successful += 1
            lam = max(lam * max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3), _MIN_DAMPING)
            nu = 2.0
            decrease = cost - cost_new
            x, problem = _recentred(x_new, problem, lay)
            cost, stats.final_errors = cost_new, errors_new
            sys = None
            logger.debug("LM %d: cost %.6g, damping %.2g", stats.iterations, cost, lam)
            if decrease <= options.function_tolerance * (cost + decrease):
                stats.termination = "function"
                break
            if step <= options.parameter_tolerance * (
                np.linalg.norm(x) + options.parameter_tolerance
            ):
                stats.termination = "parameter"
                break
        else:
            lam, nu = lam * nu, 2.0 * nu
            if lam > _MAX_DAMPING:
                stats.termination = "no_progress"
                break
    stats.final_cost = cost
    return x, problem, stats


def _scipy(
    problem: GbaProblem, options: GbaOptions, lay: Layout, K: FloatArray
) -> tuple[FloatArray, GbaProblem, _Stats]:
    """scipy.optimize.least_squares (trf, lsmr) with the analytic sparse Jacobian.

    scipy applies its loss per scalar residual (not per 2D block), and its cost is
    reported in its own convention; the summary recomputes both costs ours.
    """
    x0 = model.pack(problem, options, lay)

    def fun(x: FloatArray) -> FloatArray:
        lin = model.linearize(x, problem, options, lay=lay, intrinsics=K, jac=False)
        return np.concatenate([lin.obs_r.ravel(), lin.vc_r.T.ravel()])

    def jac(x: FloatArray) -> scipy.sparse.csr_matrix:
        lin = model.linearize(x, problem, options, lay=lay, intrinsics=K)
        return model.assemble_jacobian(lin, problem, lay)

    res = scipy.optimize.least_squares(
        fun,
        x0,
        jac=jac,
        method="trf",
        x_scale="jac",
        tr_solver="lsmr",
        loss=str(options.loss),
        f_scale=options.loss_scale_px,
        max_nfev=options.max_iterations,
        ftol=options.function_tolerance or None,
        xtol=options.parameter_tolerance or None,
        gtol=options.gradient_tolerance or None,
    )
    (c0, errors0), (c1, errors1) = (
        model.cost(x, problem, options, lay, K) for x in (x0, res.x)
    )
    stats = _Stats(
        initial_cost=c0,
        final_cost=c1,
        initial_errors=errors0,
        final_errors=errors1,
        iterations=int(res.nfev),
        successful=int(res.njev or 0),
        termination={
            0: "max_iterations",
            1: "gradient",
            2: "function",
            3: "parameter",
            4: "function",
        }.get(res.status, "no_progress"),
    )
    return res.x, problem, stats


# ---------------------------------------------------------------- public


def _permuted(problem: GbaProblem, perm: IndexArray) -> GbaProblem:
    """The problem with its VC tuples reordered."""
    fields = {
        f.name: getattr(problem, f.name)[perm]
        for f in dataclasses.fields(problem)
        if f.name.startswith("vc_")
    }
    return dataclasses.replace(problem, **fields)


def _rms(errors: FloatArray) -> float:
    return float(np.sqrt((errors**2).mean())) if len(errors) else 0.0


def metric_scale(problem: GbaProblem) -> float:
    """Scale that brings the reconstruction to the priors' metres (median ratio).

    Uses the tuples' prior depth of X1 against the current depth of X1 (co-visible
    tuples only when there are some: there X1 is the triangulated point).
    """
    has = problem.vc_has_prior
    covisible = has & (problem.vc_kind == 0)
    sel = covisible if covisible.sum() >= 10 else has
    if not sel.any():
        return 1.0
    i1 = problem.vc_image_idx1[sel]
    R, t = problem.cam_from_world[i1, :, :3], problem.cam_from_world[i1, :, 3]
    z = np.einsum("mj,mj->m", R[:, 2], problem.vc_x1_world[sel]) + t[:, 2]
    ratio = problem.vc_prior_depth1[sel] / z
    ratio = ratio[np.isfinite(ratio) & (ratio > 0)]
    return float(np.median(ratio)) if len(ratio) else 1.0


def _scaled(problem: GbaProblem, s: float) -> GbaProblem:
    """The problem in a world scaled by s about the origin (R X + t -> s (R X + t))."""
    cam = problem.cam_from_world.copy()
    cam[:, :, 3] *= s
    return dataclasses.replace(
        problem,
        cam_from_world=cam,
        points_world=problem.points_world * s,
        vc_x1_world=problem.vc_x1_world * s,
        vc_x2_world=problem.vc_x2_world * s,
    )


def solve(problem: GbaProblem, options: GbaOptions | None = None) -> GbaResult:
    """Refine poses, classic points and VC tuples of a problem.

    With the metric prior on, the problem is first scaled to the priors' metres
    (:func:`metric_scale`), so the result is metric.
    """
    options = options or GbaOptions()
    t0 = time.perf_counter()
    scale = 1.0
    if options.metric_prior_weight > 0 and problem.vc_has_prior.any():
        scale = metric_scale(problem)
        problem = _scaled(problem, scale)
    key = problem.vc_image_idx1 * problem.num_images + problem.vc_image_idx2
    perm = np.argsort(key, kind="stable")
    sorted_problem = _permuted(problem, perm)
    lay = model.layout(sorted_problem, options)
    K = intrinsics_table(sorted_problem.cameras)
    if options.solver == Solver.LM:
        x, sorted_problem, stats = _lm(sorted_problem, options, lay, K)
    else:
        x, sorted_problem, stats = _scipy(sorted_problem, options, lay, K)
    poses = model.poses_at(x, sorted_problem, lay)
    points, tup = model.points_and_tuples(x, sorted_problem, options, lay)
    inv = np.argsort(perm)
    tup = tup[inv]
    i1, i2 = problem.vc_image_idx1, problem.vc_image_idx2
    o1, o2 = poses.centre[i1], poses.centre[i2]
    x1 = tup[:, :3]
    if options.parametrization == Parametrization.HARD:
        a, b = tup[:, 3].copy(), tup[:, 4].copy()
        x2 = x1 + a[:, None] * (x1 - o1) + b[:, None] * (o2 - o1)
    else:
        x2 = tup[:, 3:6].copy()
        a, b = model.thickness_from_points(x1, x2, o1, o2)
    elapsed = time.perf_counter() - t0
    errors_num = len(stats.final_errors)
    summary = GbaSummary(
        parametrization=str(options.parametrization),
        solver=str(options.solver),
        num_images=problem.num_images,
        num_points=problem.num_points,
        num_observations=problem.num_observations,
        num_vcs=problem.num_vcs,
        num_residuals=2 * problem.num_observations
        + problem.num_vcs * model.vc_num_rows(options),
        num_parameters=lay.num_params,
        initial_cost=stats.initial_cost,
        final_cost=stats.final_cost,
        initial_rms_px=_rms(stats.initial_errors),
        final_rms_px=_rms(stats.final_errors),
        final_median_px=float(np.median(stats.final_errors)) if errors_num else 0.0,
        num_outliers=int((stats.final_errors > 10 * options.loss_scale_px).sum()),
        num_iterations=stats.iterations,
        num_successful_iterations=stats.successful,
        termination=stats.termination,
        time_s=elapsed,
        metric_scale=scale,
        fixed_image_idx=lay.fixed_image_idx,
        scale_fix=lay.scale_fix,
    )
    logger.info(
        "GBA (%s, %s): %d images, %d points, %d VC tuples; cost %.4g -> %.4g, RMS "
        "%.3g -> %.3g px (median %.3g px, %d outliers), %d iterations (%s), %.2f s",
        summary.parametrization,
        summary.solver,
        summary.num_images,
        summary.num_points,
        summary.num_vcs,
        summary.initial_cost,
        summary.final_cost,
        summary.initial_rms_px,
        summary.final_rms_px,
        summary.final_median_px,
        summary.num_outliers,
        summary.num_iterations,
        summary.termination,
        elapsed,
    )
    return GbaResult(
        image_ids=problem.image_ids.copy(),
        image_names=problem.image_names,
        cam_from_world=np.concatenate([poses.R, poses.t[:, :, None]], axis=2),
        point3D_ids=problem.point3D_ids.copy(),
        points_world=np.array(points, copy=True),
        vc_image_idx1=i1.copy(),
        vc_image_idx2=i2.copy(),
        x1_world=np.array(x1, copy=True),
        x2_world=x2,
        a=a,
        b=b,
        vc_point3D_id1=problem.vc_point3D_id1.copy(),
        vc_point3D_id2=problem.vc_point3D_id2.copy(),
        summary=summary,
    )
