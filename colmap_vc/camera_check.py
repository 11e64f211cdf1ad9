"""Camera check: each camera against the keypoints other cameras triangulate.

See :func:`check_cameras_inplace`. A wrong camera is worse than none: a camera that
contradicts the others is re-posed where its keypoints fit (as labelled, or with its
people's left and right exchanged, :mod:`colmap_vc.label_check`) or left out, with
the reason.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import pycolmap

from .keypoint_tracks import (
    KeypointTracks,
    add_keypoint_points,
    correspondences,
    delete_points_observing,
    keypoint_observations,
    loss_scale_px,
    mirrored_tracks,
    relabelled,
    residuals_px,
    subset,
)
from .label_check import exchange_labels_inplace, robust_pnp, try_exchange
from .structs import FloatArray, IndexArray

if TYPE_CHECKING:
    from .keypoint_ba import KeypointBaOptions

logger = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True, slots=True)
class CameraCheck:
    """What the camera check did to a model."""

    relocalised: list[str]  # images re-posed (by PnP, or with left/right exchanged)
    left_out: dict[str, str]  # image name -> why it was deregistered
    mirrored: list[str]  # images re-posed with (some of) their people exchanged
    tracks: KeypointTracks
    """The keypoint tracks as the model now holds them: exchanged people's labels
    exchanged, people who left an image's tracks removed."""
    exchanged: frozenset[tuple[int, int]] = frozenset()
    """(image id, person identity) of the people exchanged; identity -1: every
    person of the image. Their surface VCs come from a mesh turned front to back."""


def best_two_view_check(
    rec: pycolmap.Reconstruction,
    tracks: KeypointTracks,
    image_id: int,
    others: list[int],
    min_points: int,
) -> tuple[float, FloatArray, FloatArray]:
    """The smallest median error of image ``image_id``'s keypoints against the
    points any two other cameras triangulate, with those 2D-3D correspondences.

    The error is infinite when most of the points lie behind the camera (a camera
    posed on the mirror side of its people); the correspondences are then those of
    the pair with the most points, so that the camera can still be judged and
    re-posed. Without any pair of ``min_points`` correspondences: (inf, empty)."""
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
            if med < best[0] or (np.isinf(best[0]) and len(xy) > len(best[1])):
                best = (med, xy, pts)
    return best


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


def classic_placed(
    rec: pycolmap.Reconstruction, num_classic: dict[int, int], min_support: int
) -> frozenset[int]:
    """The registered images classic keypoints place: at least ``min_support``
    model points observed through them (:func:`classic_support`)."""
    return frozenset(
        i for i, n in classic_support(rec, num_classic).items() if n >= min_support
    )


def _without_poor_witness(
    rec: pycolmap.Reconstruction,
    tracks: KeypointTracks,
    image_id: int,
    identity: int,
    options: KeypointBaOptions,
) -> KeypointTracks:
    """``tracks`` without person ``identity``'s keypoints in image ``image_id``
    (just exchanged) when the image's other people hold at least as many
    keypoints; the model's keypoint points are rebuilt from them.

    The exchange put the camera on the right side. The exchanged landmarks stay
    poor witnesses: a pose estimator that took the person's back for the front
    also places them worse (front and back differ in more than left and right).
    Kept, they cost the pose2sim videos' static cameras 0.2-0.3 deg against the
    calibration; left out, the cameras end within 0.05 deg of no exchange at all
    (docs/real-data.md, "People seen from the back"). With fewer other
    keypoints the camera's pose rests on that person, who then stays.
    """
    assert tracks.keys is not None
    mine = tracks.image_id == image_id
    theirs = mine & (tracks.keys[tracks.track, 0] == identity)
    if (mine & ~theirs).sum() < max(theirs.sum(), options.min_check_points):
        return tracks
    logger.info(
        "camera check: %s person %d's %d exchanged keypoints leave the tracks "
        "(the image's other people hold %d)",
        rec.image(image_id).name,
        identity,
        int(theirs.sum()),
        int((mine & ~theirs).sum()),
    )
    delete_points_observing(rec, keypoint_observations(tracks))
    tracks = subset(tracks, ~theirs)
    add_keypoint_points(rec, tracks, options.min_track_length)
    return tracks


