"""Camera check: each camera against the keypoints other cameras triangulate.

See :func:`check_cameras_inplace`. A wrong camera is worse than none: a camera that
contradicts the others is re-posed where its keypoints fit (as labelled, or with its
people's left and right exchanged) or left out, with the reason. And the people
check: a person only two images see is checked against the model the others hold
(:func:`check_few_view_people`).
"""

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
    loss_scale_px,
    mirrored_tracks,
    observed_in_posed_images,
    relabelled,
    subset,
    triangulate_tracks,
)
from .structs import BoolArray, FloatArray, IndexArray

if TYPE_CHECKING:
    from .keypoint_ba import KeypointBaOptions

logger = logging.getLogger(__name__)


def residuals_px(
    camera: pycolmap.Camera, cam_from_world: FloatArray, xy: FloatArray, X: FloatArray
) -> FloatArray:
    """Reprojection errors (N,) of points X (N, 3) against pixels xy (N, 2)."""
    Xc = X @ cam_from_world[:, :3].T + cam_from_world[:, 3]
    err = np.full(len(X), np.inf)
    front = Xc[:, 2] > 1e-6
    if front.any():
        proj = np.asarray(camera.img_from_cam(Xc[front]))
        err[front] = np.linalg.norm(proj - xy[front], axis=1)
    return err


def correspondences(
    rec: pycolmap.Reconstruction,
    tracks: KeypointTracks,
    image_id: int,
    witnesses: BoolArray,
    min_views: int,
) -> tuple[FloatArray, FloatArray, IndexArray, IndexArray]:
    """Image ``image_id``'s keypoints (K, 2), the points (K, 3) the ``witnesses``
    observations triangulate (tracks they see ``min_views``+ times; an exact two for
    a pair), the view counts (K,) and the tracks (K,)."""
    X, counts = triangulate_tracks(rec, subset(tracks, witnesses))
    pad = max(tracks.num_tracks - len(X), 0)
    X = np.r_[X, np.full((pad, 3), np.nan)]
    counts = np.r_[counts, np.zeros(pad, np.int64)]
    mine = tracks.image_id == image_id
    t = tracks.track[mine]
    ok = (counts[t] >= min_views) & np.isfinite(X[t]).all(axis=1)
    return tracks.xy_img[mine][ok], X[t[ok]], counts[t[ok]], t[ok]


def best_two_view_check(
    rec: pycolmap.Reconstruction,
    tracks: KeypointTracks,
    image_id: int,
    others: list[int],
    min_points: int,
) -> tuple[float, FloatArray, FloatArray]:
    """The smallest median error of image ``image_id``'s keypoints against the
    points any two other cameras triangulate, with those 2D-3D correspondences."""
    best = (np.inf, np.zeros((0, 2)), np.zeros((0, 3)))
    if not (tracks.image_id == image_id).any():
        return best
    image = rec.image(image_id)
    camera = rec.camera(image.camera_id)
    pose = image.cam_from_world().matrix()
    for a, j in enumerate(others):  # loop over image pairs (a few dozen at most)
        for k in others[a + 1 :]:
            pair = np.isin(tracks.image_id, [j, k])
            xy, pts, counts, _ = correspondences(rec, tracks, image_id, pair, 2)
            xy, pts = xy[counts == 2], pts[counts == 2]
            if len(xy) < min_points:
                continue
            med = float(np.median(residuals_px(camera, pose, xy, pts)))
            if med < best[0]:
                best = (med, xy, pts)
    return best


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
    est.ransac.random_seed = options.surface_seed
    found = pycolmap.estimate_and_refine_absolute_pose(xy, pts, camera, est)
    if found is None or found["num_inliers"] < options.min_check_points:
        return np.inf, None
    pose = found["cam_from_world"]
    return float(np.median(residuals_px(camera, pose.matrix(), xy, pts))), pose


def label_test(
    rec: pycolmap.Reconstruction,
    tracks: KeypointTracks,
    swapped: KeypointTracks,
    image_id: int,
    identity: int,
    options: KeypointBaOptions,
    max_error_px: float,
) -> tuple[float, float, int, pycolmap.Rigid3d | None]:
    """Person ``identity`` of image ``image_id`` as labelled against the same with
    left and right exchanged (``swapped``), each with the image at its best pose
    for all its keypoints, against the points all *other* cameras triangulate:
    (the person's median error as labelled, exchanged, its number of keypoints,
    the image's pose with the exchanged labels). As labelled: the better of the
    current pose and PnP."""
    assert tracks.keys is not None
    image = rec.image(image_id)
    camera = rec.camera(image.camera_id)
    errors: list[float] = []
    pose: pycolmap.Rigid3d | None = None
    count = 0
    for labels in (tracks, swapped):
        xy, pts, _, t = correspondences(
            rec, labels, image_id, labels.image_id != image_id, 2
        )
        theirs = tracks.keys[t, 0] == identity
        _, pose = robust_pnp(camera, xy, pts, options, max_error_px)
        poses = [] if pose is None else [pose.matrix()]
        if labels is tracks:
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
    return errors[0], errors[1], count, pose


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


