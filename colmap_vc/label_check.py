"""Left and right exchanged: a camera whose person fits the other cameras better
with the labels swapped (a pose estimator that saw the person from the back and
took them for facing the camera) is re-posed with them, when the adjusted model
confirms it (:func:`try_exchange`). Used by the camera check
(:mod:`colmap_vc.camera_check`)."""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np
import pycolmap

from .keypoint_tracks import (
    KeypointTracks,
    add_keypoint_points,
    delete_points_observing,
    keypoint_observations,
    relabelled,
    residuals_px,
    solve_tracks,
    track_residuals,
    track_system,
)
from .structs import FloatArray, IndexArray

if TYPE_CHECKING:
    from .keypoint_ba import KeypointBaOptions

logger = logging.getLogger(__name__)


def robust_pnp(
    camera: pycolmap.Camera,
    xy: FloatArray,
    pts: FloatArray,
    options: KeypointBaOptions,
    max_error_px: float,
) -> tuple[float, pycolmap.Rigid3d | None]:
    """Robust PnP on keypoint 2D-3D pairs: (median error px, cam_from_world)."""
    if len(xy) < options.min_check_points:
        return np.inf, None
    est = pycolmap.AbsolutePoseEstimationOptions()
    est.ransac.max_error = max_error_px
    est.ransac.random_seed = options.check_seed
    found = pycolmap.estimate_and_refine_absolute_pose(xy, pts, camera, est)
    if found is None or found["num_inliers"] < options.min_check_points:
        return np.inf, None
    pose = found["cam_from_world"]
    return float(np.median(residuals_px(camera, pose.matrix(), xy, pts))), pose


ImageFit = tuple[FloatArray, FloatArray, IndexArray, "pycolmap.Rigid3d | None"]
"""An image's keypoints under one labelling against the other cameras' points:
(pixels, points, track ids, the image's PnP pose on all of them)."""


def image_fit(
    rec: pycolmap.Reconstruction,
    labels: KeypointTracks,
    image_id: int,
    others: tuple[FloatArray, IndexArray],
    options: KeypointBaOptions,
    max_error_px: float,
) -> ImageFit:
    """Image ``image_id``'s keypoints under ``labels`` whose points ``others``
    (the points all *other* cameras triangulate and their view counts) holds, and
    the image's best pose for all of them (:func:`robust_pnp`)."""
    X, counts = others
    mine = labels.image_id == image_id
    t = labels.track[mine]
    ok = (counts[t] >= 2) & np.isfinite(X[t]).all(axis=1)
    xy, pts, t = labels.xy_img[mine][ok], X[t[ok]], t[ok]
    camera = rec.camera(rec.image(image_id).camera_id)
    _, pose = robust_pnp(camera, xy, pts, options, max_error_px)
    return xy, pts, t, pose


def label_test(
    rec: pycolmap.Reconstruction,
    tracks: KeypointTracks,
    swapped: KeypointTracks,
    image_id: int,
    identity: int,
    others: tuple[FloatArray, IndexArray],
    options: KeypointBaOptions,
    max_error_px: float,
    as_labelled: ImageFit | None = None,
) -> tuple[float, float, int, pycolmap.Rigid3d | None]:
    """Person ``identity`` of image ``image_id`` as labelled against the same with
    left and right exchanged (``swapped``), each with the image at its best pose
    for all its keypoints, against ``others``: the points all *other* cameras
    triangulate and their view counts (the same for both labellings). Returns
    (the person's median error as labelled, exchanged, its number of keypoints,
    the image's pose with the exchanged labels). As labelled: the better of the
    current pose and PnP. ``as_labelled``: :func:`image_fit` of ``tracks``, the
    same for every person of the image (computed when not given)."""
    assert tracks.keys is not None
    image = rec.image(image_id)
    camera = rec.camera(image.camera_id)
    if as_labelled is None:
        as_labelled = image_fit(rec, tracks, image_id, others, options, max_error_px)
    exchanged = image_fit(rec, swapped, image_id, others, options, max_error_px)
    errors: list[float] = []
    count = 0
    for (xy, pts, t, pose), current in ((as_labelled, True), (exchanged, False)):
        theirs = tracks.keys[t, 0] == identity
        poses = [] if pose is None else [pose.matrix()]
        if current:
            poses.append(image.cam_from_world().matrix())
            count = int(theirs.sum())
        errors.append(
            min(
                (
                    float(np.median(residuals_px(camera, T, xy[theirs], pts[theirs])))
                    for T in poses
                    if theirs.any()
                ),
                default=np.inf,
            )
        )
    return errors[0], errors[1], count, exchanged[3]


