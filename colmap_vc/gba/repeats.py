"""Repeated detections: a person who stands still before a static camera.

A static camera films the same place over many instants, and each instant's people
are identities of their own (the association never links two instants:
:mod:`colmap_vc.static_cameras`). Someone who stands still shows the detector
nearly the same picture at every instant, and the detector makes nearly the same
error. Model a landmark's error at instant t as e_t = b + u_t: a bias b that
follows the person's pose and look, and a jitter u_t that changes from frame to
frame (per coordinate, var(b) + var(u) = sigma^2, the keypoints' spread). Counted
as independent, 18 instants of a still bystander weigh 18 times what they hold,
and with two cameras their shared bias bends the pair: on both pose2sim videos,
cam01-cam02 is 6 deg off at 20 instants and under 1 deg at 2 (docs/results.md,
"Two static cameras over many instants: a person who stands still").

The errors of one landmark at two instants, in one image, correlate by
rho = var(b) / sigma^2. Their pixel distance d tells how much: where the person
did not move, d is the jitter's difference, E[d^2] = 4 var(u) (two coordinates,
two instants), so rho = 1 - d^2 / (4 sigma^2), at least 0. A person who moved
between the instants is farther apart and gets 0, as a changed pose changes the
bias. An observation's design effect is m = 1 + the sum of rho over the same
landmark of the other instants' people in its image; weighting it by
1 / (m sigma^2) (the row sums of the correlation matrix: the diagonal
approximation of generalised least squares, as :mod:`colmap_vc.gba.correlated`
does for surface samples) gives a person who stood still for n instants the
weight of about one instant, and one who moved its n. People of the same
instant are different people, whatever their distance: never repeats.

One pair's estimate is one draw: clipped at 0, its mean is
1 - (1 - rho)(1 - exp(-1 / (1 - rho))), rho itself where the bias dominates and
more where the jitter does (1/e where the errors are independent). A still
person whose errors are all jitter then weighs less than he could, a loss of
precision, not a bias.

sigma is the keypoints' error against the truth, not their residuals' spread: the
poses absorb what the residuals would show, a repeated bias most of all, which is
the error modelled here (two cameras at 20 instants of pose2sim: the residuals
spread 4.5-5.3 px per coordinate, the landmarks' error is 13.6 px). The caller
gives it (`map`: the keypoints' Cauchy scale, their median 2D error, over
sqrt(2 ln 2); docs/gba.md, "Keypoints a static camera repeats").
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import pycolmap

from ..keypoint_tracks import KeypointTracks
from ..structs import FloatArray
from .ceres import PeopleNoise, log_rounded

MAX_PAIRS = 4_000_000
"""Observation pairs compared at once (about 100 MB of temporaries): 80 instants of
3 people seen by 4 cameras are 7.6 million pairs, a few minutes of video at
several instants a second many more."""

MIN_DESIGN = 1.04
"""A track with no observation whose design effect reaches this keeps COLMAP's
own weight (unit, the keypoints' loss): its noise, sqrt(m), would round to 1 in
the 2% steps the weights take (:func:`~colmap_vc.gba.ceres.log_rounded`)."""


def keypoint_sigma_px(loss_scale_px: float) -> float:
    """The keypoints' error per coordinate from their Cauchy scale, their median 2D
    error: over sqrt(2 ln 2), the median length of a 2D Gaussian error in units of
    its per-coordinate deviation (module doc)."""
    return loss_scale_px / float(np.sqrt(2.0 * np.log(2.0)))


def repeat_design(
    tracks: KeypointTracks, instant_of: Mapping[int, str], sigma_px: float
) -> FloatArray:
    """(O,) design effect m of each observation of ``tracks`` (module doc).
    ``instant_of``: identity -> instant; identities it does not name (an image
    that is not a static camera's) repeat nothing."""
    assert tracks.keys is not None
    index = {name: k for k, name in enumerate(sorted(set(instant_of.values())))}
    when = np.array(
        [
            index[instant_of[k]] if k in instant_of else -1
            for k in tracks.keys[:, 0].tolist()
        ],
        dtype=np.int64,
    )[tracks.track]  # loop over tracks
    landmark = tracks.keys[tracks.track, 1]
    design = np.ones(len(tracks.track))
    known = np.flatnonzero(when >= 0)
    if len(known) < 2 or sigma_px <= 0:
        return design
    # Pairs within each (image, landmark): every observation with every one of
    # its group, itself included (rho 0 there: same instant). Groups hold the
    # instants times the people; chunks of them bound the pairs held at once.
    _, group = np.unique(
        np.stack([tracks.image_id[known], landmark[known]], axis=1),
        axis=0,
        return_inverse=True,
    )
    group = group.ravel()
    order = known[np.argsort(group, kind="stable")]
    sizes = np.bincount(group)
    ends = np.cumsum(sizes)
    chunk = np.cumsum(sizes**2) // MAX_PAIRS
    for c in np.unique(chunk).tolist():  # loop over chunks of groups
        groups = np.flatnonzero(chunk == c)
        size_of = np.repeat(sizes[groups], sizes[groups])
        rows = order[ends[groups[0]] - sizes[groups[0]] : ends[groups[-1]]]
        start_of = np.repeat(np.cumsum(sizes[groups]) - sizes[groups], sizes[groups])
        i = np.repeat(rows, size_of)
        offset = np.arange(len(i)) - np.repeat(np.cumsum(size_of) - size_of, size_of)
        j = rows[np.repeat(start_of, size_of) + offset]
        d2 = ((tracks.xy_img[i] - tracks.xy_img[j]) ** 2).sum(axis=1)
        rho = np.clip(1.0 - d2 / (4.0 * sigma_px**2), 0.0, None)
        design += np.bincount(
            i, weights=rho * (when[i] != when[j]), minlength=len(design)
        )
    return design


def repeat_noise(
    rec: pycolmap.Reconstruction,
    tracks: KeypointTracks,
    instant_of: Mapping[int, str],
    sigma_px: float,
    loss_scale_px: float,
) -> tuple[PeopleNoise, FloatArray]:
    """The keypoint observations of ``rec``'s posed images weighted by their
    design effect at the keypoints' error ``sigma_px`` per coordinate (module
    doc) -> (their noise in keypoint units, sqrt(m) under the keypoints' Cauchy
    loss at ``loss_scale_px``; the design effect m of each observation of
    ``tracks``). Only the tracks with a repeated observation (m of at least
    :data:`MIN_DESIGN`) get a noise, all their observations: the others keep
    COLMAP's weight."""
    out = PeopleNoise.none(rec)
    sigma, robust = out.sigma_px, out.robust_px
    design = repeat_design(tracks, instant_of, sigma_px)
    repeated = np.zeros(tracks.num_tracks, dtype=bool)
    np.logical_or.at(repeated, tracks.track, design >= MIN_DESIGN)
    sel = repeated[tracks.track] & np.isin(tracks.image_id, list(sigma))
    noise = log_rounded(np.sqrt(design))
    for image_id in np.unique(tracks.image_id[sel]).tolist():  # loop over images
        rows = sel & (tracks.image_id == image_id)
        sigma[image_id][tracks.point2D_idx[rows]] = noise[rows]
        robust[image_id][tracks.point2D_idx[rows]] = loss_scale_px
    return out, design