def check_cameras_inplace(
    rec: pycolmap.Reconstruction,
    tracks: KeypointTracks,
    options: KeypointBaOptions,
    adjust: Callable[[pycolmap.Reconstruction], object],
    *,
    mirror: dict[int, int] | None = None,
    num_classic: dict[int, int] | None = None,
    vc_identity: dict[int, IndexArray] | None = None,
) -> CameraCheck:
    """Each camera against keypoint points *other* cameras triangulate.

    A camera whose keypoints miss the points of every pair of other cameras (the
    best pair's median error above ``max_check_ratio`` times the median camera's)
    contradicts the rest: a prior turned front to back puts its camera on the mirror
    side, consistently in every pair and cycle, and only the people's asymmetric 3D
    pose shows it. Two explanations are fitted by PnP on the best pair's points: its
    pose is wrong (the keypoints as labelled), or, with ``mirror``, its people are
    labelled left for right, as a pose estimator does that sees a person from the
    back but takes them for facing the camera (pose2sim_single cam02 at t050 and
    t070). The better fit within the limit is kept; with the exchange, the camera's
    keypoints join their counterparts' tracks and its surface VCs (from the mesh
    turned front to back) leave the model. A camera that fits neither way is left
    out. When no camera misses by that much, a camera one of whose people fits the
    points all other cameras triangulate significantly better with left and right
    exchanged (:func:`labels_exchanged`) is re-posed with them when the adjusted
    model then fits all keypoints better (:func:`try_exchange`): a nearly symmetric
    pose lets a turned prior fit within the ratio. A camera that classic keypoints
    place (``min_classic_support`` model points) is a witness, never judged: there
    the people are what is wrong. Needs 4+ cameras (with 3, two cameras always agree
    with each other). Cameras are visited in name order, worst first; ``adjust``
    bundle-adjusts the model after each change; ``vc_identity`` (per image, the
    person identity of each VC) keeps the surface VCs of an image's other people
    when one person is exchanged.
    """
    relocalised: list[str] = []
    left_out: dict[str, str] = {}
    mirrored: list[str] = []
    whole: set[str] = set()  # images with every person exchanged at once
    exchanged_people: set[tuple[int, int]] = set()  # (image id, identity)
    pending: list[tuple[int, int]] = []  # ranked for an exchange, not yet tried
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
        # A camera with points behind it (inf) is judged; one without any is not.
        errs = {i: c[0] for i, c in checks.items() if len(c[1])}
        if len(errs) < 4:
            break
        pinned = classic_placed(rec, num_classic or {}, options.min_classic_support)
        judged = [i for i in errs if i not in pinned]
        if not judged:
            break
        logger.debug(
            "camera check: %s",
            {rec.image(i).name: round(e, 1) for i, e in errs.items()},
        )
        worst = max(judged, key=lambda i: (errs[i], rec.image(i).name))
        typical = float(np.median([e for i, e in errs.items() if i != worst]))
        if not np.isfinite(typical):
            break  # most cameras have the points behind them: nobody to trust
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
                [i for i in judged if rec.image(i).name not in whole],
                options,
                limit,
                scale_px,
                num_classic,
                adjust,
                vc_identity,
                exchanged_people,
                pending,
            )
            if found is None:
                break
            tracks, image_id, identity = found.swapped, found.image_id, found.identity
            exchanged_people.add((image_id, identity))
            kept = _without_poor_witness(rec, tracks, image_id, identity, options)
            if kept is not tracks:
                tracks = kept
                adjust(rec)
            partner = mirrored_tracks(tracks, mirror)
            name = rec.image(image_id).name
            logger.warning(
                "camera check: %s re-posed with its people's left and right "
                "exchanged: they fit the points the other cameras triangulate "
                "with a median error of %.1f px, against %.1f px as labelled, "
                "and the adjusted model fits all keypoints better (the pose "
                "estimator saw them from the back as if from the front); that "
                "person's surface VCs are not used",
                name,
                found.exchanged,
                found.as_labelled,
            )
            for names in (relocalised, mirrored):
                if name not in names:
                    names.append(name)
            continue
        image = rec.image(worst)
        name = image.name
        if name in relocalised or name in left_out:
            break
        camera = rec.camera(image.camera_id)
        pnp, pose = robust_pnp(
            camera, checks[worst][1], checks[worst][2], options, limit
        )
        # Two explanations of a camera that misses by far: its pose is wrong, or
        # its people are labelled as if seen from the front (left for right).
        # Both are fitted; the better fit is kept.
        swapped = relabelled(tracks, worst, partner)
        check = best_two_view_check(
            rec, swapped, worst, witnesses[worst], options.min_check_points
        )
        swapped_pnp, swapped_pose = (
            robust_pnp(camera, check[1], check[2], options, limit)
            if partner.size and (partner >= 0).any()
            else (np.inf, None)
        )
        logger.debug(
            "camera check: %s misses by %.0f px (limit %.0f px): PnP as labelled "
            "%.0f px, with left and right exchanged %.0f px against the best pair "
            "(%.0f px, %d points)",
            name,
            errs[worst],
            limit,
            pnp,
            swapped_pnp,
            check[0],
            len(check[1]),
        )
        can_swap = num_classic is not None and swapped_pose is not None
        if pnp <= limit and (pnp <= swapped_pnp or not can_swap):
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
        if (
            swapped_pnp <= limit
            and num_classic is not None
            and swapped_pose is not None
        ):
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
            whole.add(name)
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
    whole_ids = {i for i, im in rec.images.items() if im.name in whole}
    return CameraCheck(
        relocalised=relocalised,
        left_out=left_out,
        mirrored=mirrored,
        tracks=tracks,
        exchanged=frozenset(exchanged_people | {(i, -1) for i in whole_ids}),
    )
