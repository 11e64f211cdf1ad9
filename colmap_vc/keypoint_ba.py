"""Keypoint bundle adjustment: the people's keypoints as multi-view tracks by identity.

A keypoint VC (a landmark such as a knee or a heel) names the same 3D point in every
view of the same person, so its multi-view track is known a priori: (person, keypoint).
COLMAP's mapper instead builds tracks from the two-view inliers of verification, which
on real photos drops the keypoints that disagree with the (biased) surface VCs and
keeps a selection skewed by them. This pass rebuilds the model's keypoint points from
identities (people linked across images by ``augment``'s person associations),
triangulates them with the model's poses and runs COLMAP's bundle adjustment with a
Cauchy loss scaled to the keypoints' pixel error, keeping classic (SIFT) points and
the mapper's surface-VC points, each image's weighted to a fixed total
(``surface_per_image`` observations, two images as many: dense maps rendered
from a mesh fitted to the same landmarks add correlated errors, docs/real-data.md).

On pose2sim (docs/results.md) the pass converges to the same poses from the mapper's
model, from the keypoint-only model and from the ground truth.

With static cameras, a keypoint whose error repeats the same landmark of another
instant's person (someone who stood still) is weighted down by how much it repeats
(:mod:`colmap_vc.gba.repeats`): such a person's instants count about once.

With ``surface_tracks`` (``map --gba``) the pass is the generalized bundle
adjustment instead: after the camera check every surface VC joins its track by
identity, weighted by its measured spread and correlation with its neighbours
(:func:`add_weighted_surface`, docs/gba.md).
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import pycolmap

from .camera_check import check_cameras_inplace
from .gba.ceres import PeopleNoise, bundle_adjust_inplace, log_rounded
from .gba.correlated import correlated_noise
from .gba.repeats import keypoint_sigma_px, repeat_design, repeat_noise
from .keypoint_tracks import (
    KeypointTracks,
    add_keypoint_points,
    delete_points_observing,
    keypoint_observations,
    keypoint_tracks,
    loss_scale_px,
    subset,
    surface_tracks,
    triangulate_tracks,
    vc_identities,
)
from .people_check import check_few_view_people, unchecked_people
from .vc_records import VcRecords

logger = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True, slots=True)
class KeypointBaOptions:
    """Options of the keypoint bundle adjustment."""

    loss_scale_px: float | None = None
    """Scale of the Cauchy loss, pixels; also the smallest error the camera check
    calls a contradiction. Default: ``loss_scale_frac`` of the images' larger side."""
    loss_scale_frac: float = 16.0 / 1920.0
    """The keypoints' pixel error as a fraction of the image's larger side, when
    ``loss_scale_px`` is not given: MediaPipe's landmarks are 10-15 px off (median) on
    pose2sim's 1920-px frames, 16 px; a landmark's error follows the person's size in
    pixels, so the same people in a 640-px image are about 5 px off (the synthetic
    realistic priors: 3-4 px median; a fixed 16 px let a camera turned 180 deg pass
    the camera check there at 15.8 px, against 3.8 px for the median camera)."""
    surface_per_image: float = 6.0
    """What the model's surface-VC points weigh per registered image, in keypoint
    observations: every VC-only point stays, and each of an image's N observations
    is weighted by ``surface_per_image`` / N (when N is larger) under the keypoints'
    loss (0: the points leave; negative: all at full weight). A fixed weight, not
    one that grows with the samples or the keypoints: the surface VCs of a mesh
    fitted to the same landmarks have errors correlated within each person and
    image, so they act as a prior of fixed strength on the poses, which more
    instants of keypoints should outweigh (five instants: docs/results.md). It
    replaced a random subset of that many observations, whose draw moved
    pose2sim_single t090 between 55 and 69 AUC@15 (docs/gba.md, "The default's
    surface budget"). The value: the errors a person's keypoints and surface
    share in an image, with their correlation, give one weight for pose2sim and
    the synthetic domes at 7.2 (5.2-9.1); at 6 no row's variance is more than
    8.2 % above its own best (``bench/surface_offsets.py``). Two images weigh
    the same: 6 to 48 read alike on every two-image row (docs/gba.md, "Not
    done"); two images a check leaves of a larger model are mapped again on
    their own first (:mod:`colmap_vc.mapping.pipeline`)."""
    surface_tracks: bool = False
    """The generalized BA (``map --gba``): after the camera check, the budget's
    surface points give way to every surface VC in its track by identity (person,
    template sample: one X1 shared by all views), each observation weighted by
    its spread and its correlation with its neighbours in the image, relative to
    the keypoints (:mod:`colmap_vc.gba.correlated`), instead of the fixed weight
    ``surface_per_image`` under the keypoints' loss. Off by default: against
    that weight it is level on the synthetic domes and behind on pose2sim
    (docs/gba.md, "Measured")."""
    min_sigma_px: float = 0.5
    """Smallest noise a cluster is given, pixels: a spread estimated below half a
    pixel (clean synthetic priors) is rendering, not detection, precision."""
    robust_sigmas: float = 2.0
    """With ``surface_tracks``: scale of each people observation's Cauchy loss, in
    its cluster's spread sigma (not the inflated noise: one wrong sample of a
    cluster is an outlier at a few sigma whatever the cluster's shared error)."""
    weigh_repeats: bool = True
    """Static cameras: weigh each keypoint observation by how much its error
    repeats another instant's, the same landmark of someone who stood still
    there (:mod:`colmap_vc.gba.repeats`): such a person's instants count about
    once, not once per instant. Off: every instant counts as independent."""
    min_track_length: int = 2
    """Keypoint tracks seen by fewer registered images are left out."""
    check_seed: int = 0
    """Seed of the camera check's PnP RANSAC."""
    check_cameras: bool = True
    """Check every camera against keypoint points that other cameras triangulate
    (module doc of :func:`check_cameras_inplace`): re-pose it by PnP where it
    disagrees, leave it out where nothing fits. A wrong camera is worse than none."""
    max_check_ratio: float = 2.5
    """A camera disagrees when its keypoints miss the others' points by more than
    this times the median camera's error (and the loss scale). Correct cameras stay
    within 2x the median camera on pose2sim (10-28 px at 1920 px, MediaPipe's
    landmark noise is 10-15 px); a camera on the mirror side of a person whose prior
    is turned front to back misses by about 3x (37-52 px)."""
    label_test_z: float = 2.0
    """A camera within that ratio, one of whose people fits the other cameras'
    points better with left and right exchanged, is re-posed so when the gain is
    this many standard errors of the log-ratio of the two median errors (1.02 /
    sqrt(n) for the person's n keypoints: the sampling error of a median of
    Rayleigh residuals; z = 2 is one-sided 2.3%). A prior turned front to back
    can sit within 2x of the median camera when the person's pose is nearly
    symmetric (1-person synthetic dome s0: 2.1x); its exchanged labels then fit
    at 0.4-0.6 of the labelled error, correct cameras' at 1.2-10x
    (docs/real-data.md, "People seen from the back")."""
    min_check_points: int = 10
    """Keypoint points a check needs (about half a person)."""
    min_classic_support: int = 30
    """A camera that observes this many model points through classic (SIFT)
    keypoints is placed by them, whatever its people say: the camera check does
    not move it or leave it out, and `map`'s mesh check does not judge it (its
    prior may be the wrong one: turned front to back). 30 is what COLMAP's mapper
    asks to register an image (abs_pose_min_num_inliers); spurious SIFT inliers
    on extreme pairs number 15-25 (docs/results.md)."""


