"""The noise of dense surface observations: a spread, and a correlation by distance.

A dense-correspondence map errs smoothly: neighbouring pixels slide together (a
DensePose-like network, or a mesh fitted to a few landmarks and rendered). Two
surface samples a few pixels apart in one image then share most of their error,
and samples far apart share little of it. Weighted as independent observations,
the 500 samples of a person in an image would count 500 times where their image
holds the evidence of a few dozen; a fixed weight per image (what the default
keypoint BA gives the mapper's surface points) does not follow how far the
map's errors reach.

This module measures the correlation instead. For the observations of one kind
(the surface tracks by identity) against points triangulated by all their views:

- each cluster (image, person) has a spread sigma: the scaled median absolute
  residual per coordinate, corrected for the fit of a point to its own n views
  (its residuals keep 1 - 3 / (2n) of the noise's variance);
- the correlation rho(d) of two residuals of one cluster at pixel distance d is
  pooled over all clusters, in distance bins growing by sqrt(2) (no length scale is
  assumed), normalised by the variance, made non-increasing and clipped to [0, 1];
- an observation's design effect is the sum of its correlations with the
  observations of its cluster, itself included: n_i = sum_j rho(d_ij). Weighting
  it by 1 / (sigma^2 n_i) gives a cluster the weight of about (its area / the area
  of one correlation cell) independent observations, however densely it is
  sampled (the row sums of the correlation matrix: the diagonal approximation of
  generalised least squares).

Only residuals within 3 sigma of zero enter the correlation: a limb whose map is
flipped left and right is an outlier, not a correlated error.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pycolmap

from ..keypoint_tracks import KeypointTracks
from ..structs import FloatArray, IndexArray
from .noise import MAD_TO_SIGMA, reprojection_residuals

INLIER_SPREADS = 3.0
"""Residuals within this many spreads of zero in both coordinates enter the
correlation estimate."""


@dataclass(frozen=True, kw_only=True, slots=True)
class CorrelatedNoise:
    """Spread and correlation of one kind of observations (module doc)."""

    cluster: IndexArray  # (O,) cluster (image, person) of each observation; -1: none
    sigma_px: FloatArray  # (C,) spread per coordinate of each cluster, pixels
    bin_edges_px: FloatArray  # (B + 1,) pixel-distance bins of the correlation
    rho: FloatArray  # (B,) correlation of two residuals of a cluster, per bin
    design: FloatArray  # (O,) sum_j rho(d_ij) over the observation's cluster (NaN)

    def observation_sigma_px(self, min_sigma_px: float) -> FloatArray:
        """(O,) sigma sqrt(n_i) of each observation (NaN: not estimated)."""
        return self.observation_spread_px(min_sigma_px) * np.sqrt(self.design)

    def observation_spread_px(self, min_sigma_px: float) -> FloatArray:
        """(O,) the spread sigma of each observation's cluster (NaN: none)."""
        out = np.full(len(self.cluster), np.nan)
        ok = self.cluster >= 0
        out[ok] = np.maximum(self.sigma_px[self.cluster[ok]], min_sigma_px)
        return out


