"""Left and right exchanged: a camera whose person fits the other cameras better
with the labels swapped (a pose estimator that saw the person from the back and
took them for facing the camera) is re-posed with them, when the adjusted model
confirms it (:func:`try_exchange`). Used by the camera check
(:mod:`colmap_vc.camera_check`)."""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import TYPE_CHECKING, NamedTuple

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


class Exchange(NamedTuple):
    """One person whose labels fit better exchanged (:func:`exchange_of`)."""

    image_id: int
    identity: int
    swapped: KeypointTracks  # the tracks with that person exchanged
    pose: pycolmap.Rigid3d  # the image's pose with the exchanged labels
    as_labelled: float  # the person's median error as labelled, px
    exchanged: float  # and exchanged, px
    score: float  # log(exchanged / as labelled) sqrt(n): lower is clearer


def exchange_of(
    rec: pycolmap.Reconstruction,
    tracks: KeypointTracks,
    partner: IndexArray,
    image_id: int,
    identity: int,
    others: tuple[FloatArray, IndexArray],
    fit: ImageFit,
    options: KeypointBaOptions,
    limit_px: float,
) -> Exchange | None:
    """Person ``identity`` of image ``image_id`` exchanged, when their keypoints
    fit significantly better so (:func:`labels_exchanged`, within ``limit_px``);
    ``others`` and ``fit`` as :func:`label_test` takes them."""
    swapped = relabelled(tracks, image_id, partner, identity)
    as_labelled, exchanged, n, pose = label_test(
        rec, tracks, swapped, image_id, identity, others, options, limit_px, fit
    )
    logger.debug(
        "camera check: %s person %d as labelled %.1f px, exchanged %.1f px "
        "(%d keypoints)",
        rec.image(image_id).name,
        identity,
        as_labelled,
        exchanged,
        n,
    )
    if pose is None or exchanged > limit_px or n < options.min_check_points:
        return None
    if not labels_exchanged(as_labelled, exchanged, n, options.label_test_z):
        return None
    score = float(np.log(exchanged / as_labelled) * np.sqrt(n))
    return Exchange(image_id, identity, swapped, pose, as_labelled, exchanged, score)


def _exchangeable(
    tracks: KeypointTracks, partner: IndexArray, image_id: int
) -> list[int]:
    """The identities of image ``image_id`` with keypoints that have a mirror."""
    assert tracks.keys is not None
    mine = tracks.track[tracks.image_id == image_id]
    return np.unique(tracks.keys[mine[partner[mine] >= 0], 0]).tolist()


def ranked_exchanges(
    rec: pycolmap.Reconstruction,
    tracks: KeypointTracks,
    partner: IndexArray,
    candidates: list[int],
    options: KeypointBaOptions,
    limit_px: float,
    skip: set[tuple[int, int]],
) -> list[Exchange]:
    """Every person of the ``candidates`` images whose keypoints fit the other
    cameras' points significantly better with left and right exchanged
    (:func:`exchange_of`; (image, person) pairs in ``skip`` are not tried), most
    significant first. One person at a time: a prior is turned per person, and
    another person of the image (or a false detection linked across two images)
    keeps its labels. Visited in name order, ties go to the first."""
    found: list[Exchange] = []
    system = track_system(rec, tracks)
    for i in sorted(candidates, key=lambda i: rec.image(i).name):
        others = solve_tracks(system, tracks, tracks.image_id == i)
        fit = None  # as labelled: one PnP per image, whoever is exchanged
        for identity in _exchangeable(tracks, partner, i):
            if (i, identity) in skip:
                continue
            if fit is None:
                fit = image_fit(rec, tracks, i, others, options, limit_px)
            one = exchange_of(
                rec, tracks, partner, i, identity, others, fit, options, limit_px
            )
            if one is not None:
                found.append(one)
    return sorted(found, key=lambda e: e.score)  # stable: name order on ties


def retest(
    rec: pycolmap.Reconstruction,
    tracks: KeypointTracks,
    partner: IndexArray,
    image_id: int,
    identity: int,
    options: KeypointBaOptions,
    limit_px: float,
) -> Exchange | None:
    """:func:`exchange_of` of one person on the model as it is now."""
    if identity not in _exchangeable(tracks, partner, image_id):
        return None
    others = solve_tracks(
        track_system(rec, tracks), tracks, tracks.image_id == image_id
    )
    fit = image_fit(rec, tracks, image_id, others, options, limit_px)
    return exchange_of(
        rec, tracks, partner, image_id, identity, others, fit, options, limit_px
    )


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
    pending: list[tuple[int, int]] | None = None,
) -> Exchange | None:
    """Exchange left and right of the most significant person
    :func:`ranked_exchanges` finds, when the adjusted model then fits all
    keypoints better (:func:`keypoint_cost`), and return it. An exchange the
    adjustment does not confirm is undone and the next person is tried; None when
    no exchange is confirmed. ``vc_identity`` (per image, the identity of each
    VC) limits the surface VCs that leave to that person's; (image, person) pairs
    in ``done`` (exchanged before) are not tried again, the image's other people
    are: a static camera's image holds the same person seen from the back at
    several instants.

    ``pending`` (updated in place, kept between calls): the (image, person)
    pairs an earlier ranking found and nobody has tried, most significant first.
    Each is tested again on the model as it is now before it is tried; everybody
    is ranked again only when none is left. An exchange changes one person's
    points and one image's pose, and the others' tests little; with static
    cameras a ranking per exchange grew with the cube of the instants."""
    tried: set[tuple[int, int]] = set(done or ())
    pending = [] if pending is None else pending
    ranked: list[Exchange] = []  # this model's ranking (a failed trial keeps it)
    ranked_once = False  # the model changes only when this call returns
    before = keypoint_cost(rec, tracks, scale_px)
    while True:
        if ranked:
            found: Exchange | None = ranked.pop(0)
        elif pending:
            image_id, identity = pending.pop(0)
            if (image_id, identity) in tried or image_id not in candidates:
                continue
            found = retest(rec, tracks, partner, image_id, identity, options, limit_px)
        else:
            if ranked_once:
                return None  # every person this model ranks has been tried
            ranked_once = True
            ranked = ranked_exchanges(
                rec, tracks, partner, candidates, options, limit_px, tried
            )
            if not ranked:
                return None
            continue
        if found is None:  # no longer significant
            continue
        image_id, identity = found.image_id, found.identity
        trial = pycolmap.Reconstruction(rec)
        person = (
            None
            if vc_identity is None or image_id not in vc_identity
            else (identity, vc_identity[image_id])
        )
        change = (tracks, found.swapped, image_id, found.pose, num_classic, options)
        exchange_labels_inplace(trial, *change, person)
        adjust(trial)
        after = keypoint_cost(trial, found.swapped, scale_px)
        logger.debug(
            "camera check: %s person %d exchanged: keypoint cost %.4g -> %.4g",
            rec.image(image_id).name,
            identity,
            before,
            after,
        )
        if after < before:
            exchange_labels_inplace(rec, *change, person)
            if not _adopt_adjusted(rec, trial):
                adjust(rec)
            if ranked_once:  # pending was empty; the rest of this ranking waits
                pending[:] = [(e.image_id, e.identity) for e in ranked]
            return found
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
