"""COLMAP's bundle adjustment with extra, individually weighted observations.

The generalized BA runs on COLMAP's own Ceres problem: pycolmap builds it for the
model's registered images (its pose manifolds, gauge, camera models and solver
options), every observation of a model point as COLMAP's reprojection cost with
its robust loss. The observations of the people's tracks (keypoints and surface
samples by identity) then leave COLMAP's cost and come back as pycolmap's
reprojection costs with a covariance of their own noise (:mod:`colmap_vc.gba.noise`)
on the same parameter blocks. pycolmap hands its problem to Python through pyceres,
whose ``Problem`` holds COLMAP's blocks by address: the model's poses and points
are numpy views of the reconstruction's own memory, so the solve writes into it.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import pyceres
import pycolmap
import pycolmap.cost_functions as cost_functions

from ..structs import FloatArray

logger = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True, slots=True)
class PeopleNoise:
    """Noise of the people observations, per image over its points2D."""

    sigma_px: Mapping[int, FloatArray]  # (num points2D,) noise px; NaN: classic
    robust_px: Mapping[int, FloatArray]  # (num points2D,) Cauchy scale px


def bundle_adjust_inplace(
    rec: pycolmap.Reconstruction,
    loss_scale_px: float,
    people: PeopleNoise | None = None,
) -> pycolmap.BundleAdjustmentSummary:
    """COLMAP's bundle adjustment of ``rec`` in place (intrinsics fixed).

    Args:
        rec: the model; every registered image is adjusted, the gauge fixed as
            COLMAP's global BA does (two cameras).
        loss_scale_px: scale of the Cauchy loss of the observations without a
            noise in ``people`` (classic keypoints), pixels.
        people: a model point all of whose observations have a noise there is
            weighted by them (covariance sigma^2 I, Cauchy loss at ``robust_px``);
            None: plain COLMAP BA.
    """
    options = pycolmap.BundleAdjustmentOptions(
        refine_focal_length=False,
        refine_principal_point=False,
        refine_extra_params=False,
        print_summary=False,
    )
    options.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
    options.ceres.loss_function_scale = loss_scale_px
    config = pycolmap.BundleAdjustmentConfig()
    for image_id in sorted(rec.reg_image_ids()):
        config.add_image(image_id)
    config.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
    adjuster = pycolmap.create_default_ceres_bundle_adjuster(options, config, rec)
    keep_alive = [] if people is None else _reweight(adjuster.problem, rec, people)
    summary = adjuster.solve()
    del keep_alive
    return summary


def _reweight(
    problem: pyceres.Problem, rec: pycolmap.Reconstruction, people: PeopleNoise
) -> list:
    """Replace the costs of the weighted points by covariance-weighted ones; returns
    the new cost and loss objects (alive until the solve is over)."""
    losses: dict[float, pyceres.LossFunction] = {}
    alive = []
    sigma_px, robust_px = people.sigma_px, people.robust_px
    for point_id, point in rec.points3D.items():  # loop over the model's points
        els = point.track.elements
        sig = [
            float(sigma_px[e.image_id][e.point2D_idx])
            if e.image_id in sigma_px
            else np.nan
            for e in els
        ]
        if not np.isfinite(sig).all() or not problem.has_parameter_block(point.xyz):
            continue
        xyz = rec.point3D(point_id).xyz  # a view of the model's memory
        problem.remove_parameter_block(xyz)
        for e, s in zip(els, sig, strict=True):  # loop over one point's views
            image = rec.image(e.image_id)
            pose = image.frame.rig_from_world.params
            camera = rec.camera(image.camera_id)
            if not problem.has_parameter_block(pose):
                continue
            xy = np.asarray(image.points2D[e.point2D_idx].xy, dtype=np.float64)
            scale = round(float(robust_px[e.image_id][e.point2D_idx]) / s, 3)
            loss = losses.setdefault(scale, pyceres.CauchyLoss(scale))
            cost = cost_functions.ReprojErrorCost(camera.model, (s * s) * np.eye(2), xy)
            problem.add_residual_block(cost, loss, [xyz, pose, camera.params])
            alive.append(cost)
    return alive + list(losses.values())
