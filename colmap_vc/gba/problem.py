"""GBA inputs: options, the problem arrays, and building them from a reconstruction.

A :class:`GbaProblem` is plain arrays: registered images (cameras, poses), classic 3D
points with their observations, and VC tuples (two images, two pixels, initial X1/X2
in world, and the human prior's depths and thickness). It is built by
:func:`build_problem` from a ``pycolmap.Reconstruction`` plus the VCs that ``augment``
wrote (:func:`vc_tuples_from_db` reads them back). The model is in docs/gba.md.
"""

from __future__ import annotations

import copy
import enum
import logging
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from os import PathLike
from typing import Any

import numpy as np
import pycolmap

from ..structs import BoolArray, FloatArray, IndexArray, PairVcMatches, VcKeypoints
from .camera import intrinsics_table

logger = logging.getLogger(__name__)

_INVALID_POINT3D_ID = 2**64 - 1  # pycolmap's kInvalidPoint3DId


class Parametrization(enum.StrEnum):
    """How the coplanarity of a VC tuple's two rays enters the problem."""

    HARD = "hard"  # variables X1, a, b; X2 = X1 + a (X1 - o1) + b (o2 - o1)
    SOFT = "soft"  # variables X1, X2; a weighted coplanarity residual


class LossType(enum.StrEnum):
    """Robust loss on reprojection (and prior) residual blocks."""

    HUBER = "huber"
    CAUCHY = "cauchy"
    LINEAR = "linear"


class Solver(enum.StrEnum):
    """Nonlinear least-squares solver."""

    LM = "lm"  # own Levenberg-Marquardt, Schur complement on the cameras
    SCIPY = "scipy"  # scipy.optimize.least_squares(method="trf"), sparse Jacobian


@dataclass(frozen=True, kw_only=True, slots=True)
class GbaOptions:
    """Options of the generalized bundle adjustment."""

    parametrization: Parametrization = Parametrization.HARD
    """Hard (X2 derived, coplanarity exact) or soft (coplanarity penalised)."""
    loss: LossType = LossType.CAUCHY
    """Robust loss on each 2D reprojection residual (and each prior block)."""
    loss_scale_px: float = 2.0
    """Scale of the robust loss, pixels (the prior blocks use the same number)."""
    coplanarity_weight: float = 1.0
    """Soft only: weight of the coplanarity residual, which is the angle of ray 2 to
    the plane (o1, X1, o2) times the focal length (about pixels). Stiffer weights
    converge worse (docs/gba.md)."""
    metric_prior_weight: float = 0.0
    """Weight of the human-prior terms (relative depth of X1 and X2, relative
    X2 - X1 displacement): 10 makes a 10% error cost like 1 px. 0 turns them off;
    on, they fix the metric scale and only the first pose is held."""
    max_iterations: int = 50
    """Maximum solver iterations (LM: step attempts, as Ceres counts them)."""
    refine_classic_points: bool = True
    """Refine classic 3D points (off: they are constant and define the frame)."""
    solver: Solver = Solver.LM
    """Own sparse LM with Schur complement (fast) or scipy's trf (reference)."""
    function_tolerance: float = 1e-6
    """Stop when a successful step changes the cost by less than this, relatively."""
    gradient_tolerance: float = 1e-10
    """Stop when the max-norm of the gradient falls below this."""
    parameter_tolerance: float = 1e-8
    """Stop when the step is smaller than this times (|x| + this)."""
    gauge_image_idx: int = 0
    """Image (row of the problem) whose pose is held fixed."""
    initial_damping: float = 1e-4
    """Initial LM damping (the inverse of Ceres' initial trust-region radius)."""


def _empty(*shape: int, dtype: type = np.float64) -> np.ndarray:
    return np.zeros((0, *shape), dtype=dtype)


