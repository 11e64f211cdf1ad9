"""Keypoint tracks: the people's keypoints as multi-view tracks by identity.

A keypoint VC (a landmark such as a knee or a heel) names the same 3D point in every
view of the same person, so its multi-view track is known a priori: (person identity,
keypoint). This module reads those tracks from an augmented database, triangulates
them with a model's poses and puts them into the model; :mod:`colmap_vc.keypoint_ba`
adjusts them, :mod:`colmap_vc.camera_check` checks each camera against them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pycolmap

from .structs import BoolArray, FloatArray, HitKind, IndexArray
from .vc_records import VcRecords


@dataclass(frozen=True, kw_only=True, slots=True)
class KeypointTracks:
    """Keypoint observations grouped into multi-view tracks by identity."""

    track: IndexArray  # (O,) int64 track index of each observation, sorted
    image_id: IndexArray  # (O,) int64
    point2D_idx: IndexArray  # (O,) int64, in the image's full keypoint list
    xy_img: FloatArray  # (O, 2) float64
    keys: IndexArray | None = None  # (T, 2) int64: (identity, template track id)

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


def keypoint_tracks(records: VcRecords, image_ids: IndexArray) -> KeypointTracks:
    """The keypoint VCs of the given images, as tracks (person identity, keypoint).

    A VC keypoint is a keypoint when some pair matched it as ``HitKind.KEYPOINT``; its
    identity is its person's (``person_identities``) and its template track id.
    """
    return body_tracks(records, image_ids, surface=False)


def surface_tracks(records: VcRecords, image_ids: IndexArray) -> KeypointTracks:
    """The surface VCs of the given images, as tracks (person identity, template
    surface sample): one 3D point of the body seen (or hidden) in every view of the
    person, the X1 that all pairs of those views share."""
    return body_tracks(records, image_ids, surface=True)


def vc_identities(records: VcRecords) -> dict[int, IndexArray]:
    """Per image, the person identity (``person_identities``) of each of its VC
    keypoints, in their order after the classic keypoints (-1: none)."""
    return {
        v.image_id: np.array(
            [records.identity.get((v.image_id, int(p)), -1) for p in v.person_id],
            dtype=np.int64,
        )
        for v in records.vc_keypoints  # loop over images
    }


def body_tracks(
    records: VcRecords, image_ids: IndexArray, *, surface: bool
) -> KeypointTracks:
    """The keypoint (``surface`` False) or surface VCs of the given images as tracks
    by (person identity, template track id). A VC keypoint is a keypoint when some
    pair matched it as ``HitKind.KEYPOINT``, a surface sample when a pair matched it
    and none as a keypoint."""
    num_classic = records.num_classic
    identity = records.identity
    is_kp: dict[int, np.ndarray] = {
        v.image_id: np.zeros(len(v.track_id), dtype=bool) for v in records.vc_keypoints
    }
    used = {k: v.copy() for k, v in is_kp.items()}
    for p in records.pairs:  # loop over image pairs, vectorized over VCs
        kp = p.kind == HitKind.KEYPOINT
        is_kp[p.image_id1][p.idx1[kp]] = True
        is_kp[p.image_id2][p.idx2[kp]] = True
        used[p.image_id1][p.idx1] = True
        used[p.image_id2][p.idx2] = True
    chosen = {k: used[k] & ~v for k, v in is_kp.items()} if surface else is_kp
    wanted = set(np.asarray(image_ids).tolist())
    parts = []
    for v in records.vc_keypoints:  # loop over images
        if v.image_id not in wanted or not chosen[v.image_id].any():
            continue
        rows = np.flatnonzero(chosen[v.image_id])
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
    if not parts:  # no VC of the kind of a person with an identity
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
    keys, track = np.unique(
        np.stack([ident, track_id], axis=1), axis=0, return_inverse=True
    )
    order = np.argsort(track, kind="stable")
    return KeypointTracks(
        track=track.ravel()[order].astype(np.int64),
        image_id=image_id[order],
        point2D_idx=idx[order],
        # float64 already (the database's x, y are f8); the unpacking of the
        # generators above joins the five arrays' dtypes, asarray restores it.
        xy_img=np.asarray(xy[order], dtype=np.float64),
        keys=keys.astype(np.int64),
    )


def mirrored_tracks(tracks: KeypointTracks, mirror: dict[int, int]) -> IndexArray:
    """(T,) the track of the same person's left/right counterpart (-1: none).

    ``mirror`` maps a template track id to its counterpart's (left knee -> right
    knee); a track id absent from it has none.
    """
    if tracks.keys is None or not mirror:
        return np.full(tracks.num_tracks, -1, dtype=np.int64)
    src = np.array(sorted(mirror), dtype=np.int64)
    dst = np.array([mirror[k] for k in src.tolist()], dtype=np.int64)
    ident, tid = tracks.keys[:, 0], tracks.keys[:, 1]
    pos = np.clip(np.searchsorted(src, tid), 0, len(src) - 1)
    partner = np.where(src[pos] == tid, dst[pos], -1)
    # keys are sorted (identity, track id): find (identity, partner) among them.
    width = int(max(tracks.keys[:, 1].max(), dst.max())) + 2
    code = tracks.keys[:, 0] * width + tracks.keys[:, 1]
    want = ident * width + partner
    at = np.clip(np.searchsorted(code, want), 0, len(code) - 1)
    return np.where((partner >= 0) & (code[at] == want), at, -1).astype(np.int64)


@dataclass(frozen=True, kw_only=True, slots=True)
class TrackSystem:
    """The DLT equations of every observation of some tracks (the model's poses):
    a track's point from any subset of its observations without recomputing."""

    rows: FloatArray  # (O, 2, 4) unit rows of each observation (zero: not posed)
    depth_row: FloatArray  # (O, 4) the point's depth in the observation's camera
    posed: BoolArray  # (O,) the observation's image has a pose
    normal: FloatArray  # (T, 4, 4) sum of rows^T rows over each track's posed obs.


def track_system(rec: pycolmap.Reconstruction, tracks: KeypointTracks) -> TrackSystem:
    """The DLT equations of ``tracks``' observations with ``rec``'s poses."""
    rows = np.zeros((len(tracks.track), 2, 4))
    depth_row = np.zeros((len(tracks.track), 4))
    posed = observed_in_posed_images(rec, tracks)
    for image_id in np.unique(tracks.image_id[posed]):  # loop over images
        sel = tracks.image_id == image_id
        image = rec.image(int(image_id))
        T = image.cam_from_world().matrix()
        uv = np.asarray(rec.camera(image.camera_id).cam_from_img(tracks.xy_img[sel]))
        rows[sel, 0] = uv[:, :1] * T[2] - T[0]
        rows[sel, 1] = uv[:, 1:2] * T[2] - T[1]
        depth_row[sel] = T[2]
    rows[posed] /= np.linalg.norm(rows[posed], axis=2, keepdims=True)
    normal = np.zeros((tracks.num_tracks, 4, 4))
    np.add.at(normal, tracks.track, np.einsum("oki,okj->oij", rows, rows))
    return TrackSystem(rows=rows, depth_row=depth_row, posed=posed, normal=normal)


def solve_tracks(
    system: TrackSystem, tracks: KeypointTracks, leave_out: BoolArray | None = None
) -> tuple[FloatArray, IndexArray]:
    """DLT point (T, 3) of each track and its view count (T,), from its posed
    observations except those in ``leave_out`` (O,). A point behind any of its
    cameras (or at infinity) is NaN."""
    use = system.posed if leave_out is None else system.posed & ~leave_out
    normal = system.normal
    if leave_out is not None and (system.posed & leave_out).any():
        out = system.posed & leave_out
        normal = normal.copy()
        np.subtract.at(
            normal,
            tracks.track[out],
            np.einsum("oki,okj->oij", system.rows[out], system.rows[out]),
        )
    _, vecs = np.linalg.eigh(normal)
    X = vecs[:, :, 0]
    w = np.where(np.abs(X[:, 3]) > 1e-12, X[:, 3], np.nan)
    X = X / w[:, None]
    behind = np.zeros(len(X), dtype=bool)
    np.logical_or.at(
        behind,
        tracks.track[use],
        np.einsum("oi,oi->o", system.depth_row[use], X[tracks.track[use]]) <= 0,
    )
    X[behind] = np.nan
    counts = np.bincount(tracks.track[use], minlength=len(X))
    return X[:, :3], counts


def triangulate_tracks(
    rec: pycolmap.Reconstruction, tracks: KeypointTracks
) -> tuple[FloatArray, IndexArray]:
    """DLT point (T, 3) of each track (the model's poses) and its view count (T,).

    A point behind any of its cameras (or at infinity) is NaN. Observations in
    images without a pose (left out by a camera check) do not count.
    """
    return solve_tracks(track_system(rec, tracks), tracks)


def observed_in_posed_images(
    rec: pycolmap.Reconstruction, tracks: KeypointTracks
) -> BoolArray:
    """(O,) whether each observation's image is in ``rec`` with a pose."""
    ids = np.unique(tracks.image_id)
    ok = np.array(
        [int(i) in rec.images and rec.image(int(i)).has_pose for i in ids], dtype=bool
    )
    return ok[np.searchsorted(ids, tracks.image_id)]


def loss_scale_px(
    rec: pycolmap.Reconstruction, scale_px: float | None, frac: float
) -> float:
    """``scale_px`` when given, else ``frac`` of the median larger image side of the
    model's cameras (the keypoints' error follows the image's resolution)."""
    if scale_px is not None:
        return float(scale_px)
    sides = [max(c.width, c.height) for c in rec.cameras.values()] or [1920]
    return frac * float(np.median(sides))


def subset(tracks: KeypointTracks, keep: np.ndarray) -> KeypointTracks:
    return KeypointTracks(
        track=tracks.track[keep],
        image_id=tracks.image_id[keep],
        point2D_idx=tracks.point2D_idx[keep],
        xy_img=tracks.xy_img[keep],
        keys=tracks.keys,
    )


def relabelled(
    tracks: KeypointTracks,
    image_id: int,
    partner: IndexArray,
    identity: int | None = None,
) -> KeypointTracks:
    """``tracks`` with image ``image_id``'s keypoints (of person ``identity`` only,
    when given) moved to their left/right counterparts' tracks (those without one
    are dropped)."""
    track = tracks.track.copy()
    mine = tracks.image_id == image_id
    if identity is not None:
        assert tracks.keys is not None
        mine &= tracks.keys[tracks.track, 0] == identity
    track[mine] = partner[track[mine]]
    keep = track >= 0
    order = np.argsort(track[keep], kind="stable")
    return KeypointTracks(
        track=track[keep][order],
        image_id=tracks.image_id[keep][order],
        point2D_idx=tracks.point2D_idx[keep][order],
        xy_img=tracks.xy_img[keep][order],
        keys=tracks.keys,
    )


def keypoint_observations(tracks: KeypointTracks) -> set[tuple[int, int]]:
    return set(zip(tracks.image_id.tolist(), tracks.point2D_idx.tolist(), strict=True))


def delete_points_observing(
    rec: pycolmap.Reconstruction, observations: set[tuple[int, int]]
) -> None:
    """Delete every 3D point with an observation in ``observations``."""
    stale = [
        point_id
        for point_id, point in rec.points3D.items()  # loop over the model's points
        if any(
            (e.image_id, e.point2D_idx) in observations for e in point.track.elements
        )
    ]
    for point_id in stale:  # deleting while iterating over points3D crashes pycolmap
        rec.delete_point3D(point_id)


def add_keypoint_points(
    rec: pycolmap.Reconstruction, tracks: KeypointTracks, min_track_length: int
) -> tuple[np.ndarray, IndexArray]:
    """Triangulate the tracks with the model's poses and add those seen often
    enough; returns (added per track, views per track)."""
    X, counts = triangulate_tracks(rec, tracks)
    good = (counts >= min_track_length) & np.isfinite(X).all(axis=1)
    posed = observed_in_posed_images(rec, tracks)
    starts = np.searchsorted(tracks.track, np.arange(tracks.num_tracks))
    ends = np.r_[starts[1:], len(tracks.track)]
    for t in np.flatnonzero(good):  # loop over tracks: pycolmap's API adds one point
        track = pycolmap.Track()
        for o in range(starts[t], ends[t]):
            if posed[o]:
                track.add_element(int(tracks.image_id[o]), int(tracks.point2D_idx[o]))
        rec.add_point3D(X[t], track)
    return good, counts


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


def track_residuals(rec: pycolmap.Reconstruction, tracks: KeypointTracks) -> FloatArray:
    """(O,) reprojection error of each observation, pixels, against the point all
    its track's views triangulate with the model's poses (inf: behind the camera;
    NaN: an unposed image, a point seen once or none)."""
    X, counts = triangulate_tracks(rec, tracks)
    ok = observed_in_posed_images(rec, tracks)
    ok &= (counts[tracks.track] >= 2) & np.isfinite(X[tracks.track]).all(axis=1)
    err = np.full(len(tracks.track), np.nan)
    for image_id in np.unique(tracks.image_id[ok]):  # loop over images
        sel = ok & (tracks.image_id == image_id)
        image = rec.image(int(image_id))
        err[sel] = residuals_px(
            rec.camera(image.camera_id),
            image.cam_from_world().matrix(),
            tracks.xy_img[sel],
            X[tracks.track[sel]],
        )
    return err