def classic_support(
    rec: pycolmap.Reconstruction, num_classic: dict[int, int]
) -> dict[int, int]:
    """Per registered image: how many model points it observes through classic
    keypoints (the rows before the VCs)."""
    out = {}
    for image_id, image in rec.images.items():  # loop over images
        if not image.has_pose:
            continue
        idx = np.asarray(image.get_observation_point2D_idxs(), dtype=np.int64)
        out[image_id] = int((idx < num_classic.get(image_id, 0)).sum())
    return out


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
    for i in sorted(candidates, key=lambda i: rec.image(i).name):
        mine = tracks.track[tracks.image_id == i]
        for identity in np.unique(tracks.keys[mine[partner[mine] >= 0], 0]).tolist():
            if (i, identity) in skip:
                continue
            swapped = relabelled(tracks, i, partner, identity)
            as_labelled, exchanged, n, pose = label_test(
                rec, tracks, swapped, i, identity, options, limit_px
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
) -> None:
    """Re-pose image ``image_id`` at ``pose`` with its people's left and right
    exchanged: the keypoint points are rebuilt from ``swapped`` (``tracks`` with
    that image's keypoints on their counterparts' tracks) and the image's surface
    VCs, from the mesh turned front to back, leave the model."""
    rec.frame(rec.image(image_id).frame_id).rig_from_world = pose
    delete_points_observing(rec, keypoint_observations(tracks))
    surface = [
        k
        for k, p in enumerate(rec.image(image_id).points2D)  # loop over keypoints
        if k >= num_classic[image_id] and p.has_point3D()
    ]
    for k in surface:  # its surface VCs
        rec.delete_observation(image_id, k)
    add_keypoint_points(rec, swapped, options.min_track_length)


def person_errors(
    rec: pycolmap.Reconstruction, tracks: KeypointTracks
) -> dict[int, float]:
    """Each person's (identity's) median keypoint reprojection error, pixels,
    against the points all its views triangulate with the model's poses."""
    assert tracks.keys is not None
    X, counts = triangulate_tracks(rec, tracks)
    posed = observed_in_posed_images(rec, tracks)
    posed &= (counts[tracks.track] >= 2) & np.isfinite(X[tracks.track]).all(axis=1)
    err = np.full(len(tracks.track), np.nan)
    for image_id in np.unique(tracks.image_id[posed]):  # loop over images
        sel = posed & (tracks.image_id == image_id)
        image = rec.image(int(image_id))
        err[sel] = residuals_px(
            rec.camera(image.camera_id),
            image.cam_from_world().matrix(),
            tracks.xy_img[sel],
            X[tracks.track[sel]],
        )
    ident = tracks.keys[tracks.track, 0]
    return {
        int(k): float(np.median(err[posed & (ident == k)]))
        for k in np.unique(ident[posed])
    }


def people_views(tracks: KeypointTracks) -> dict[int, int]:
    """Each person's (identity's) number of distinct images."""
    assert tracks.keys is not None
    ident = tracks.keys[tracks.track, 0]
    pairs = np.unique(np.stack([ident, tracks.image_id], axis=1), axis=0)
    people, views = np.unique(pairs[:, 0], return_counts=True)
    return dict(zip(people.tolist(), views.tolist(), strict=True))


def unchecked_people(tracks: KeypointTracks, min_views: int = 3) -> list[int]:
    """The people seen by fewer than ``min_views`` images."""
    return [k for k, n in people_views(tracks).items() if n < min_views]


def check_few_view_people(
    rec: pycolmap.Reconstruction,
    tracks: KeypointTracks,
    few: list[int],
    max_ratio: float,
    floor_px: float,
) -> tuple[KeypointTracks, dict[int, float]]:
    """``tracks`` without those of the people ``few`` (seen by two images, left
    out of ``rec``'s adjustment) whose keypoints miss the model the other people
    hold, and their median errors: above ``max_ratio`` times the median of the
    others' errors and above ``floor_px``.

    Two images can always be bent until the rays of a person linked across them
    meet, so such a person is checked against poses it did not shape: a false
    detection linked across two images (the synthetic scenes' random bodies)
    misses, a static object detected as a person (pose2sim's skeleton model,
    1.5-5 px) fits and stays."""
    errs = person_errors(rec, tracks)
    logger.debug("person check: %s", {k: round(e, 1) for k, e in errs.items()})
    held = [e for k, e in errs.items() if k not in few]
    if not held:
        return tracks, {}
    limit = max(max_ratio * float(np.median(held)), floor_px)
    missed = {k: errs.get(k, np.inf) for k in few if not errs.get(k, np.inf) <= limit}
    assert tracks.keys is not None
    keep = ~np.isin(tracks.keys[tracks.track, 0], list(missed))
    return subset(tracks, keep), missed