def _check(name: str, array: np.ndarray, shape: tuple[int | None, ...]) -> None:
    ok = array.ndim == len(shape) and all(
        want is None or have == want
        for have, want in zip(array.shape, shape, strict=True)
    )
    if not ok:
        raise ValueError(f"GbaProblem.{name} has shape {array.shape}, expected {shape}")


@dataclass(frozen=True, kw_only=True, slots=True)
class GbaProblem:
    """All inputs of one GBA run (images are rows 0..N-1, world frame of the poses).

    Prior fields are in metres in the cameras' frames; ``vc_prior_depth1 <= 0``
    marks a tuple without a usable prior.
    """

    image_ids: IndexArray  # (N,) int64, COLMAP image ids
    image_names: tuple[str, ...]  # (N,)
    cameras: tuple[pycolmap.Camera, ...]  # (N,) intrinsics of each image (fixed)
    cam_from_world: FloatArray  # (N, 3, 4) float64 initial poses
    point3D_ids: IndexArray = field(default_factory=lambda: _empty(dtype=np.int64))
    """(P,) int64 COLMAP ids of the classic points (-1: none)."""
    points_world: FloatArray = field(default_factory=lambda: _empty(3))  # (P, 3)
    obs_image_idx: IndexArray = field(default_factory=lambda: _empty(dtype=np.int64))
    obs_point_idx: IndexArray = field(default_factory=lambda: _empty(dtype=np.int64))
    obs_xy: FloatArray = field(default_factory=lambda: _empty(2))  # (O, 2) pixels
    vc_image_idx1: IndexArray = field(default_factory=lambda: _empty(dtype=np.int64))
    vc_image_idx2: IndexArray = field(default_factory=lambda: _empty(dtype=np.int64))
    vc_xy1: FloatArray = field(default_factory=lambda: _empty(2))  # (T, 2) pixels
    vc_xy2: FloatArray = field(default_factory=lambda: _empty(2))  # (T, 2) pixels
    vc_x1_world: FloatArray = field(default_factory=lambda: _empty(3))  # (T, 3) init
    vc_x2_world: FloatArray = field(default_factory=lambda: _empty(3))  # (T, 3) init
    vc_prior_depth1: FloatArray = field(default_factory=lambda: _empty())  # (T,) m
    vc_prior_depth2: FloatArray = field(default_factory=lambda: _empty())  # (T,) m
    vc_prior_a: FloatArray = field(default_factory=lambda: _empty())  # (T,)
    vc_prior_b: FloatArray = field(default_factory=lambda: _empty())  # (T,)
    vc_kind: IndexArray = field(default_factory=lambda: _empty(dtype=np.int64))
    """(T,) int64 HitKind values."""
    vc_point3D_id1: IndexArray = field(default_factory=lambda: _empty(dtype=np.int64))
    """(T,) int64 COLMAP 3D point of the VC keypoint in image 1 (-1: none)."""
    vc_point3D_id2: IndexArray = field(default_factory=lambda: _empty(dtype=np.int64))

    def __post_init__(self) -> None:
        n = len(self.image_ids)
        if n == 0:
            raise ValueError("GbaProblem needs at least one image")
        _check("image_ids", self.image_ids, (n,))
        if len(self.image_names) != n or len(self.cameras) != n:
            raise ValueError(
                f"GbaProblem has {n} image ids, {len(self.image_names)} names and "
                f"{len(self.cameras)} cameras"
            )
        _check("cam_from_world", self.cam_from_world, (n, 3, 4))
        p = len(self.points_world)
        _check("points_world", self.points_world, (p, 3))
        _check("point3D_ids", self.point3D_ids, (p,))
        o = len(self.obs_image_idx)
        _check("obs_image_idx", self.obs_image_idx, (o,))
        _check("obs_point_idx", self.obs_point_idx, (o,))
        _check("obs_xy", self.obs_xy, (o, 2))
        t = len(self.vc_image_idx1)
        for name in (
            "vc_image_idx2",
            "vc_prior_depth1",
            "vc_prior_depth2",
            "vc_prior_a",
            "vc_prior_b",
            "vc_kind",
            "vc_point3D_id1",
            "vc_point3D_id2",
        ):
            _check(name, getattr(self, name), (t,))
        for name in ("vc_xy1", "vc_xy2"):
            _check(name, getattr(self, name), (t, 2))
        for name in ("vc_x1_world", "vc_x2_world"):
            _check(name, getattr(self, name), (t, 3))
        for name, idx, size in (
            ("obs_image_idx", self.obs_image_idx, n),
            ("obs_point_idx", self.obs_point_idx, p),
            ("vc_image_idx1", self.vc_image_idx1, n),
            ("vc_image_idx2", self.vc_image_idx2, n),
        ):
            if len(idx) and (idx.min() < 0 or idx.max() >= size):
                raise ValueError(
                    f"GbaProblem.{name} has values in [{idx.min()}, {idx.max()}], "
                    f"outside [0, {size})"
                )
        if t and (self.vc_image_idx1 == self.vc_image_idx2).any():
            bad = int(np.argmax(self.vc_image_idx1 == self.vc_image_idx2))
            raise ValueError(
                f"VC tuple {bad} links image {self.vc_image_idx1[bad]} to itself"
            )
        for name in (
            "cam_from_world",
            "points_world",
            "obs_xy",
            "vc_xy1",
            "vc_xy2",
            "vc_x1_world",
            "vc_x2_world",
        ):
            if not np.isfinite(getattr(self, name)).all():
                raise ValueError(f"GbaProblem.{name} has non-finite values")
        intrinsics_table(self.cameras)  # NotImplementedError for unsupported models

    @property
    def num_images(self) -> int:
        return len(self.image_ids)

    @property
    def num_points(self) -> int:
        return len(self.points_world)

    @property
    def num_observations(self) -> int:
        return len(self.obs_image_idx)

    @property
    def num_vcs(self) -> int:
        return len(self.vc_image_idx1)

    @property
    def vc_has_prior(self) -> BoolArray:
        """(T,) bool: the tuple has positive finite prior depths."""
        d1, d2 = self.vc_prior_depth1, self.vc_prior_depth2
        ok = np.isfinite(d1) & np.isfinite(d2) & (d1 > 0) & (d2 > 0)
        return ok & np.isfinite(self.vc_prior_a) & np.isfinite(self.vc_prior_b)