@dataclass(frozen=True, kw_only=True, slots=True)
class KeypointBaSummary:
    """What the keypoint bundle adjustment did."""

    num_tracks: int
    num_keypoint_observations: int
    num_surface_observations: int  # kept
    num_surface_observations_dropped: int
    elapsed_s: float
    relocalised: tuple[str, ...] = ()  # images re-posed by the camera check
    left_out: dict[str, str] | None = None  # image name -> why it was deregistered
    mirrored: tuple[str, ...] = ()  # re-posed with their people's left/right swapped
    people: PeopleNoise | None = None
    """The noise of each surface observation (the budget's weights, or the
    surface tracks'; None without surface weights): what a later bundle
    adjustment of the model weighs them by."""
    tracks: KeypointTracks | None = None
    """The keypoint tracks as the model holds them after the camera check (people
    exchanged or left out there); None without keypoint VCs."""
    repeats: RepeatSummary | None = None
    """How the keypoints of people who stood still were weighed (static cameras)."""


@dataclass(frozen=True, kw_only=True, slots=True)
class RepeatSummary:
    """Keypoints repeated over static cameras' instants (:mod:`.gba.repeats`)."""

    sigma_px: float  # the keypoints' error per coordinate the repeats are read at
    num_observations: int  # keypoint observations of the instants' people
    effective: float  # what they count as: the sum of 1 / m


