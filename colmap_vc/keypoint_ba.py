"""Keypoint bundle adjustment: the people's keypoints as multi-view tracks by identity.

A keypoint VC (a landmark such as a knee or a heel) names the same 3D point in every
view of the same person, so its multi-view track is known a priori: (person, keypoint).
COLMAP's mapper instead builds tracks from the two-view inliers of verification, which
on real photos drops the keypoints that disagree with the (biased) surface VCs and
keeps a selection skewed by them. This pass rebuilds the model's keypoint points from
identities (people linked across images by ``augment``'s person associations),
triangulates them with the model's poses and runs COLMAP's bundle adjustment with a
Cauchy loss scaled to the keypoints' pixel error, keeping classic (SIFT) points and a
budget of the surface-VC points (``surface_per_image`` observations per image, more
for two images: dense maps rendered from a mesh fitted to the same landmarks add
correlated errors, docs/real-data.md).

On pose2sim (docs/results.md) the pass converges to the same poses from the mapper's
model, from the keypoint-only model and from the ground truth.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap

from . import database
from .structs import FloatArray, HitKind, IndexArray

logger = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True, slots=True)
class KeypointBaOptions:
    """Options of the keypoint bundle adjustment."""

    loss_scale_px: float = 16.0
    """Scale of the Cauchy loss, pixels (about the landmarks' error: MediaPipe's is
    10-15 px median on 1920-px frames)."""
    surface_per_image: float = 6.0
    """Surface-VC observations kept per registered image (an even random subset of the
    model's VC-only points; negative: keep them all). A fixed budget, not one that
    grows with the keypoints: the surface VCs of a mesh fitted to the same landmarks
    have errors correlated within each person and image, so they act as a prior of
    fixed strength on the poses (helps one instant, pose2sim: 41.7 -> 43.8 AUC@15),
    which more instants of keypoints should outweigh (five instants: docs/results.md).
    """
    surface_per_image_two_view: float = 24.0
    """The same budget for a model of two images, where one person's keypoint tracks
    (2 observations each) barely constrain the relative pose and the surface VCs
    condition it (synthetic two-view scenes, realistic priors: AUC@15 20.8 with 6,
    34.5 with 24; docs/results.md)."""
    min_track_length: int = 2
    """Keypoint tracks seen by fewer registered images are left out."""
    surface_seed: int = 0
    """Seed of the surface subset."""
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
    min_check_points: int = 10
    """Keypoint points a check needs (about half a person)."""


@dataclass(frozen=True, kw_only=True, slots=True)
class KeypointTracks:
    """Keypoint observations grouped into multi-view tracks by identity."""

    track: IndexArray  # (O,) int64 track index of each observation, sorted
    image_id: IndexArray  # (O,) int64
    point2D_idx: IndexArray  # (O,) int64, in the image's full keypoint list
    xy_img: FloatArray  # (O, 2) float64

    def __post_init__(self) -> None:
        n = self.track.shape[0]
        for name in ("image_id", "point2D_idx"):
            if getattr(self, name).shape != (n,):
                raise ValueError(f"{name} has shape {getattr(self, name).shape}")
        if self.xy_img.shape != (n, 2):
            raise ValueError(f"xy_img has shape {self.xy_img.shape}")

    @property
    def num_tracks(self) -> int:
        return int(self.track.max()) + 1 if len(self.track) else 0


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


def person_identities(
    associations: list[database.PersonAssociation],
) -> dict[tuple[int, int], int]:
    """(image_id, person_id) -> identity, by union-find over the associations."""
    parent: dict[tuple[int, int], tuple[int, int]] = {}

    def find(a: tuple[int, int]) -> tuple[int, int]:
        parent.setdefault(a, a)
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    for a in associations:  # loop over person pairs (a handful per image pair)
        ra = find((a.image_id1, a.person_id1))
        rb = find((a.image_id2, a.person_id2))
        if ra != rb:
            parent[max(ra, rb)] = min(ra, rb)
    roots = sorted({find(k) for k in parent})
    index = {r: i for i, r in enumerate(roots)}
    return {k: index[find(k)] for k in parent}


def keypoint_tracks(database_path: Path, image_ids: IndexArray) -> KeypointTracks:
    """The keypoint VCs of the given images, as tracks (person identity, keypoint).

    A VC keypoint is a keypoint when some pair matched it as ``HitKind.KEYPOINT``; its
    identity is its person's (``person_identities``) and its template track id.
    """
    views = database.read_views(database_path)
    num_classic = dict(
        zip(views.image_ids.tolist(), views.num_keypoints.tolist(), strict=True)
    )
    vc_keypoints, pairs = database.read_virtual_correspondences(database_path)
    identity = person_identities(database.read_person_associations(database_path))
    is_kp: dict[int, np.ndarray] = {
        v.image_id: np.zeros(len(v.track_id), dtype=bool) for v in vc_keypoints
    }
    for p in pairs:  # loop over image pairs, vectorized over VCs
        kp = p.kind == HitKind.KEYPOINT
        is_kp[p.image_id1][p.idx1[kp]] = True
        is_kp[p.image_id2][p.idx2[kp]] = True
    wanted = set(np.asarray(image_ids).tolist())
    parts = []
    for v in vc_keypoints:  # loop over images
        if v.image_id not in wanted or not is_kp[v.image_id].any():
            continue
        rows = np.flatnonzero(is_kp[v.image_id])
        ident = np.array(
            [identity.get((v.image_id, int(p)), -1) for p in v.person_id[rows]],
            dtype=np.int64,
        )
        ok = ident >= 0
        rows = rows[ok]
        parts.append(
            (
                ident[ok],
                v.track_id[rows],
                np.full(len(rows), v.image_id, dtype=np.int64),
                num_classic[v.image_id] + rows,
                v.xy_img[rows],
            )
        )
    parts = [part for part in parts if len(part[0])]
    if not parts:  # no keypoint VC of a person with an identity
        z = np.zeros(0, dtype=np.int64)
        return KeypointTracks(
            track=z, image_id=z, point2D_idx=z, xy_img=np.zeros((0, 2))
        )
    ident, track_id, image_id, idx, xy = (
        np.concatenate(a) for a in zip(*parts, strict=True)
    )
    # A chain of wrong associations can put two people of one image into one
    # identity: such tracks would see an image twice, so they are left out.
    _, track_of = np.unique(
        np.stack([ident, track_id], axis=1), axis=0, return_inverse=True
    )
    track_of = track_of.ravel()
    _, first, seen = np.unique(
        np.stack([track_of, image_id], axis=1),
        axis=0,
        return_index=True,
        return_counts=True,
    )
    bad = np.zeros(track_of.max() + 1, dtype=bool)
    bad[track_of[first[seen > 1]]] = True
    keep = ~bad[track_of]
    ident, track_id, image_id, idx, xy = (
        a[keep] for a in (ident, track_id, image_id, idx, xy)
    )
    _, track = np.unique(
        np.stack([ident, track_id], axis=1), axis=0, return_inverse=True
    )
    order = np.argsort(track, kind="stable")
    return KeypointTracks(
        track=track.ravel()[order].astype(np.int64),
        image_id=image_id[order],
        point2D_idx=idx[order],
        xy_img=xy[order],
    )


def triangulate_tracks(
    rec: pycolmap.Reconstruction, tracks: KeypointTracks
) -> tuple[FloatArray, IndexArray]:
    """DLT point (T, 3) of each track (the model's poses) and its view count (T,).

    A point behind any of its cameras (or at infinity) is NaN.
    """
    num = tracks.num_tracks
    rows = np.zeros((len(tracks.track), 2, 4))
    depth_row = np.zeros((len(tracks.track), 4))  # z of the point in its camera
    for image_id in np.unique(tracks.image_id):  # loop over images, vectorized over obs
        sel = tracks.image_id == image_id
        image = rec.image(int(image_id))
        T = image.cam_from_world().matrix()
        uv = np.asarray(rec.camera(image.camera_id).cam_from_img(tracks.xy_img[sel]))
        rows[sel, 0] = uv[:, :1] * T[2] - T[0]
        rows[sel, 1] = uv[:, 1:2] * T[2] - T[1]
        depth_row[sel] = T[2]
    rows /= np.linalg.norm(rows, axis=2, keepdims=True)
    A = np.zeros((num, 4, 4))  # normal equations A^T A per track
    np.add.at(A, tracks.track, np.einsum("oki,okj->oij", rows, rows))
    _, vecs = np.linalg.eigh(A)
    X = vecs[:, :, 0]
    w = np.where(np.abs(X[:, 3]) > 1e-12, X[:, 3], np.nan)
    X = X / w[:, None]
    behind = np.zeros(num, dtype=bool)
    np.logical_or.at(
        behind, tracks.track, np.einsum("oi,oi->o", depth_row, X[tracks.track]) <= 0
    )
    X[behind] = np.nan
    counts = np.bincount(tracks.track, minlength=num)
    return X[:, :3], counts


def bundle_adjust_inplace(rec: pycolmap.Reconstruction, loss_scale_px: float) -> None:
    """COLMAP's bundle adjustment (intrinsics fixed, Cauchy loss), in place."""
    ba = pycolmap.BundleAdjustmentOptions(
        refine_focal_length=False,
        refine_principal_point=False,
        refine_extra_params=False,
        print_summary=False,
    )
    ba.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
    ba.ceres.loss_function_scale = loss_scale_px
    pycolmap.bundle_adjustment(rec, ba)


def keypoint_bundle_adjustment(
    database_path: Path,
    rec: pycolmap.Reconstruction,
    options: KeypointBaOptions | None = None,
) -> tuple[pycolmap.Reconstruction, KeypointBaSummary]:
    """A copy of ``rec`` with keypoint tracks by identity, bundle-adjusted (module doc).

    ``rec`` is not modified. A database without keypoint VCs returns a plain copy.
    """
    options = options or KeypointBaOptions()
    t0 = time.perf_counter()
    out = pycolmap.Reconstruction(rec)
    registered = np.array(
        [i for i, im in out.images.items() if im.has_pose], dtype=np.int64
    )
    tracks = keypoint_tracks(Path(database_path), registered)
    if tracks.num_tracks == 0:
        logger.info(
            "keypoint BA: no keypoint VCs in %s: model unchanged", database_path
        )
        return out, KeypointBaSummary(
            num_tracks=0,
            num_keypoint_observations=0,
            num_surface_observations=0,
            num_surface_observations_dropped=0,
            elapsed_s=time.perf_counter() - t0,
        )
    views = database.read_views(database_path)
    num_classic = dict(
        zip(views.image_ids.tolist(), views.num_keypoints.tolist(), strict=True)
    )
    # The model's points: classic ones stay; VC-only ones are surface points (the
    # keypoint ones are rebuilt below), thinned to the budget.
    keypoint_obs = set(
        zip(tracks.image_id.tolist(), tracks.point2D_idx.tolist(), strict=True)
    )
    vc_only, vc_obs, stale, dropped = [], [], [], 0
    for point_id, point in out.points3D.items():  # loop over the model's points
        els = [(e.image_id, e.point2D_idx) for e in point.track.elements]
        if any(e in keypoint_obs for e in els):
            stale.append(point_id)  # rebuilt below, by identity
            continue
        if any(idx < num_classic[i] for i, idx in els):
            continue
        vc_only.append(point_id)
        vc_obs.append(len(els))
    for point_id in stale:  # deleting while iterating over points3D crashes pycolmap
        out.delete_point3D(point_id)
    X, counts = triangulate_tracks(out, tracks)
    good = (counts >= options.min_track_length) & np.isfinite(X).all(axis=1)
    num_kp_obs = int(counts[good].sum())
    per_image = (
        options.surface_per_image_two_view
        if len(registered) == 2
        else options.surface_per_image
    )
    if per_image >= 0 and vc_only:
        order = np.random.default_rng(options.surface_seed).permutation(len(vc_only))
        kept_obs = np.cumsum(np.asarray(vc_obs)[order])
        budget = per_image * len(registered)
        for k in order[kept_obs > budget]:
            dropped += vc_obs[k]
            out.delete_point3D(vc_only[k])
    starts = np.searchsorted(tracks.track, np.arange(tracks.num_tracks))
    ends = np.r_[starts[1:], len(tracks.track)]
    for t in np.flatnonzero(good):  # loop over tracks: pycolmap's API adds one point
        track = pycolmap.Track()
        for o in range(starts[t], ends[t]):
            track.add_element(int(tracks.image_id[o]), int(tracks.point2D_idx[o]))
        out.add_point3D(X[t], track)
    bundle_adjust_inplace(out, options.loss_scale_px)
    relocalised: list[str] = []
    left_out: dict[str, str] = {}
    if options.check_cameras:
        relocalised, left_out = check_cameras_inplace(out, tracks, options)
    summary = KeypointBaSummary(
        num_tracks=int(good.sum()),
        num_keypoint_observations=num_kp_obs,
        num_surface_observations=int(sum(vc_obs)) - dropped,
        num_surface_observations_dropped=dropped,
        elapsed_s=time.perf_counter() - t0,
        relocalised=tuple(relocalised),
        left_out=left_out,
    )
    logger.info(
        "keypoint BA: %d keypoint tracks (%d observations), %d surface-VC "
        "observations kept, %d dropped (%.1f s)",
        summary.num_tracks,
        summary.num_keypoint_observations,
        summary.num_surface_observations,
        summary.num_surface_observations_dropped,
        summary.elapsed_s,
    )
    return out, summary


def _subset(tracks: KeypointTracks, keep: np.ndarray) -> KeypointTracks:
    return KeypointTracks(
        track=tracks.track[keep],
        image_id=tracks.image_id[keep],
        point2D_idx=tracks.point2D_idx[keep],
        xy_img=tracks.xy_img[keep],
    )


def _residuals_px(
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


def _best_two_view_check(
    rec: pycolmap.Reconstruction,
    tracks: KeypointTracks,
    image_id: int,
    others: list[int],
    min_points: int,
) -> tuple[float, FloatArray, FloatArray]:
    """The smallest median error of image ``image_id``'s keypoints against the
    points any two other cameras triangulate, with those 2D-3D correspondences."""
    mine = tracks.image_id == image_id
    best = (np.inf, np.zeros((0, 2)), np.zeros((0, 3)))
    if not mine.any():
        return best
    image = rec.image(image_id)
    camera = rec.camera(image.camera_id)
    pose = image.cam_from_world().matrix()
    for a, j in enumerate(others):  # loop over image pairs (a few dozen at most)
        for k in others[a + 1 :]:
            sub = _subset(tracks, np.isin(tracks.image_id, [j, k]))
            X, counts = triangulate_tracks(rec, sub)
            pad = tracks.num_tracks - len(X)
            X = np.r_[X, np.full((max(pad, 0), 3), np.nan)]
            counts = np.r_[counts, np.zeros(max(pad, 0), np.int64)]
            t = tracks.track[mine]
            ok = (counts[t] == 2) & np.isfinite(X[t]).all(axis=1)
            if ok.sum() < min_points:
                continue
            xy, pts = tracks.xy_img[mine][ok], X[t[ok]]
            med = float(np.median(_residuals_px(camera, pose, xy, pts)))
            if med < best[0]:
                best = (med, xy, pts)
    return best


def check_cameras_inplace(
    rec: pycolmap.Reconstruction, tracks: KeypointTracks, options: KeypointBaOptions
) -> tuple[list[str], dict[str, str]]:
    """Each camera against keypoint points two *other* cameras triangulate.

    A camera whose keypoints miss the points of every pair of other cameras (the
    best pair's median error above ``max_check_ratio`` times the median camera's)
    contradicts the rest: a prior turned front to back puts its camera on the
    mirror side, consistently in every pair and cycle, and only the people's
    asymmetric 3D pose shows it. It is re-posed by PnP on the best pair's points
    when that fits as well as the other cameras do, else left out. Needs 4+
    cameras (with 3, two cameras always agree with each other). Cameras are
    visited in name order, worst first. Returns (re-posed names, left out: reason).
    """
    relocalised: list[str] = []
    left_out: dict[str, str] = {}
    while True:
        reg = sorted(
            (i for i, im in rec.images.items() if im.has_pose),
            key=lambda i: rec.image(i).name,  # name order, never the ids
        )
        if len(reg) < 4:
            break
        # The 6 cameras sharing most keypoints are enough witnesses.
        obs = {i: set(tracks.track[tracks.image_id == i].tolist()) for i in reg}
        checks = {}
        for i in reg:
            others = sorted(
                (j for j in reg if j != i),
                key=lambda j: (-len(obs[i] & obs[j]), rec.image(j).name),
            )[:6]
            checks[i] = _best_two_view_check(
                rec, tracks, i, others, options.min_check_points
            )
        errs = {i: c[0] for i, c in checks.items() if np.isfinite(c[0])}
        if len(errs) < 4:
            break
        logger.debug(
            "camera check: %s",
            {rec.image(i).name: round(e, 1) for i, e in errs.items()},
        )
        worst = max(errs, key=lambda i: (errs[i], rec.image(i).name))
        typical = float(np.median([e for i, e in errs.items() if i != worst]))
        limit = max(options.max_check_ratio * typical, options.loss_scale_px)
        if errs[worst] <= limit:
            break
        image = rec.image(worst)
        name = image.name
        if name in relocalised or name in left_out:
            break
        _, xy, pts = checks[worst]
        camera = rec.camera(image.camera_id)
        est = pycolmap.AbsolutePoseEstimationOptions()
        est.ransac.max_error = options.loss_scale_px
        est.ransac.random_seed = options.surface_seed
        found = pycolmap.estimate_and_refine_absolute_pose(xy, pts, camera, est)
        pnp = np.inf
        if found is not None and found["num_inliers"] >= options.min_check_points:
            pnp = float(
                np.median(
                    _residuals_px(camera, found["cam_from_world"].matrix(), xy, pts)
                )
            )
        if pnp <= limit:
            rec.frame(image.frame_id).rig_from_world = found["cam_from_world"]
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
        else:
            left_out[name] = (
                f"left out: its keypoints miss the points the other cameras "
                f"triangulate (median {errs[worst]:.0f} px, the median camera "
                f"{typical:.0f} px) and no pose fits them"
            )
            logger.warning("camera check: %s %s", name, left_out[name])
            rec.deregister_frame(image.frame_id)
        bundle_adjust_inplace(rec, options.loss_scale_px)
    return relocalised, left_out
