"""COLMAP's bundle adjustment with extra, individually weighted observations.

The generalized BA runs on COLMAP's own Ceres problem: pycolmap builds it for the
model's registered images (its pose manifolds, gauge, camera models and solver
options), every observation of a model point as COLMAP's reprojection cost with
its robust loss. The observations of the people's tracks (keypoints and surface
samples by identity) are not COLMAP's: they enter the same problem as pycolmap's
reprojection costs weighted by their own noise (:mod:`colmap_vc.gba.noise`), on
COLMAP's pose blocks. pycolmap hands its problem to Python through pyceres, whose
``Problem`` holds COLMAP's blocks by address: the poses are numpy views of the
reconstruction's own memory, so the solve writes into them.

COLMAP's problem is built on a copy of the model without the weighted points
(Ceres removes a block in time linear in the problem, as COLMAP does not enable
fast removal): only where an image would then have no point at all, one of its
weighted points stays to put its pose into the problem, with COLMAP's manifold,
and is removed again.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import pyceres
import pycolmap
import pycolmap.cost_functions as cost_functions

from ..colmap_log import colmap_quiet
from ..structs import FloatArray
from .up import UpPriors, add_up_priors

logger = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True, slots=True)
class PeopleNoise:
    """Noise of the people observations, per image over its points2D."""

    sigma_px: Mapping[int, FloatArray]  # (num points2D,) noise px; NaN: classic
    robust_px: Mapping[int, FloatArray]  # (num points2D,) Cauchy scale px

    @classmethod
    def none(cls, rec: pycolmap.Reconstruction) -> PeopleNoise:
        """No noise (every observation COLMAP's) for each posed image of ``rec``:
        arrays to fill in."""
        sigma = {
            i: np.full(im.num_points2D(), np.nan)
            for i, im in rec.images.items()
            if im.has_pose
        }
        return cls(sigma_px=sigma, robust_px={i: v.copy() for i, v in sigma.items()})

    def _copy(self) -> tuple[dict[int, FloatArray], dict[int, FloatArray]]:
        return (
            {i: v.copy() for i, v in self.sigma_px.items()},
            {i: v.copy() for i, v in self.robust_px.items()},
        )

    def or_else(self, other: PeopleNoise) -> PeopleNoise:
        """This noise, and ``other``'s where this has none."""
        sigma, robust = self._copy()
        for i, v in other.sigma_px.items():  # loop over images
            if i not in sigma:
                sigma[i], robust[i] = v.copy(), other.robust_px[i].copy()
                continue
            fill = np.isnan(sigma[i]) & np.isfinite(v)
            sigma[i][fill] = v[fill]
            robust[i][fill] = other.robust_px[i][fill]
        return PeopleNoise(sigma_px=sigma, robust_px=robust)

    def without(self, image_id: np.ndarray, point2D_idx: np.ndarray) -> PeopleNoise:
        """This noise with none for the given observations (rows of the two)."""
        sigma, robust = self._copy()
        for i in np.unique(image_id).tolist():  # loop over images
            if i in sigma:
                rows = point2D_idx[image_id == i]
                rows = rows[rows < len(sigma[i])]
                sigma[i][rows] = np.nan
                robust[i][rows] = np.nan
        return PeopleNoise(sigma_px=sigma, robust_px=robust)


# Ceres stops once an iteration lowers the cost by less than this fraction of it.
# COLMAP sets none (0.0), so its adjustments run until the gradient tolerance or
# 100 iterations: a 128-image model with 124k people observations took 101
# iterations, 46 s per adjustment, for 11 s at this tolerance (23 iterations). The
# people's residuals are whitened by their noise and the classic ones are pixels,
# whose noise is about one, so a model of N observations at its noise costs about
# N / 2 and this stops on a gain below 0.1 for N under 200k: a fifth of the 1/2
# that moving one parameter by one standard deviation adds. Measured on the
# benchmarks (docs/benchmark.md, "Bundle adjustment's stopping rule").
FUNCTION_TOLERANCE = 1e-6


def ba_options(loss_scale_px: float) -> pycolmap.BundleAdjustmentOptions:
    """COLMAP's BA options colmap-vc adjusts with: intrinsics fixed (known), a
    Cauchy loss at ``loss_scale_px``, stopping at :data:`FUNCTION_TOLERANCE`."""
    options = pycolmap.BundleAdjustmentOptions(
        refine_focal_length=False,
        refine_principal_point=False,
        refine_extra_params=False,
        print_summary=False,
    )
    options.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
    options.ceres.loss_function_scale = loss_scale_px
    options.ceres.solver_options.function_tolerance = FUNCTION_TOLERANCE
    return options


def log_rounded(sigma: np.ndarray, step: float = 0.02) -> np.ndarray:
    """``sigma`` rounded to 2% steps: one whitened camera block per (camera, value)
    (:func:`bundle_adjust_inplace`), a few dozen, not one per observation."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.exp(np.round(np.log(sigma) / step) * step)


def bundle_adjust_inplace(
    rec: pycolmap.Reconstruction,
    loss_scale_px: float,
    people: PeopleNoise | None = None,
    up: UpPriors | None = None,
) -> pyceres.SolverSummary:
    """COLMAP's bundle adjustment of ``rec`` in place (intrinsics fixed).

    Args:
        rec: the model; every registered image is adjusted, the gauge fixed as
            COLMAP's global BA does (two cameras).
        loss_scale_px: scale of the Cauchy loss of the observations without a
            noise in ``people`` (classic keypoints), pixels.
        people: a model point all of whose observations have a noise there is
            weighted by them (1 / sigma^2, Cauchy loss at ``robust_px``); None:
            plain COLMAP BA.
        up: measured up directions of some cameras (:mod:`colmap_vc.gba.up`);
            used with two or more.
    """
    options = ba_options(loss_scale_px)
    config = pycolmap.BundleAdjustmentConfig()
    for image_id in sorted(rec.reg_image_ids()):
        config.add_image(image_id)
    config.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
    observed = None if people is None else _people_observations(rec, people)
    weighted = [] if observed is None else observed.point_ids
    if not weighted:
        adjuster = pycolmap.create_default_ceres_bundle_adjuster(options, config, rec)
        alive = _add_up(adjuster.problem, rec, up)
        summary = _solve(adjuster, options, config)
        del alive
        restore_cheirality_inplace(rec)
        return summary
    assert people is not None and observed is not None
    work = pycolmap.Reconstruction(rec)
    anchors = _anchors(work, weighted)
    for point_id in sorted(set(weighted) - set(anchors)):
        work.delete_point3D(point_id)
    adjuster = pycolmap.create_default_ceres_bundle_adjuster(options, config, work)
    for point_id in anchors:
        adjuster.problem.remove_parameter_block(work.point3D(point_id).xyz)
    X = np.array([rec.point3D(p).xyz for p in weighted], dtype=np.float64)
    keep_alive = _add_weighted(adjuster.problem, work, observed, X, people)
    keep_alive += _add_up(adjuster.problem, work, up)
    summary = _solve(adjuster, options, config)
    del keep_alive
    for image_id in work.reg_image_ids():  # loop over images: the solved poses
        frame_id = work.image(image_id).frame_id
        rec.frame(frame_id).rig_from_world = work.frame(frame_id).rig_from_world
    for point_id, point in work.points3D.items():  # the classic points
        if point_id not in anchors:
            rec.point3D(point_id).xyz = point.xyz
    for row, point_id in enumerate(weighted):  # loop over the people's points
        rec.point3D(point_id).xyz = X[row]
    restore_cheirality_inplace(rec)
    return summary


def restore_cheirality_inplace(rec: pycolmap.Reconstruction) -> bool:
    """Reflect ``rec`` through the origin when most of its observations lie behind
    their cameras; returns whether it did.

    A reprojection error cannot tell a model from its point reflection (every
    point X -> -X, every camera centre C -> -C, the rotations kept): a point's
    coordinates in a camera all change sign, the numerator and the denominator of
    its projection alike. A Levenberg-Marquardt step from a poor start can cross
    the cameras' planes and land the whole model there. pose2sim_single t050
    (`bench/pose2sim.py`, seed 1): the mesh-initialised model, cameras 4-28 deg
    off and every point in front, came out of the keypoint BA with 594 of its
    598 observations behind their cameras and the relative translations 177-179
    deg off; the outputs then dropped every point and kept three wrong cameras.
    The reflection is the same optimum in front of the cameras. A majority of
    the observations decides which side the model is on (COLMAP's filter, which
    also drops a point's last observation in front with it). Models with rigs of
    several sensors are left as they are (a rig's offsets do not reflect).
    """
    total = rec.compute_num_observations()
    if total == 0:
        return False
    probe = pycolmap.Reconstruction(rec)
    pycolmap.ObservationManager(probe).filter_observations_with_negative_depth()
    behind = total - probe.compute_num_observations()  # with the points they leave
    if 2 * behind <= total:
        return False
    rigs = {rec.frame(frame_id).rig_id for frame_id in rec.reg_frame_ids()}
    if any(rec.rig(rig_id).num_sensors() > 1 for rig_id in rigs):
        logger.warning(
            "bundle adjustment: %d of %d observations behind their cameras; a "
            "model with multi-sensor rigs is not reflected back",
            behind,
            total,
        )
        return False
    rec.transform(pycolmap.Sim3d(-1.0, pycolmap.Rotation3d(), np.zeros(3)))
    logger.info(
        "bundle adjustment: %d of %d observations had crossed behind their "
        "cameras (the model's point reflection, the same reprojection errors): "
        "reflected back in front",
        behind,
        total,
    )
    return True


def _solve(
    adjuster: pycolmap.CeresBundleAdjuster,
    options: pycolmap.BundleAdjustmentOptions,
    config: pycolmap.BundleAdjustmentConfig,
) -> pyceres.SolverSummary:
    """Solve the adjuster's problem with COLMAP's solver options for it, through
    pyceres, which lets go of Python's lock while Ceres runs.

    The cameras' up residuals are Python cost functions. pycolmap's own
    ``adjuster.solve()`` keeps the lock, so once a problem is large enough for
    COLMAP to evaluate it on several threads (50000 residuals), a worker thread
    waits for the lock forever: `map` hung on pose2sim_multi's 20 images with
    ``--gba``, and would on any large model with measured ups.
    """
    solver = pyceres.SolverOptions()
    solver.mergedict(
        options.ceres.create_solver_options(config, adjuster.problem).todict()
    )
    summary = pyceres.SolverSummary()
    with colmap_quiet(logger):
        pyceres.solve(solver, adjuster.problem, summary)
    return summary


def _add_up(
    problem: pyceres.Problem, rec: pycolmap.Reconstruction, up: UpPriors | None
) -> list:
    """The up residuals on ``rec``'s pose blocks in ``problem`` (none without
    ``up``); returns what must stay alive until the solve."""
    if up is None:
        return []
    blocks = {}
    for image_id in up.image_id.tolist():  # loop over the measured cameras
        if image_id in rec.images and rec.image(image_id).has_pose:
            block = _pose_block(rec, rec.image(image_id))
            if problem.has_parameter_block(block):
                blocks[image_id] = block
    if len(blocks) < 2:
        return []
    block, alive = add_up_priors(problem, blocks, up)
    return [block, *alive]


def weighted_points(rec: pycolmap.Reconstruction, people: PeopleNoise) -> list[int]:
    """The model points all of whose observations have a noise, in id order."""
    return _people_observations(rec, people).point_ids


@dataclass(frozen=True, kw_only=True, slots=True)
class _Observations:
    """The observations of the weighted points, one row each, in point id order."""

    point_ids: list[int]  # the weighted points, in id order
    row: np.ndarray  # (M,) int64: the point's index in point_ids
    image_id: np.ndarray  # (M,) int64
    point2D_idx: np.ndarray  # (M,) int64


def _people_observations(
    rec: pycolmap.Reconstruction, people: PeopleNoise
) -> _Observations:
    """One pass over the model's tracks: the weighted points and their
    observations (the setup of a bundle adjustment of thousands of people's
    points is this and adding their residuals, bench/gba_speed.py)."""
    ids, lengths, image_ids, idxs = [], [], [], []
    for point_id in sorted(rec.point3D_ids()):  # loop over the model's points
        els = rec.point3D(point_id).track.elements
        ids.append(point_id)
        lengths.append(len(els))
        image_ids += [e.image_id for e in els]
        idxs += [e.point2D_idx for e in els]
    point_of = np.repeat(np.arange(len(ids)), lengths)
    image_of = np.asarray(image_ids, dtype=np.int64)
    idx_of = np.asarray(idxs, dtype=np.int64)
    finite = np.zeros(len(image_of), dtype=bool)
    for image_id in np.unique(image_of).tolist():  # loop over images
        if image_id in people.sigma_px:
            sel = np.flatnonzero(image_of == image_id)
            finite[sel] = np.isfinite(people.sigma_px[image_id][idx_of[sel]])
    bad = np.zeros(len(ids), dtype=bool)
    np.logical_or.at(bad, point_of, ~finite)
    keep = ~bad
    rows = np.cumsum(keep) - 1
    obs = keep[point_of]
    return _Observations(
        point_ids=[p for p, k in zip(ids, keep.tolist(), strict=True) if k],
        row=rows[point_of[obs]],
        image_id=image_of[obs],
        point2D_idx=idx_of[obs],
    )


def _anchors(rec: pycolmap.Reconstruction, weighted: list[int]) -> list[int]:
    """A few weighted points, so that every registered image keeps one point in
    the copy COLMAP builds its problem from (and its pose its manifold)."""
    weighted_set = set(weighted)
    covered = set()
    for point_id, point in rec.points3D.items():  # loop over the model's points
        if point_id not in weighted_set:
            covered |= {e.image_id for e in point.track.elements}
    need = set(rec.reg_image_ids()) - covered
    anchors = []
    for point_id in weighted:  # in id order: each that covers an uncovered image
        if not need:
            break
        seen = {e.image_id for e in rec.point3D(point_id).track.elements} & need
        if seen:
            anchors.append(point_id)
            need -= seen
    return anchors


def _pose_block(rec: pycolmap.Reconstruction, image: pycolmap.Image) -> np.ndarray:
    """The image's pose parameters: a view of the model's memory, the block COLMAP's
    problem holds (the image is its frame's only one)."""
    pose = rec.frame(image.frame_id).rig_from_world
    assert pose is not None, f"{image.name} has no pose"
    return pose.params


def _whitened_params(camera: pycolmap.Camera, sigma_px: float) -> np.ndarray:
    """Camera parameters whose pixels are the camera's divided by ``sigma_px``.

    Every COLMAP camera model maps its distorted normalised coordinates to pixels
    by the focal lengths and the principal point, so dividing those by sigma
    divides the reprojection error by sigma: the observation is weighted by
    1 / sigma^2 with pycolmap's plain reprojection cost (its covariance-weighted
    cost evaluates 4x slower, bench/gba_speed.py)."""
    params = np.array(camera.params, dtype=np.float64)
    idx = [*camera.focal_length_idxs(), *camera.principal_point_idxs()]
    params[idx] /= sigma_px
    return params


def _add_weighted(
    problem: pyceres.Problem,
    work: pycolmap.Reconstruction,
    observed: _Observations,
    X: np.ndarray,
    people: PeopleNoise,
) -> list:
    """Add the observations of the weighted points (rows of ``X``) to ``problem``,
    on the poses of ``work``; returns the new blocks and cost and loss objects
    (alive until the solve is over).

    An observation with noise sigma is seen through its camera scaled by 1/sigma
    (:func:`_whitened_params`, one constant block per camera and sigma), with its
    pixel divided by sigma and a Cauchy loss at its robust scale over sigma.
    """
    image_of, idx_of = observed.image_id, observed.point2D_idx
    sigma = np.empty(len(image_of))
    robust = np.empty(len(image_of))
    xy = np.empty((len(image_of), 2))
    posed = np.zeros(len(image_of), dtype=bool)
    for image_id in np.unique(image_of).tolist():  # loop over images
        sel = np.flatnonzero(image_of == image_id)
        image = work.image(image_id)
        sigma[sel] = people.sigma_px[image_id][idx_of[sel]]
        robust[sel] = people.robust_px[image_id][idx_of[sel]]
        points2D = image.points2D
        xy[sel] = [points2D[k].xy for k in idx_of[sel].tolist()]
        posed[sel] = problem.has_parameter_block(_pose_block(work, image))
    sigma = np.round(sigma, 4)
    xy /= sigma[:, None]
    scale = np.round(robust / sigma, 3)
    obs = np.flatnonzero(posed)
    # One constant block of whitened camera parameters per (camera, sigma), one
    # Cauchy loss per scale: indices per observation, then a lean loop.
    camera_of = {i: work.image(i).camera_id for i in np.unique(image_of).tolist()}
    cam = np.array([camera_of[i] for i in image_of[obs].tolist()], dtype=np.int64)
    sigmas, sigma_of = np.unique(sigma[obs], return_inverse=True)
    keys, key_of = np.unique(cam * len(sigmas) + sigma_of, return_inverse=True)
    whitened = []
    for key in keys.tolist():  # loop over (camera, sigma) pairs
        camera_id, s = divmod(key, len(sigmas))
        params = _whitened_params(work.camera(camera_id), float(sigmas[s]))
        problem.add_parameter_block(params, len(params))
        problem.set_parameter_block_constant(params)
        whitened.append(params)
    loss_values, loss_of = np.unique(scale[obs], return_inverse=True)
    losses = [pyceres.CauchyLoss(v) for v in loss_values.tolist()]
    poses = {  # COLMAP's pose blocks
        i: _pose_block(work, work.image(i)) for i in np.unique(image_of[obs]).tolist()
    }
    model_of = {i: work.camera(camera_of[i]).model for i in poses}
    points = list(X)  # row views: one parameter block per point
    make = cost_functions.ReprojErrorCost
    costs = [  # loop over the observations
        make(model_of[i], p)
        for i, p in zip(image_of[obs].tolist(), xy[obs], strict=True)
    ]
    add = problem.add_residual_block
    for cost, row, image_id, k, loss in zip(  # loop over the observations
        costs,
        observed.row[obs].tolist(),
        image_of[obs].tolist(),
        key_of.ravel().tolist(),
        loss_of.ravel().tolist(),
        strict=True,
    ):
        add(cost, losses[loss], [points[row], poses[image_id], whitened[k]])
    return costs + whitened + losses