def surface_budget_noise(
    rec: pycolmap.Reconstruction,
    observations: np.ndarray,
    per_image: float,
    loss_scale_px: float,
) -> PeopleNoise:
    """The surface-VC ``observations`` ((image id, point2D index) rows) weighted so
    that each image's weigh ``per_image`` keypoint observations together: an image
    with N of them gives each the noise sqrt(N / ``per_image``) in keypoint units
    (1 when N is smaller), under the keypoints' Cauchy loss at ``loss_scale_px``.

    The same prior strength as a random subset of ``per_image`` observations per
    image, without the draw: every sample speaks, none decides alone."""
    out = PeopleNoise.none(rec)
    sigma, robust = out.sigma_px, out.robust_px
    if not len(observations):
        return out
    images, index, count = np.unique(
        observations[:, 0], return_inverse=True, return_counts=True
    )
    noise = np.sqrt(np.maximum(count / per_image, 1.0))
    for k, image_id in enumerate(images.tolist()):  # loop over images
        rows = observations[index == k, 1]
        sigma[image_id][rows] = noise[k]
        robust[image_id][rows] = loss_scale_px
    return out


def with_loss_scale(
    options: KeypointBaOptions, rec: pycolmap.Reconstruction
) -> KeypointBaOptions:
    """``options`` with ``loss_scale_px`` set: given, else ``loss_scale_frac`` of the
    median larger image side of the model's cameras."""
    scale = loss_scale_px(rec, options.loss_scale_px, options.loss_scale_frac)
    return dataclasses.replace(options, loss_scale_px=scale)


