"""The noise of each person's observations in each image, estimated from the data.

A body prediction errs as a whole: a mesh turned by a few degrees, a landmark
detector biased in one camera, shift every point of that person in that image
together. Its observations (keypoints or surface samples) then carry two errors:
one of their own (spread sigma, independent) and one they share (tau, the same for
the N observations of the cluster). Weighted as N independent observations, the
shared error would count N times; the estimate of the cluster's offset has
variance tau^2 + sigma^2 / N, which N independent observations of variance
sigma^2 + N tau^2 reproduce (Kish's design effect). Each observation gets that
variance, so a cluster of biased surface samples weighs about as much as one
observation at its bias, whatever the number of samples, and an unbiased one
(clean priors) counts fully.

Both are estimated per cluster (kind, image, person) from the residuals against
points triangulated by *all* views. The shared error is the part of the cluster's
residuals that a small motion of its camera explains (least squares on the
derivative of the projections by the camera's rotation and translation): the part
that would move the camera, and a body predicted turned, shifted or at the wrong
depth errs in that way. tau^2 is its mean square per coordinate less what noise
alone would fit (6 s^2 / N, s the spread left in the residuals); the spread
sigma is the scaled MAD of the rest, corrected for the fit of the points to
their own views (a two-view track's residuals keep a quarter of the variance).

`map` uses it for the keypoints: what one keypoint residual is worth against the
cameras' up (:mod:`colmap_vc.mapping.up`). The GBA's surface samples are weighted
by :mod:`colmap_vc.gba.correlated` instead, whose correlation by distance also
sees errors shorter-ranged than a whole person's.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pycolmap

from ..keypoint_tracks import KeypointTracks, observed_in_posed_images
from ..structs import FloatArray, IndexArray

MAD_TO_SIGMA = 1.4826
"""Standard deviation of a normal distribution over its median absolute deviation."""


@dataclass(frozen=True, kw_only=True, slots=True)
class ClusterNoise:
    """Noise of the observations of one kind, per cluster (image, person)."""

    cluster: IndexArray  # (O,) cluster of each observation (-1: not estimated)
    image_id: IndexArray  # (C,)
    identity: IndexArray  # (C,)
    count: IndexArray  # (C,) observations
    sigma_px: FloatArray  # (C,) independent spread, per coordinate
    tau_px: FloatArray  # (C,) shared offset, per coordinate

    def observation_sigma_px(self, min_sigma_px: float) -> FloatArray:
        """(O,) sqrt(sigma^2 + N tau^2) of each observation's cluster (NaN: none)."""
        var = np.maximum(self.sigma_px, min_sigma_px) ** 2 + self.count * self.tau_px**2
        return self._per_observation(np.sqrt(var))

    def observation_spread_px(self, min_sigma_px: float) -> FloatArray:
        """(O,) the independent spread sigma of each observation's cluster."""
        return self._per_observation(np.maximum(self.sigma_px, min_sigma_px))

    def _per_observation(self, per_cluster: FloatArray) -> FloatArray:
        out = np.full(len(self.cluster), np.nan)
        ok = self.cluster >= 0
        out[ok] = per_cluster[self.cluster[ok]]
        return out


def reprojection_residuals(
    rec: pycolmap.Reconstruction, tracks: KeypointTracks, X: FloatArray
) -> FloatArray:
    """(O, 2) projection of each observation's track point minus its pixel (NaN for
    observations in images without a pose, of points without a position or behind
    the camera)."""
    out = np.full((len(tracks.track), 2), np.nan)
    posed = observed_in_posed_images(rec, tracks)
    for image_id in np.unique(tracks.image_id[posed]):  # loop over images
        sel = np.flatnonzero(tracks.image_id == image_id)
        image = rec.image(int(image_id))
        T = image.cam_from_world().matrix()
        Xc = X[tracks.track[sel]] @ T[:, :3].T + T[:, 3]
        front = np.isfinite(Xc).all(axis=1) & (Xc[:, 2] > 1e-9)
        if front.any():
            proj = np.asarray(rec.camera(image.camera_id).img_from_cam(Xc[front]))
            out[sel[front]] = proj - tracks.xy_img[sel[front]]
    return out