def correlated_noise(
    rec: pycolmap.Reconstruction, tracks: KeypointTracks, X: FloatArray
) -> CorrelatedNoise:
    """Spread, correlation by distance and design effect of ``tracks``'
    observations against the track points ``X`` (T, 3) (module doc); tracks seen
    by fewer than two posed images do not count."""
    res = reprojection_residuals(rec, tracks, X)
    finite = np.isfinite(res).all(axis=1)
    views = np.bincount(tracks.track[finite], minlength=tracks.num_tracks)
    n_views = views[tracks.track]
    ok = finite & (n_views >= 2)
    none = CorrelatedNoise(
        cluster=np.full(len(tracks.track), -1, dtype=np.int64),
        sigma_px=np.zeros(0),
        bin_edges_px=np.zeros(1),
        rho=np.zeros(0),
        design=np.full(len(tracks.track), np.nan),
    )
    if tracks.keys is None or not ok.any():
        return none
    with np.errstate(divide="ignore", invalid="ignore"):
        kept = np.sqrt(1.0 - 3.0 / (2.0 * n_views))
    r = np.where(ok[:, None], res / np.where(ok, kept, 1.0)[:, None], np.nan)
    identity = tracks.keys[tracks.track, 0]
    _, cl = np.unique(
        np.stack([tracks.image_id[ok], identity[ok]], axis=1),
        axis=0,
        return_inverse=True,
    )
    cluster = np.full(len(tracks.track), -1, dtype=np.int64)
    cluster[ok] = cl.ravel()
    members = _members(cluster)
    sigma = np.array(
        [MAD_TO_SIGMA * np.median(np.abs(r[m])) for m in members]  # loop: clusters
    )
    extent = max(
        float(np.ptp(tracks.xy_img[m], axis=0).max()) if len(m) > 1 else 0.0
        for m in members  # loop over clusters
    )
    edges = _edges(extent)
    nbins = len(edges) - 1
    num = np.zeros(nbins)
    den = np.zeros(nbins)
    var = 0.0
    count = 0
    for m, s in zip(members, sigma, strict=True):  # loop over clusters
        inl = m[np.abs(r[m]).max(axis=1) <= INLIER_SPREADS * max(s, 1e-9)]
        if len(inl) < 2:
            continue
        b = _bins(tracks.xy_img[inl], nbins)
        cov = r[inl] @ r[inl].T / 2.0
        iu = np.triu_indices(len(inl), k=1)
        num += np.bincount(b[iu], weights=cov[iu], minlength=nbins)
        den += np.bincount(b[iu], minlength=nbins)
        var += float(np.trace(cov))
        count += len(inl)
    if count == 0:
        return none
    rho = _monotone(num, den, var / count, 2.0 / np.sqrt(count))
    design = np.full(len(tracks.track), np.nan)
    for m in members:  # loop over clusters
        design[m] = rho[_bins(tracks.xy_img[m], nbins)].sum(axis=1)  # rho(0) = 1
    return CorrelatedNoise(
        cluster=cluster, sigma_px=sigma, bin_edges_px=edges, rho=rho, design=design
    )


def _members(cluster: IndexArray) -> list[IndexArray]:
    """Observation indices of each cluster 0..C-1."""
    order = np.argsort(cluster, kind="stable")
    order = order[cluster[order] >= 0]
    counts = np.bincount(cluster[order])
    return np.split(order, np.cumsum(counts)[:-1])


def _edges(extent_px: float) -> FloatArray:
    """Distance bins: [0, 1) px, then edges growing by sqrt(2) past ``extent_px``."""
    k = int(np.ceil(2 * np.log2(max(extent_px, 1.0) * np.sqrt(2)))) + 1
    return np.r_[0.0, np.sqrt(2.0) ** np.arange(k)]


def _bins(xy: FloatArray, num_bins: int) -> IndexArray:
    """(N, N) distance bin (:func:`_edges`) of every pair of pixels: 0 below 1 px,
    then floor(log2 d^2) + 1, as edges growing by sqrt(2) from 1 px give."""
    d2 = (xy[:, None, 0] - xy[None, :, 0]) ** 2 + (xy[:, None, 1] - xy[None, :, 1]) ** 2
    with np.errstate(divide="ignore"):
        b = np.floor(np.log2(d2)) + 1.0
    return np.clip(np.nan_to_num(b, neginf=0.0), 0, num_bins - 1).astype(np.intp)


def _monotone(num: FloatArray, den: FloatArray, var: float, noise: float) -> FloatArray:
    """Correlation per bin: covariance over variance, empty bins taking the
    previous bin's value, non-increasing, within [0, 1], zero from the first bin
    below ``noise`` on."""
    rho = np.full(len(num), np.nan)
    # A bin's correlation has a standard error of at least 1 / sqrt(its pairs):
    # bins with fewer pairs than the significance level asks are read as empty.
    seen = den >= 1.0 / noise**2
    rho[seen] = num[seen] / den[seen] / max(var, 1e-12)
    rho[0] = 1.0  # closer than a pixel: the same error
    for k in range(1, len(rho)):  # loop over a few dozen bins
        if not seen[k]:
            rho[k] = rho[k - 1]
    rho = np.minimum.accumulate(np.clip(rho, 0.0, 1.0))
    rho[np.cumsum(rho < noise) > 0] = 0.0
    return rho