def labels_exchanged(as_labelled: float, exchanged: float, n: int, z: float) -> bool:
    """Whether the exchanged labels fit better beyond the sampling error of the two
    medians: the median of n residual norms (2D Gaussian: Rayleigh) has a relative
    standard error of 1 / (2 ln 2 sqrt(n)), so log(exchanged / as labelled) of two
    such medians has sqrt(2) times that; the exchanged labels win when the log-ratio
    is ``z`` of those below zero."""
    if not (np.isfinite(as_labelled) and np.isfinite(exchanged)) or n == 0:
        return False
    se = np.sqrt(2.0) / (2.0 * np.log(2.0) * np.sqrt(n))
    return bool(np.log(exchanged / as_labelled) < -z * se)


def best_exchange(
    rec: pycolmap.Reconstruction,
    tracks: KeypointTracks,
    partner: IndexArray,
    candidates: list[int],
    options: KeypointBaOptions,
    limit_px: float,
    skip: set[tuple[int, int]],
) -> tuple[int, int, KeypointTracks, pycolmap.Rigid3d, float, float] | None:
    """Among the people of the ``candidates`` images, the one whose keypoints fit
    the other cameras' points most significantly better with left and right
    exchanged (:func:`labels_exchanged`, within ``limit_px``; (image, person)
    pairs in ``skip`` are not tried): (image id, person, the tracks with that
    person exchanged, the image's pose, median error as labelled, exchanged);
    None when nobody's do. One person at a time: a prior is
    turned per person, and another person of the image (or a false detection
    linked across two images) keeps its labels. Visited in name order, ties go to
    the first."""
    assert tracks.keys is not None
    Found = tuple[float, int, int, KeypointTracks, pycolmap.Rigid3d, float, float]
    best: Found | None = None
    system = track_system(rec, tracks)
    for i in sorted(candidates, key=lambda i: rec.image(i).name):
        others = solve_tracks(system, tracks, tracks.image_id == i)
        mine = tracks.track[tracks.image_id == i]
        fit = None  # as labelled: one PnP per image, whoever is exchanged
        for identity in np.unique(tracks.keys[mine[partner[mine] >= 0], 0]).tolist():
            if (i, identity) in skip:
                continue
            if fit is None:
                fit = image_fit(rec, tracks, i, others, options, limit_px)
            swapped = relabelled(tracks, i, partner, identity)
            as_labelled, exchanged, n, pose = label_test(
                rec, tracks, swapped, i, identity, others, options, limit_px, fit
            )
            logger.debug(
                "camera check: %s person %d as labelled %.1f px, exchanged %.1f px "
                "(%d keypoints)",
                rec.image(i).name,
                identity,
                as_labelled,
                exchanged,
                n,
            )
            if pose is None or exchanged > limit_px or n < options.min_check_points:
                continue
            if not labels_exchanged(as_labelled, exchanged, n, options.label_test_z):
                continue
            score = np.log(exchanged / as_labelled) * np.sqrt(n)
            if best is None or score < best[0]:
                best = (score, i, identity, swapped, pose, as_labelled, exchanged)
    return None if best is None else best[1:]


def exchange_labels_inplace(
    rec: pycolmap.Reconstruction,
    tracks: KeypointTracks,
    swapped: KeypointTracks,
    image_id: int,
    pose: pycolmap.Rigid3d,
    num_classic: dict[int, int],
    options: KeypointBaOptions,
    person: tuple[int, IndexArray] | None = None,
) -> None:
    """Re-pose image ``image_id`` at ``pose`` with its people's left and right
    exchanged: the keypoint points are rebuilt from ``swapped`` (``tracks`` with
    that image's keypoints on their counterparts' tracks) and the image's surface
    VCs, from the mesh turned front to back, leave the model. With ``person``
    (an identity and the identity of each of the image's VCs) only that person's
    surface VCs leave: a static camera's image holds every instant's people."""
    rec.frame(rec.image(image_id).frame_id).rig_from_world = pose
    delete_points_observing(rec, keypoint_observations(tracks))
    first = num_classic[image_id]
    surface = [
        k
        for k, p in enumerate(rec.image(image_id).points2D)  # loop over keypoints
        if k >= first
        and p.has_point3D()
        and (person is None or person[1][k - first] == person[0])
    ]
    for k in surface:  # its surface VCs
        rec.delete_observation(image_id, k)
    add_keypoint_points(rec, swapped, options.min_track_length)