def keypoint_cost(
    rec: pycolmap.Reconstruction, tracks: KeypointTracks, scale_px: float
) -> float:
    """Cauchy cost (scale ``scale_px``) of every keypoint observation in a posed
    image against the point all its views triangulate: one number to compare two
    labellings of the same observations."""
    X, counts = triangulate_tracks(rec, tracks)
    posed = observed_in_posed_images(rec, tracks)
    posed &= (counts[tracks.track] >= 2) & np.isfinite(X[tracks.track]).all(axis=1)
    cost = 0.0
    for image_id in np.unique(tracks.image_id[posed]):  # loop over images
        sel = posed & (tracks.image_id == image_id)
        image = rec.image(int(image_id))
        r = residuals_px(
            rec.camera(image.camera_id),
            image.cam_from_world().matrix(),
            tracks.xy_img[sel],
            X[tracks.track[sel]],
        )
        r = np.minimum(r, 1e6)  # behind the camera: the loss saturates anyway
        cost += float(np.sum(scale_px**2 * np.log1p((r / scale_px) ** 2)))
    return cost


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
) -> tuple[KeypointTracks, int, float, float] | None:
    """Exchange left and right of the person :func:`best_exchange` finds, when
    the adjusted model then fits all keypoints better (:func:`keypoint_cost`):
    (the new tracks, the image re-posed, median error as labelled, exchanged).
    An exchange the adjustment does not confirm is undone and the next person is
    tried; None when no exchange is confirmed."""
    tried: set[tuple[int, int]] = set()
    before = keypoint_cost(rec, tracks, scale_px)
    while True:
        found = best_exchange(
            rec, tracks, partner, candidates, options, limit_px, tried
        )
        if found is None:
            return None
        image_id, identity, swapped, pose, as_labelled, exchanged = found
        trial = pycolmap.Reconstruction(rec)
        exchange_labels_inplace(
            trial, tracks, swapped, image_id, pose, num_classic, options
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
                rec, tracks, swapped, image_id, pose, num_classic, options
            )
            adjust(rec)
            return swapped, image_id, as_labelled, exchanged
        tried.add((image_id, identity))