def keypoint_bundle_adjustment(
    records: VcRecords,
    rec: pycolmap.Reconstruction,
    options: KeypointBaOptions | None = None,
    *,
    mirror: dict[int, int] | None = None,
    instant_of: Mapping[int, str] | None = None,
) -> tuple[pycolmap.Reconstruction, KeypointBaSummary]:
    """A copy of ``rec`` with keypoint tracks by identity, bundle-adjusted (module doc).

    ``rec`` is not modified. Without keypoint VCs in ``records`` (what `augment`
    wrote, :func:`~colmap_vc.vc_records.read_vc_records`) it returns a plain copy.
    ``mirror`` (template track id -> its left/right counterpart's) lets the camera
    check try an image's people with left and right exchanged. ``instant_of``
    (static cameras: identity -> instant) lets ``weigh_repeats`` find the
    people who stood still.
    """
    options = with_loss_scale(options or KeypointBaOptions(), rec)
    loss = options.loss_scale_px
    assert loss is not None
    t0 = time.perf_counter()
    out = pycolmap.Reconstruction(rec)
    registered = np.array(
        [i for i, im in out.images.items() if im.has_pose], dtype=np.int64
    )
    tracks = keypoint_tracks(records, registered)
    if tracks.num_tracks == 0:
        logger.info("keypoint BA: no keypoint VCs in the database: model unchanged")
        return out, KeypointBaSummary(
            num_tracks=0,
            num_keypoint_observations=0,
            num_surface_observations=0,
            num_surface_observations_dropped=0,
            elapsed_s=time.perf_counter() - t0,
        )
    num_classic = records.num_classic
    # The model's points: classic ones stay; VC-only ones are surface points (the
    # keypoint ones are rebuilt below), weighted to the budget.
    keypoint_obs = keypoint_observations(tracks)
    delete_points_observing(out, keypoint_obs)  # rebuilt below, by identity
    vc_only, vc_obs = [], []
    for point_id, point in out.points3D.items():  # loop over the model's points
        els = [(e.image_id, e.point2D_idx) for e in point.track.elements]
        if any(idx < num_classic[i] for i, idx in els):
            continue
        vc_only.append(point_id)
        vc_obs.extend(els)
    per_image = options.surface_per_image
    dropped = 0
    if per_image == 0:
        for point_id in vc_only:
            out.delete_point3D(point_id)
        dropped, vc_obs = len(vc_obs), []
    weights = (
        surface_budget_noise(out, np.array(vc_obs).reshape(-1, 2), per_image, loss)
        if per_image > 0
        else None
    )
    good, counts = add_keypoint_points(out, tracks, options.min_track_length)
    bundle_adjust_inplace(out, loss, weights)
    repeats, repeat_summary = None, None
    if instant_of and options.weigh_repeats:
        repeats, repeat_summary = _repeats(out, tracks, instant_of, options)
        if repeats is not None:
            weights = repeats if weights is None else weights.or_else(repeats)
            bundle_adjust_inplace(out, loss, weights)
    few = unchecked_people(tracks) if len(registered) >= 3 else []
    if few and options.check_cameras:
        tracks, missed = check_few_view_people(
            out, tracks, few, options.max_check_ratio, loss
        )
        if missed:
            logger.warning(
                "person check: %d person(s) seen by two images left out of the "
                "keypoint tracks: their keypoints miss the model the others hold "
                "(median %s px)",
                len(missed),
                ", ".join(f"{e:.0f}" for e in missed.values()),
            )
            delete_points_observing(out, keypoint_obs)
            good, counts = add_keypoint_points(out, tracks, options.min_track_length)
            bundle_adjust_inplace(out, loss, weights)
    num_kp_obs = int(counts[good].sum())
    num_surface = len(vc_obs)
    relocalised: list[str] = []
    left_out: dict[str, str] = {}
    mirrored: list[str] = []
    exchanged: frozenset[tuple[int, int]] = frozenset()
    if options.check_cameras:
        check = check_cameras_inplace(
            out,
            tracks,
            options,
            lambda rec: bundle_adjust_inplace(rec, loss, weights),
            mirror=mirror,
            num_classic=num_classic,
            vc_identity=vc_identities(records),
        )
        relocalised, left_out, mirrored = (
            check.relocalised,
            check.left_out,
            check.mirrored,
        )
        tracks, exchanged = check.tracks, check.exchanged
    noise = weights
    if options.surface_tracks:
        # After the camera check: a prior turned front to back would pull its
        # camera with hundreds of surface samples before the check could
        # exchange its people's left and right.
        for point_id in vc_only:  # the budget's points: replaced by the tracks
            if out.exists_point3D(point_id):
                out.delete_point3D(point_id)
        noise, num_surface = add_weighted_surface(
            records,
            out,
            tracks,
            options,
            exchanged,
            instant_of if options.weigh_repeats else None,
        )
        if repeats is not None:
            noise = noise.or_else(repeats)
        bundle_adjust_inplace(out, loss, noise)
    summary = KeypointBaSummary(
        num_tracks=int(good.sum()),
        num_keypoint_observations=num_kp_obs,
        num_surface_observations=num_surface,
        num_surface_observations_dropped=dropped,
        elapsed_s=time.perf_counter() - t0,
        people=noise,
        relocalised=tuple(relocalised),
        left_out=left_out,
        mirrored=tuple(mirrored),
        tracks=tracks,
        repeats=repeat_summary,
    )
    logger.info(
        "keypoint BA: %d keypoint tracks (%d observations), %d surface-VC "
        "observations%s, %d dropped (%.1f s)",
        summary.num_tracks,
        summary.num_keypoint_observations,
        summary.num_surface_observations,
        (
            ""
            if options.surface_tracks or weights is None
            else f" weighing {per_image:g} per image"
        ),
        summary.num_surface_observations_dropped,
        summary.elapsed_s,
    )
    return out, summary


def _repeats(
    rec: pycolmap.Reconstruction,
    tracks: KeypointTracks,
    instant_of: Mapping[int, str],
    options: KeypointBaOptions,
) -> tuple[PeopleNoise | None, RepeatSummary | None]:
    """The repeated keypoints' noise (None: nothing repeats) and its summary."""
    assert options.loss_scale_px is not None and tracks.keys is not None
    ok = np.isin(tracks.keys[tracks.track, 0], list(instant_of))
    if not ok.any():
        return None, None
    sigma = keypoint_sigma_px(options.loss_scale_px)
    noise, design = repeat_noise(rec, tracks, instant_of, sigma, options.loss_scale_px)
    summary = RepeatSummary(
        sigma_px=sigma,
        num_observations=int(ok.sum()),
        effective=float(np.sum(1.0 / design[ok])),
    )
    logger.info(
        "keypoint BA: the static cameras' %d keypoint observations count as %.0f "
        "(errors repeated by people who stood still; keypoint error %.1f px per "
        "coordinate)",
        summary.num_observations,
        summary.effective,
        sigma,
    )
    if not any(np.isfinite(v).any() for v in noise.sigma_px.values()):
        return None, summary
    return noise, summary