# ---------------------------------------------------------------- building


def rays_world(
    cameras: Sequence[pycolmap.Camera],
    cam_from_world: FloatArray,
    image_idx: IndexArray,
    xy: FloatArray,
) -> tuple[FloatArray, FloatArray]:
    """Camera centres and unit ray directions (M, 3) in world of pixels (M, 2)."""
    dirs = np.zeros((len(xy), 3))
    for i in np.unique(image_idx):  # one unprojection call per image
        sel = image_idx == i
        dirs[sel, :2] = cameras[i].cam_from_img(np.ascontiguousarray(xy[sel]))
    dirs[:, 2] = 1.0
    R, t = cam_from_world[image_idx, :, :3], cam_from_world[image_idx, :, 3]
    centres = -np.einsum("mji,mj->mi", R, t)
    dirs = np.einsum("mji,mj->mi", R, dirs)
    return centres, dirs / np.linalg.norm(dirs, axis=1, keepdims=True)


def _ray_parameters(
    o1: FloatArray, d1: FloatArray, o2: FloatArray, d2: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Distances along two rays of their closest points (NaN for parallel rays)."""
    w = o1 - o2
    b = np.einsum("mi,mi->m", d1, d2)
    d, e = np.einsum("mi,mi->m", d1, w), np.einsum("mi,mi->m", d2, w)
    den = 1.0 - b * b
    ok = den > 1e-12
    den = np.where(ok, den, 1.0)
    s = np.where(ok, (b * e - d) / den, np.nan)
    t = np.where(ok, (e - b * d) / den, np.nan)
    return s, t


def _image_points2d(image: pycolmap.Image) -> tuple[FloatArray, IndexArray]:
    """(K, 2) xy and (K,) point3D ids (-1: none) of an image's points2D."""
    pts = image.points2D
    if len(pts) == 0:
        return np.zeros((0, 2)), np.zeros(0, np.int64)
    xy = np.array([p.xy for p in pts], dtype=np.float64)
    ids = np.array([p.point3D_id for p in pts], dtype=np.uint64)
    return xy, np.where(ids == _INVALID_POINT3D_ID, -1, ids.astype(np.int64))


def build_problem(
    rec: pycolmap.Reconstruction,
    vc_keypoints: Sequence[VcKeypoints],
    vc_pairs: Sequence[PairVcMatches],
    image_id_to_num_classic: Mapping[int, int] | None = None,
    inliers_only: bool = True,
    max_vcs_per_pair: int | None = None,
) -> GbaProblem:
    """The GBA problem of a reconstruction and its VCs (the input is not modified).

    Args:
        rec: registered images (their poses and cameras) and classic 3D points.
        vc_keypoints: VC keypoints per image (as ``augment`` wrote them).
        vc_pairs: VC tuples per image pair; keypoint indices relative to the VC block.
        image_id_to_num_classic: classic keypoints per image: VC keypoint k of image
            i is the reconstruction's point2D ``num_classic[i] + k``. When None, it
            is inferred from the images' points2D (VCs appended at the end) or the
            VC keypoints are taken as absent from the reconstruction.
        inliers_only: keep only the tuples that passed geometric verification.
        max_vcs_per_pair: keep at most this many tuples per pair, evenly spaced.

    Initial X1 is the reconstruction's 3D point of the VC keypoint (or of its partner)
    when COLMAP triangulated it, else the midpoint of the two rays, moved onto ray 1;
    X2 is the closest point of ray 2, so a, b start consistent with the current poses.
    Tuples whose rays do not meet in front of both cameras start at the median depth.
    """
    image_ids = [i for i in sorted(rec.reg_image_ids()) if rec.images[i].has_pose]
    if not image_ids:
        raise ValueError("the reconstruction has no registered image")
    row_of = {image_id: k for k, image_id in enumerate(image_ids)}
    images = [rec.images[i] for i in image_ids]
    cameras = tuple(copy.copy(rec.cameras[im.camera_id]) for im in images)
    cam_from_world = np.stack([im.cam_from_world().matrix() for im in images])
    kp_of = {kp.image_id: kp for kp in vc_keypoints}

    # Per image: points2D xy/ids and the number of classic keypoints.
    xy2d, ids2d, num_classic = [], [], []
    for image_id, image in zip(image_ids, images, strict=True):
        xy, ids = _image_points2d(image)
        num_vc = len(kp_of[image_id]) if image_id in kp_of else 0
        if image_id_to_num_classic is not None and image_id in image_id_to_num_classic:
            n_classic = int(image_id_to_num_classic[image_id])
        elif (
            num_vc
            and len(xy) >= num_vc
            and np.allclose(xy[len(xy) - num_vc :], kp_of[image_id].xy_img, atol=1e-2)
        ):
            n_classic = len(xy) - num_vc  # VC keypoints appended after the classic ones
        else:
            n_classic = len(xy)
        xy2d.append(xy)
        ids2d.append(ids)
        num_classic.append(min(n_classic, len(xy)))

    # Classic observations: points2D below num_classic with a 3D point.
    obs_img, obs_pid, obs_xy = [], [], []
    for k, (xy, ids, n) in enumerate(zip(xy2d, ids2d, num_classic, strict=True)):
        sel = np.nonzero(ids[:n] >= 0)[0]
        obs_img.append(np.full(len(sel), k, np.int64))
        obs_pid.append(ids[sel])
        obs_xy.append(xy[sel])
    obs_img_a = np.concatenate(obs_img)
    obs_pid_a = np.concatenate(obs_pid)
    obs_xy_a = np.concatenate(obs_xy).reshape(-1, 2)
    point_ids, obs_point, counts = np.unique(
        obs_pid_a, return_inverse=True, return_counts=True
    )
    keep_point = counts >= 2  # a point seen once constrains nothing
    keep_obs = keep_point[obs_point]
    point_ids = point_ids[keep_point]
    obs_point = np.cumsum(keep_point)[obs_point[keep_obs]] - 1
    obs_img_a, obs_xy_a = obs_img_a[keep_obs], obs_xy_a[keep_obs]

    # VC tuples of pairs whose two images are registered.
    cols: dict[str, list[np.ndarray]] = {
        k: []
        for k in ("i1", "i2", "xy1", "xy2", "z1", "z2", "a", "b", "kind", "p1", "p2")
    }
    for pair in vc_pairs:
        if pair.image_id1 not in row_of or pair.image_id2 not in row_of:
            continue
        if pair.image_id1 not in kp_of or pair.image_id2 not in kp_of:
            raise ValueError(
                f"pair ({pair.image_id1}, {pair.image_id2}) has VCs but no VC keypoints"
            )
        sel = np.nonzero(pair.is_inlier)[0] if inliers_only else np.arange(len(pair))
        if max_vcs_per_pair is not None and len(sel) > max_vcs_per_pair:
            sel = sel[
                np.unique(
                    np.linspace(0, len(sel) - 1, max_vcs_per_pair)
                    .round()
                    .astype(np.int64)
                )
            ]
        k1, k2 = row_of[pair.image_id1], row_of[pair.image_id2]
        idx1, idx2 = pair.idx1[sel], pair.idx2[sel]
        kp1, kp2 = kp_of[pair.image_id1], kp_of[pair.image_id2]
        if len(sel) and (idx1.max() >= len(kp1) or idx2.max() >= len(kp2)):
            raise ValueError(
                f"pair ({pair.image_id1}, {pair.image_id2}) indexes VC keypoints "
                f"beyond {len(kp1)}/{len(kp2)}"
            )
        cols["i1"].append(np.full(len(sel), k1, np.int64))
        cols["i2"].append(np.full(len(sel), k2, np.int64))
        cols["xy1"].append(kp1.xy_img[idx1])
        cols["xy2"].append(kp2.xy_img[idx2])
        cols["z1"].append(pair.points1_cam[sel, 2])
        cols["z2"].append(pair.points2_cam[sel, 2])
        cols["a"].append(pair.a[sel])
        cols["b"].append(pair.b[sel])
        cols["kind"].append(pair.kind[sel].astype(np.int64))
        for key, row, idx in (("p1", k1, idx1), ("p2", k2, idx2)):
            abs_idx = num_classic[row] + idx
            inside = abs_idx < len(ids2d[row])
            pid = np.full(len(sel), -1, np.int64)
            pid[inside] = ids2d[row][abs_idx[inside]]
            cols[key].append(pid)
    vc: dict[str, Any] = {
        k: np.concatenate(v) if v else np.zeros((0, 2) if k.startswith("xy") else 0)
        for k, v in cols.items()
    }
    for name in ("i1", "i2", "kind", "p1", "p2"):
        vc[name] = vc[name].astype(np.int64)

    # Coordinates of every 3D point referenced (one lookup per point).
    needed = np.unique(np.concatenate([point_ids, vc["p1"], vc["p2"]]))
    needed = needed[needed >= 0]
    xyz = np.array([rec.points3D[int(p)].xyz for p in needed]).reshape(-1, 3)

    def coords(pids: IndexArray) -> tuple[FloatArray, BoolArray]:
        out, ok = np.zeros((len(pids), 3)), np.zeros(len(pids), bool)
        if len(needed):
            row = np.clip(np.searchsorted(needed, pids), 0, len(needed) - 1)
            ok = (pids >= 0) & (needed[row] == pids)
            out[ok] = xyz[row[ok]]
        return out, ok

    x1, x2 = _initial_tuples(cameras, cam_from_world, vc, coords)
    problem = GbaProblem(
        image_ids=np.asarray(image_ids, np.int64),
        image_names=tuple(im.name for im in images),
        cameras=cameras,
        cam_from_world=cam_from_world,
        point3D_ids=point_ids.astype(np.int64),
        points_world=coords(point_ids)[0],
        obs_image_idx=obs_img_a,
        obs_point_idx=obs_point.astype(np.int64),
        obs_xy=obs_xy_a,
        vc_image_idx1=vc["i1"],
        vc_image_idx2=vc["i2"],
        vc_xy1=vc["xy1"].reshape(-1, 2),
        vc_xy2=vc["xy2"].reshape(-1, 2),
        vc_x1_world=x1,
        vc_x2_world=x2,
        vc_prior_depth1=vc["z1"],
        vc_prior_depth2=vc["z2"],
        vc_prior_a=vc["a"],
        vc_prior_b=vc["b"],
        vc_kind=vc["kind"],
        vc_point3D_id1=vc["p1"],
        vc_point3D_id2=vc["p2"],
    )
    logger.info(
        "GBA problem: %d images, %d classic points (%d observations), %d VC tuples",
        problem.num_images,
        problem.num_points,
        problem.num_observations,
        problem.num_vcs,
    )
    return problem


def _initial_tuples(
    cameras: Sequence[pycolmap.Camera],
    cam_from_world: FloatArray,
    vc: Mapping[str, np.ndarray],
    coords: Callable[[IndexArray], tuple[FloatArray, BoolArray]],
) -> tuple[FloatArray, FloatArray]:
    """Initial X1 (on ray 1) and X2 (on ray 2) of every tuple, (T, 3) each."""
    num = len(vc["i1"])
    if num == 0:
        return np.zeros((0, 3)), np.zeros((0, 3))
    o1, d1 = rays_world(cameras, cam_from_world, vc["i1"], vc["xy1"])
    o2, d2 = rays_world(cameras, cam_from_world, vc["i2"], vc["xy2"])
    s, t = _ray_parameters(o1, d1, o2, d2)  # midpoint triangulation
    point = 0.5 * (o1 + s[:, None] * d1 + o2 + t[:, None] * d2)
    for key in ("p2", "p1"):  # COLMAP's point wins over the midpoint; p1 over p2
        xyz, ok = coords(vc[key])
        point[ok] = xyz[ok]
    s = np.einsum("mi,mi->m", point - o1, d1)  # distances along ray 1 and ray 2
    t = np.einsum("mi,mi->m", point - o2, d2)
    good = np.isfinite(s) & np.isfinite(t) & (s > 0) & (t > 0)
    # Rays that do not meet in front of both cameras start at a typical depth.
    typical = float(np.median(s[good])) if good.any() else 1.0
    fallback = np.maximum(np.nan_to_num(s, nan=typical), 0.0)
    s = np.where(good, s, np.where(fallback > 0.1 * typical, fallback, typical))
    x1 = o1 + s[:, None] * d1
    t = np.einsum("mi,mi->m", x1 - o2, d2)  # X2: closest point of ray 2 to X1
    t = np.where(t > 0.1 * typical, t, typical)
    x2 = o2 + t[:, None] * d2
    logger.debug(
        "GBA init: %d of %d tuples meet in front of both cameras", good.sum(), num
    )
    return x1, x2


def vc_tuples_from_db(
    db_path: str | PathLike[str],
) -> tuple[list[VcKeypoints], list[PairVcMatches], dict[int, int]]:
    """VC keypoints, tuples and classic keypoint counts per image id of a database."""
    from .. import database  # only database.py touches the database

    keypoints, pairs = database.read_virtual_correspondences(db_path)
    views = database.read_views(db_path)
    num_classic = {
        int(i): int(n)
        for i, n in zip(views.image_ids, views.num_keypoints, strict=True)
    }
    return keypoints, pairs, num_classic