def keypoint_cost(
    rec: pycolmap.Reconstruction, tracks: KeypointTracks, scale_px: float
) -> float:
    """Cauchy cost (scale ``scale_px``) of every keypoint observation in a posed
    image against the point all its views triangulate: one number to compare two
    labellings of the same observations."""
    r = track_residuals(rec, tracks)
    r = np.minimum(r[~np.isnan(r)], 1e6)  # behind the camera: the loss saturates
    return float(np.sum(scale_px**2 * np.log1p((r / scale_px) ** 2)))


def try_exchange(
    rec: pycolmap.Reconstruction,
    tracks: KeypointTracks,
    partner: IndexArray,
    candidates: list[int],
    options: KeypointBaOptions,
    limit_px: float,
    scale_px: float,
    num_classic: dict[int, int],
    adjust: Callable[[pycolmap.Reconstruction], object],
    vc_identity: dict[int, IndexArray] | None = None,
    done: set[tuple[int, int]] | None = None,
) -> tuple[KeypointTracks, int, int, float, float] | None:
    """Exchange left and right of the person :func:`best_exchange` finds, when
    the adjusted model then fits all keypoints better (:func:`keypoint_cost`):
    (the new tracks, the image re-posed, the person, median error as labelled,
    exchanged). An exchange the adjustment does not confirm is undone and the
    next person is tried; None when no exchange is confirmed. ``vc_identity``
    (per image, the identity of each VC) limits the surface VCs that leave to
    that person's; (image, person) pairs in ``done`` (exchanged before) are not
    tried again, the image's other people are: a static camera's image holds the
    same person seen from the back at several instants."""
    tried: set[tuple[int, int]] = set(done or ())
    before = keypoint_cost(rec, tracks, scale_px)
    while True:
        found = best_exchange(
            rec, tracks, partner, candidates, options, limit_px, tried
        )
        if found is None:
            return None
        image_id, identity, swapped, pose, as_labelled, exchanged = found
        trial = pycolmap.Reconstruction(rec)
        person = (
            None
            if vc_identity is None or image_id not in vc_identity
            else (identity, vc_identity[image_id])
        )
        exchange_labels_inplace(
            trial, tracks, swapped, image_id, pose, num_classic, options, person
        )
        adjust(trial)
        after = keypoint_cost(trial, swapped, scale_px)
        logger.debug(
            "camera check: %s person %d exchanged: keypoint cost %.4g -> %.4g",
            rec.image(image_id).name,
            identity,
            before,
            after,
        )
        if after < before:
            exchange_labels_inplace(
                rec, tracks, swapped, image_id, pose, num_classic, options, person
            )
            if not _adopt_adjusted(rec, trial):
                adjust(rec)
            return swapped, image_id, identity, as_labelled, exchanged
        tried.add((image_id, identity))


def _adopt_adjusted(
    rec: pycolmap.Reconstruction, trial: pycolmap.Reconstruction
) -> bool:
    """Give ``rec`` the poses and points of ``trial``, the same model adjusted, when
    both hold the same registered frames and points; returns whether it did.

    ``rec`` has just been changed as ``trial`` was before its adjustment, so the
    adjustment would reach ``trial``'s state again: one bundle adjustment fewer
    per confirmed exchange."""
    if sorted(rec.reg_frame_ids()) != sorted(trial.reg_frame_ids()):
        return False
    if sorted(rec.point3D_ids()) != sorted(trial.point3D_ids()):
        return False
    for frame_id in trial.reg_frame_ids():  # loop over the frames
        rec.frame(frame_id).rig_from_world = trial.frame(frame_id).rig_from_world
    for point_id, point in trial.points3D.items():  # loop over the model's points
        rec.point3D(point_id).xyz = point.xyz
    return True