def cluster_noise(
    rec: pycolmap.Reconstruction, tracks: KeypointTracks, X: FloatArray
) -> ClusterNoise:
    """Spread and shared offset per (image, person) of ``tracks``' observations
    against the track points ``X`` (T, 3), triangulated from these observations
    (module doc); tracks seen by one image do not count."""
    res = reprojection_residuals(rec, tracks, X)
    # A point triangulated from its own n views fits them: the residuals keep
    # 1 - 3 / (2 n) of the independent noise's variance (3 of the 2n coordinates
    # are spent on the point). The spread is corrected for it, so a two-view
    # track's observations count like any other's.
    views = np.bincount(
        tracks.track[np.isfinite(res).all(axis=1)], minlength=tracks.num_tracks
    )[tracks.track]
    res[views < 2] = np.nan
    with np.errstate(divide="ignore", invalid="ignore"):
        kept = np.sqrt(1.0 - 3.0 / (2.0 * views))
    ok = np.isfinite(res).all(axis=1)
    if tracks.keys is None or not ok.any():
        z = np.zeros(0, dtype=np.int64)
        return ClusterNoise(
            cluster=np.full(len(tracks.track), -1, dtype=np.int64),
            image_id=z,
            identity=z,
            count=z,
            sigma_px=np.zeros(0),
            tau_px=np.zeros(0),
        )
    identity = tracks.keys[tracks.track, 0]
    keys, cl = np.unique(
        np.stack([tracks.image_id[ok], identity[ok]], axis=1),
        axis=0,
        return_inverse=True,
    )
    cl = cl.ravel()
    n = np.bincount(cl, minlength=len(keys))
    r = res[ok]
    shared = _fitted_field(_pose_jacobians(rec, tracks, X)[ok], r, cl, len(keys))
    order = np.argsort(cl, kind="stable")
    starts = np.r_[0, np.cumsum(n)[:-1]]
    dev = (np.abs(r - shared) / kept[ok][:, None])[order]
    mad = _grouped_median(dev, starts, n)
    sigma = MAD_TO_SIGMA * mad.mean(axis=1)
    # E|shared|^2 per coordinate = tau^2 + (6 / n) s^2 (6 fitted coefficients),
    # s the spread left in the residuals
    field2 = np.bincount(cl, weights=(shared**2).sum(axis=1), minlength=len(keys))
    left = np.bincount(cl, weights=kept[ok] ** 2, minlength=len(keys)) / n
    tau2 = np.maximum(field2 / (2 * n) - 6 * left * sigma**2 / n, 0.0)
    cluster = np.full(len(tracks.track), -1, dtype=np.int64)
    cluster[np.flatnonzero(ok)] = cl
    return ClusterNoise(
        cluster=cluster,
        image_id=keys[:, 0].astype(np.int64),
        identity=keys[:, 1].astype(np.int64),
        count=n.astype(np.int64),
        sigma_px=sigma,
        tau_px=np.sqrt(tau2),
    )


def _pose_jacobians(
    rec: pycolmap.Reconstruction, tracks: KeypointTracks, X: FloatArray
) -> FloatArray:
    """(O, 2, 6) derivative of each observation's projection by a small motion of
    its camera (rotation, translation): the error a camera pose can absorb."""
    out = np.full((len(tracks.track), 2, 6), np.nan)
    posed = observed_in_posed_images(rec, tracks)
    for image_id in np.unique(tracks.image_id[posed]):  # loop over images
        sel = np.flatnonzero(tracks.image_id == image_id)
        image = rec.image(int(image_id))
        camera = rec.camera(image.camera_id)
        T = image.cam_from_world().matrix()
        Xc = X[tracks.track[sel]] @ T[:, :3].T + T[:, 3]
        x, y, z = Xc.T
        # d(pixel)/d(camera point) by central differences: any camera model.
        h = 1e-6 * np.maximum(np.abs(z), 1e-3)
        P = np.empty((len(sel), 2, 3))
        for k in range(3):  # loop over the 3 coordinates
            step = np.zeros_like(Xc)
            step[:, k] = h
            plus = np.asarray(camera.img_from_cam(Xc + step))
            minus = np.asarray(camera.img_from_cam(Xc - step))
            P[:, :, k] = (plus - minus) / (2 * h[:, None])
        M = np.zeros((len(sel), 3, 6))
        M[:, 0, 1], M[:, 0, 2] = z, -y  # -[Xc]x
        M[:, 1, 0], M[:, 1, 2] = -z, x
        M[:, 2, 0], M[:, 2, 1] = y, -x
        M[:, :, 3:] = np.eye(3)
        out[sel] = P @ M
    return out


def _fitted_field(
    J: FloatArray, r: FloatArray, cluster: IndexArray, num: int
) -> FloatArray:
    """(O, 2) least-squares fit of the residuals of each cluster by J delta."""
    m = J.shape[2]
    JtJ = np.zeros((num, m, m))
    Jtr = np.zeros((num, m))
    np.add.at(JtJ, cluster, np.einsum("oki,okj->oij", J, J))
    np.add.at(Jtr, cluster, np.einsum("oki,ok->oi", J, r))
    d = np.sqrt(np.maximum(np.einsum("cii->ci", JtJ), 1e-12))  # column scaling
    A = JtJ / d[:, :, None] / d[:, None, :] + 1e-9 * np.eye(m)
    delta = np.linalg.solve(A, (Jtr / d)[..., None])[..., 0] / d
    return np.einsum("oki,oi->ok", J, delta[cluster])


def _grouped_median(
    values: FloatArray, starts: IndexArray, counts: IndexArray
) -> FloatArray:
    """Per-group median (G, D) of ``values`` (N, D) sorted by group."""
    group = np.repeat(np.arange(len(counts)), counts)
    out = np.empty((len(counts), values.shape[1]))
    for d in range(values.shape[1]):  # loop over the 2 coordinates
        order = np.lexsort((values[:, d], group))
        v = values[order, d]
        lo = starts + (counts - 1) // 2
        hi = starts + counts // 2
        out[:, d] = 0.5 * (v[lo] + v[hi])
    return out