def check_cameras_inplace(
    rec: pycolmap.Reconstruction,
    tracks: KeypointTracks,
    options: KeypointBaOptions,
    adjust: Callable[[pycolmap.Reconstruction], object],
    *,
    mirror: dict[int, int] | None = None,
    num_classic: dict[int, int] | None = None,
) -> tuple[list[str], dict[str, str], list[str]]:
    """Each camera against keypoint points *other* cameras triangulate.

    A camera whose keypoints miss the points of every pair of other cameras (the
    best pair's median error above ``max_check_ratio`` times the median camera's)
    contradicts the rest: a prior turned front to back puts its camera on the
    mirror side, consistently in every pair and cycle, and only the people's
    asymmetric 3D pose shows it. It is re-posed by PnP on the best pair's points
    when that fits as well as the other cameras do. Else, with ``mirror``, its
    people's keypoints are tried with left and right exchanged: a pose estimator
    that sees a person from the back but takes them for facing the camera labels
    every left landmark right (pose2sim_single cam02 at t050 and t070). When that
    fits, the camera is re-posed, its keypoints join their counterparts' tracks and
    its surface VCs (from the mesh turned front to back) leave the model. Else the
    camera is left out. When no camera misses by that much, a camera one of whose
    people fits the points all other cameras triangulate significantly better
    with left and right exchanged (:func:`labels_exchanged`) is re-posed with them
    when the adjusted model then fits all keypoints better (:func:`try_exchange`):
    a nearly symmetric pose lets a turned prior fit within the ratio. A camera
    that classic keypoints place (``min_classic_support`` model points) is a
    witness, never judged: there the
    people are what is wrong. Needs 4+ cameras (with 3, two cameras always agree
    with each other). Cameras are visited in name order, worst first; ``adjust``
    bundle-adjusts the model after each change. Returns (re-posed names, left out:
    reason, re-posed with left/right exchanged).
    """
    relocalised: list[str] = []
    left_out: dict[str, str] = {}
    mirrored: list[str] = []
    scale_px = loss_scale_px(rec, options.loss_scale_px, options.loss_scale_frac)
    partner = mirrored_tracks(tracks, mirror or {})
    while True:
        reg = sorted(
            (i for i, im in rec.images.items() if im.has_pose),
            key=lambda i: rec.image(i).name,  # name order, never the ids
        )
        if len(reg) < 4:
            break
        # The 6 cameras sharing most keypoints are enough witnesses.
        obs = {i: set(tracks.track[tracks.image_id == i].tolist()) for i in reg}
        witnesses, checks = {}, {}
        for i in reg:
            witnesses[i] = sorted(
                (j for j in reg if j != i),
                key=lambda j: (-len(obs[i] & obs[j]), rec.image(j).name),
            )[:6]
            checks[i] = best_two_view_check(
                rec, tracks, i, witnesses[i], options.min_check_points
            )
        errs = {i: c[0] for i, c in checks.items() if np.isfinite(c[0])}
        if len(errs) < 4:
            break
        pinned = {
            i
            for i, n in classic_support(rec, num_classic or {}).items()
            if n >= options.min_classic_support
        }
        judged = [i for i in errs if i not in pinned]
        if not judged:
            break
        logger.debug(
            "camera check: %s",
            {rec.image(i).name: round(e, 1) for i, e in errs.items()},
        )
        worst = max(judged, key=lambda i: (errs[i], rec.image(i).name))
        typical = float(np.median([e for i, e in errs.items() if i != worst]))
        limit = max(options.max_check_ratio * typical, scale_px)
        if errs[worst] <= limit:
            # No camera misses by far; one whose people fit clearly better with
            # left and right exchanged still sits on the mirror side.
            if mirror is None or num_classic is None:
                break
            found = try_exchange(
                rec,
                tracks,
                partner,
                [i for i in judged if rec.image(i).name not in mirrored],
                options,
                limit,
                scale_px,
                num_classic,
                adjust,
            )
            if found is None:
                break
            tracks, image_id, as_labelled, exchanged = found
            partner = mirrored_tracks(tracks, mirror)
            name = rec.image(image_id).name
            logger.warning(
                "camera check: %s re-posed with its people's left and right "
                "exchanged: they fit the points the other cameras triangulate "
                "with a median error of %.1f px, against %.1f px as labelled, "
                "and the adjusted model fits all keypoints better (the pose "
                "estimator saw them from the back as if from the front); its "
                "surface VCs are not used",
                name,
                exchanged,
                as_labelled,
            )
            relocalised.append(name)
            mirrored.append(name)
            continue
        image = rec.image(worst)
        name = image.name
        if name in relocalised or name in left_out:
            break
        camera = rec.camera(image.camera_id)
        pnp, pose = robust_pnp(
            camera, checks[worst][1], checks[worst][2], options, limit
        )
        if pnp <= limit:
            rec.frame(image.frame_id).rig_from_world = pose
            logger.warning(
                "camera check: %s re-posed by PnP on the keypoints two other cameras "
                "triangulate (median error %.0f px -> %.0f px; the median camera's "
                "%.0f px)",
                name,
                errs[worst],
                pnp,
                typical,
            )
            relocalised.append(name)
            adjust(rec)
            continue
        swapped = relabelled(tracks, worst, partner)
        check = best_two_view_check(
            rec, swapped, worst, witnesses[worst], options.min_check_points
        )
        swapped_pnp, swapped_pose = robust_pnp(
            camera, check[1], check[2], options, limit
        )
        logger.debug(
            "camera check: %s with left and right exchanged: %.0f px against the "
            "best pair, PnP on %d points %.0f px (limit %.0f px)",
            name,
            check[0],
            len(check[1]),
            swapped_pnp,
            limit,
        )
        if swapped_pnp <= limit and num_classic is not None and swapped_pose:
            exchange_labels_inplace(
                rec, tracks, swapped, worst, swapped_pose, num_classic, options
            )
            tracks = swapped
            partner = mirrored_tracks(tracks, mirror or {})
            logger.warning(
                "camera check: %s re-posed with its people's left and right "
                "exchanged (the pose estimator saw them from the back as if from "
                "the front): median error %.0f px -> %.0f px, the median camera's "
                "%.0f px; its surface VCs are not used",
                name,
                errs[worst],
                swapped_pnp,
                typical,
            )
            relocalised.append(name)
            mirrored.append(name)
        else:
            left_out[name] = (
                f"left out: its keypoints miss the points the other cameras "
                f"triangulate (median {errs[worst]:.0f} px, the median camera "
                f"{typical:.0f} px) and no pose fits them, also with left and "
                "right exchanged"
            )
            logger.warning("camera check: %s %s", name, left_out[name])
            rec.deregister_frame(image.frame_id)
        adjust(rec)
    return relocalised, left_out, mirrored
