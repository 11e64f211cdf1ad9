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
points triangulated by *all* views: the shared error is an affine function of the
pixel position fitted to the cluster's residuals (an offset, and the stretch and
turn of a body predicted turned or at the wrong depth), tau^2 its mean square less
what noise alone would fit; the spread is the scaled MAD of the rest.
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
    against the track points ``X`` (T, 3) (module doc)."""
    res = reprojection_residuals(rec, tracks, X)
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
    shared = _affine_field(tracks.xy_img[ok], r, cl, len(keys))  # (O_ok, 2)
    order = np.argsort(cl, kind="stable")
    starts = np.r_[0, np.cumsum(n)[:-1]]
    dev = np.abs(r - shared)[order]
    centre = _grouped_median(dev, starts, n)
    sigma = MAD_TO_SIGMA * centre.mean(axis=1)
    # E|shared|^2 per coordinate = tau^2 + (3 / n) sigma^2 (3 fitted coefficients)
    field2 = np.bincount(cl, weights=(shared**2).sum(axis=1), minlength=len(keys))
    tau2 = np.maximum(field2 / (2 * n) - 3 * sigma**2 / n, 0.0)
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


def _affine_field(
    xy: FloatArray, r: FloatArray, cluster: IndexArray, num: int
) -> FloatArray:
    """(O, 2) least-squares affine function of the pixel position fitted to the
    residuals ``r`` of each cluster (its shared error: an offset, and the
    stretch and turn that a body turned or scaled in depth gives), evaluated at
    each observation. A cluster with fewer than 6 observations gets its mean."""
    centre = np.zeros((num, 2))
    np.add.at(centre, cluster, xy)
    n = np.bincount(cluster, minlength=num).astype(np.float64)
    centre /= np.maximum(n, 1)[:, None]
    scale = np.zeros(num)
    d = xy - centre[cluster]
    np.add.at(scale, cluster, (d**2).sum(axis=1))
    scale = np.sqrt(np.maximum(scale / np.maximum(n, 1), 1e-12))
    A = np.c_[d / scale[cluster][:, None], np.ones(len(xy))]  # (O, 3)
    AtA = np.zeros((num, 3, 3))
    Atr = np.zeros((num, 3, 2))
    np.add.at(AtA, cluster, A[:, :, None] * A[:, None, :])
    np.add.at(Atr, cluster, A[:, :, None] * r[:, None, :])
    small = n < 6
    AtA[small, :2, :] = 0.0
    AtA[small, :, :2] = 0.0
    AtA[small, 0, 0] = AtA[small, 1, 1] = 1.0
    Atr[small, :2] = 0.0
    coef = np.linalg.solve(AtA + 1e-9 * np.eye(3), Atr)  # (C, 3, 2)
    return np.einsum("oi,oij->oj", A, coef[cluster])


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