def add_weighted_surface(
    records: VcRecords,
    rec: pycolmap.Reconstruction,
    tracks: KeypointTracks,
    options: KeypointBaOptions,
    exchanged: frozenset[tuple[int, int]] = frozenset(),
    instant_of: Mapping[int, str] | None = None,
) -> tuple[PeopleNoise, int]:
    """Add the surface tracks by identity of ``rec``'s posed images (its poses
    adjusted by the keypoints ``tracks``) and weigh each surface observation
    relative to the keypoints by its spread and correlation with its neighbours
    (:mod:`colmap_vc.gba.correlated`) -> (the people's noise, surface
    observations added). The keypoints keep COLMAP's loss and unit weight.
    People in ``exchanged`` ((image, identity); -1: the whole image) add none:
    their mesh was turned front to back. ``instant_of`` (static cameras:
    identity -> instant) also weighs each sample by how much it repeats the
    same sample of the other instants' people (:mod:`colmap_vc.gba.repeats`)."""
    registered = np.array(
        sorted(i for i, im in rec.images.items() if im.has_pose), dtype=np.int64
    )
    surface = surface_tracks(records, registered)
    if surface.num_tracks and tracks.num_tracks and tracks.keys is not None:
        # Only people whose keypoints the checks kept in that image, and not
        # those exchanged there.
        assert surface.keys is not None
        identity = surface.keys[surface.track, 0]
        width = int(max(identity.max(), tracks.keys[:, 0].max())) + 2
        code = surface.image_id * width + identity
        kept = np.unique(tracks.image_id * width + tracks.keys[tracks.track, 0])
        pairs = np.array(sorted(exchanged), dtype=np.int64).reshape(-1, 2)
        person = pairs[pairs[:, 1] >= 0]
        out = np.isin(surface.image_id, pairs[pairs[:, 1] < 0, 0]) | np.isin(
            code, person[:, 0] * width + person[:, 1]
        )
        surface = subset(surface, np.isin(code, kept) & ~out)
    noise = surface_noise(rec, tracks, surface, options, instant_of)
    if not any(np.isfinite(v).any() for v in noise.sigma_px.values()):
        return noise, 0
    good, counts = add_keypoint_points(rec, surface, options.min_track_length)
    return noise, int(counts[good].sum())


def surface_noise(
    rec: pycolmap.Reconstruction,
    keypoints: KeypointTracks,
    surface: KeypointTracks,
    options: KeypointBaOptions,
    instant_of: Mapping[int, str] | None = None,
) -> PeopleNoise:
    """The noise of each ``surface`` observation in keypoint units: its spread
    times the square root of its design effect (:mod:`colmap_vc.gba.correlated`),
    over the keypoints' spread, which keep COLMAP's loss and unit weight; a
    Cauchy loss at ``robust_sigmas`` spreads. Both kinds' spreads are measured
    against their tracks' points triangulated with ``rec``'s poses."""
    out = PeopleNoise.none(rec)
    sigma, robust = out.sigma_px, out.robust_px
    if surface.num_tracks == 0 or keypoints.num_tracks == 0:
        return out
    kp = correlated_noise(rec, keypoints, triangulate_tracks(rec, keypoints)[0])
    if not len(kp.sigma_px):
        return out
    unit = max(float(np.median(kp.sigma_px)), options.min_sigma_px)
    noise = correlated_noise(rec, surface, triangulate_tracks(rec, surface)[0])
    per_obs = noise.observation_sigma_px(options.min_sigma_px) / unit
    if instant_of:  # the instants repeat the whole mesh: separable correlation
        assert options.loss_scale_px is not None
        sigma_kp = keypoint_sigma_px(options.loss_scale_px)
        per_obs = per_obs * np.sqrt(repeat_design(surface, instant_of, sigma_kp))
    per_obs = log_rounded(per_obs)
    spread = noise.observation_spread_px(options.min_sigma_px)
    ok = np.isfinite(per_obs)
    for image_id in np.unique(surface.image_id[ok]):  # loop over images
        sel = ok & (surface.image_id == image_id)
        sigma[int(image_id)][surface.point2D_idx[sel]] = per_obs[sel]
        robust[int(image_id)][surface.point2D_idx[sel]] = (
            options.robust_sigmas * spread[sel]
        )
    logger.debug(
        "GBA: keypoint spread %.2f px; surface spread %.2f px, correlation %s by "
        "distance %s px, design effect median %.1f",
        unit,
        float(np.median(noise.sigma_px)) if len(noise.sigma_px) else float("nan"),
        np.round(noise.rho, 2),
        np.round(noise.bin_edges_px[1:], 1),
        float(np.nanmedian(noise.design)) if ok.any() else float("nan"),
    )
    return out
