"""Pixel rays through COLMAP cameras and their intersections with triangle meshes.

Rays come from ``pycolmap.Camera.cam_from_img`` so every COLMAP camera model,
distortion included, is handled by COLMAP itself. Intersections use Embree (through
``embreex``) in one call per depth layer: the multi-hit loop iterates over layers
(entry, exit, re-entry, ...), never over rays. Embree works in float32; every hit is
then re-intersected in float64 against its triangle (Moller-Trumbore), so hit points
lie on the mesh and reproject to their pixels to ~1e-9 px.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pycolmap

from .structs import BoolArray, FloatArray, IndexArray, _check_shape

logger = logging.getLogger(__name__)

_EMBREE_WARNED = False


@dataclass(frozen=True, kw_only=True, slots=True)
class RaycastOptions:
    """Options of the ray caster."""

    max_hits: int = 8
    """Maximum number of surface hits recorded per ray (entry, exit, ...)."""
    require_embree: bool = False
    """Fail instead of falling back to trimesh's pure-Python ray_triangle."""
    epsilon_m: float = 1e-4
    """Distance past a hit where the next layer's ray starts, in metres (above
    Embree's float32 resolution at scene scale, below any body thickness)."""


@dataclass(frozen=True, kw_only=True, slots=True)
class RayHits:
    """All surface hits of a bundle of rays on one scene.

    ``ray_idx`` is sorted, and the hits of one ray are ordered by ``depth``.
    """

    ray_idx: IndexArray  # (H,) int64, the ray of each hit
    geom_idx: IndexArray  # (H,) int64, the mesh of the scene that was hit
    face_idx: IndexArray  # (H,) int64, triangle within that mesh
    bary: FloatArray  # (H, 3) float64, barycentric coordinates in the triangle
    depth: FloatArray  # (H,) float64, distance along the (unit) ray, metres

    def __post_init__(self) -> None:
        _check_shape("ray_idx", self.ray_idx, (None,))
        h = self.ray_idx.shape[0]
        for name in ("geom_idx", "face_idx", "depth"):
            _check_shape(name, getattr(self, name), (h,))
        _check_shape("bary", self.bary, (h, 3))

    def __len__(self) -> int:
        return int(self.ray_idx.shape[0])


@dataclass(frozen=True, slots=True)
class MeshScene:
    """Triangle meshes prepared for ray queries (one Embree scene)."""

    vertices: tuple[FloatArray, ...]  # per mesh (V_i, 3) float64
    faces: tuple[IndexArray, ...]  # per mesh (F_i, 3) int64
    _engine: Any = field(repr=False)
    uses_embree: bool = True
    face_offset: IndexArray = field(init=False, repr=False)  # (M,) first row per mesh
    v0: FloatArray = field(init=False, repr=False)  # (sum F_i, 3) first vertex per face
    e1: FloatArray = field(init=False, repr=False)  # (sum F_i, 3) v1 - v0
    e2: FloatArray = field(init=False, repr=False)  # (sum F_i, 3) v2 - v0
    normal: FloatArray = field(init=False, repr=False)  # (sum F_i, 3) e1 x e2
    proj_u: FloatArray = field(init=False, repr=False)  # (sum F_i, 3) point -> u
    proj_v: FloatArray = field(init=False, repr=False)  # (sum F_i, 3) point -> v

    def __post_init__(self) -> None:
        tri = (
            np.concatenate(
                [v[f] for v, f in zip(self.vertices, self.faces, strict=True)]
            )
            if self.faces
            else np.zeros((0, 3, 3))
        )
        sizes = [len(f) for f in self.faces]
        object.__setattr__(
            self,
            "face_offset",
            np.r_[0, np.cumsum(sizes)[:-1]].astype(np.int64)
            if sizes
            else np.zeros(0, np.int64),
        )
        object.__setattr__(self, "v0", np.ascontiguousarray(tri[:, 0]))
        object.__setattr__(self, "e1", tri[:, 1] - tri[:, 0])
        object.__setattr__(self, "e2", tri[:, 2] - tri[:, 0])
        object.__setattr__(self, "normal", _cross(self.e1, self.e2))
        # (u, v) of a point P in the face's plane: G^-1 [e1; e2] (P - v0), G the Gram
        # matrix of the edges; degenerate faces get zeros.
        g11 = np.einsum("ij,ij->i", self.e1, self.e1)
        g12 = np.einsum("ij,ij->i", self.e1, self.e2)
        g22 = np.einsum("ij,ij->i", self.e2, self.e2)
        det = g11 * g22 - g12 * g12
        inv = np.where(np.abs(det) > 1e-30, 1.0 / np.where(det == 0, 1.0, det), 0.0)
        object.__setattr__(
            self,
            "proj_u",
            (g22 * inv)[:, None] * self.e1 - (g12 * inv)[:, None] * self.e2,
        )
        object.__setattr__(
            self,
            "proj_v",
            (g11 * inv)[:, None] * self.e2 - (g12 * inv)[:, None] * self.e1,
        )


def build_scene(
    meshes: list[tuple[FloatArray, IndexArray]],
    options: RaycastOptions | None = None,
) -> MeshScene:
    """Build a ray-query scene from ``(vertices (V, 3), faces (F, 3))`` pairs."""
    options = options or RaycastOptions()
    vertices = tuple(np.asarray(v, dtype=np.float64) for v, _ in meshes)
    faces = tuple(np.asarray(f, dtype=np.int64) for _, f in meshes)
    for i, (v, f) in enumerate(zip(vertices, faces, strict=True)):
        _check_shape(f"meshes[{i}] vertices", v, (None, 3))
        _check_shape(f"meshes[{i}] faces", f, (None, 3))
    try:
        from embreex import mesh_construction, rtcore_scene
    except ImportError as exc:
        if options.require_embree:
            raise RuntimeError(
                "embreex is required (RaycastOptions.require_embree) but cannot be "
                "imported: pip install embreex"
            ) from exc
        global _EMBREE_WARNED
        if not _EMBREE_WARNED:
            logger.warning("embreex not available: falling back to brute force (slow)")
            _EMBREE_WARNED = True
        return MeshScene(vertices, faces, None, uses_embree=False)
    scene = rtcore_scene.EmbreeScene()
    # Embree numbers geometries 0, 1, ... in insertion order: geomID == mesh index.
    keep = [
        mesh_construction.TriangleMesh(
            scene=scene,
            vertices=v.astype(np.float32),
            indices=f.astype(np.int32),
        )
        for v, f in zip(vertices, faces, strict=True)
    ]
    return MeshScene(vertices, faces, (scene, keep), uses_embree=True)


def _cross(a: FloatArray, b: FloatArray) -> FloatArray:
    """Row-wise cross product (N, 3); explicit, about 3x faster than np.cross."""
    out = np.zeros_like(a)
    out[:, 0] = a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1]
    out[:, 1] = a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2]
    out[:, 2] = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    return out


def _refine_hits(
    scene: MeshScene,
    origins: FloatArray,
    dirs: FloatArray,
    geom_idx: IndexArray,
    face_idx: IndexArray,
) -> tuple[FloatArray, FloatArray]:
    """Float64 Moller-Trumbore of each ray against its hit triangle -> (t, bary)."""
    # Per-face first vertex and edges of all meshes, stacked at build time.
    row = scene.face_offset[geom_idx] + face_idx
    v0, e1, e2 = scene.v0[row], scene.e1[row], scene.e2[row]
    p = _cross(dirs, e2)
    det = np.einsum("ij,ij->i", e1, p)
    # A ray exactly in the triangle's plane has det = 0: guard the division.
    det = np.where(np.abs(det) < 1e-300, 1e-300, det)
    inv_det = 1.0 / det
    s = origins - v0
    u = np.einsum("ij,ij->i", s, p) * inv_det
    q = _cross(s, e1)
    v = np.einsum("ij,ij->i", dirs, q) * inv_det
    t = np.einsum("ij,ij->i", e2, q) * inv_det
    return t, np.stack([1.0 - u - v, u, v], axis=1)


def inside_face(bary: FloatArray, hit: BoolArray) -> FloatArray:
    """Barycentrics of the hits (``hit``) clipped into their face and renormalised.

    Embree picks the face in float32; the float64 barycentrics of a ray grazing an
    edge can fall just outside it (-1e-3 was seen), which the priors format refuses
    for surface maps. The hit point moves by at most that fraction of the face.
    """
    out = bary.copy()
    inside = out[hit].clip(0.0, None)
    out[hit] = inside / inside.sum(axis=1, keepdims=True)
    return out


def _cast_once(
    scene: MeshScene, origins: FloatArray, dirs: FloatArray
) -> tuple[IndexArray, IndexArray, FloatArray, FloatArray]:
    """First hit of every ray -> (geom_idx, face_idx, t, bary); -1 / inf on a miss.

    Embree finds the face in float32; depth and barycentrics are then recomputed in
    float64 against that face's plane (precomputed normals and barycentric
    projectors), so hit points lie on the mesh and on the ray to ~1e-12 m.
    """
    if scene.uses_embree:
        # Embree wants contiguous float32; skip the copy when the caller has one.
        o32 = origins if origins.dtype == np.float32 else origins.astype(np.float32)
        d32 = dirs if dirs.dtype == np.float32 else dirs.astype(np.float32)
        out = scene._engine[0].run(o32, d32, output=1)
        face = out["primID"].astype(np.int64)
        geom = out["geomID"].astype(np.int64)
        t = np.full(len(origins), np.inf)
        bary = np.zeros((len(origins), 3))
        hit = np.flatnonzero(face >= 0)  # integer indices: one pass, then gathers
        if len(hit):
            row = scene.face_offset[geom[hit]] + face[hit]
            d_hit = dirs[hit]
            n = scene.normal[row]
            rel = scene.v0[row] - origins[hit]
            t_hit = np.einsum("ij,ij->i", n, rel) / np.einsum("ij,ij->i", n, d_hit)
            t[hit] = t_hit
            # Exact float64 barycentrics of the float64 hit point in its face.
            w = t_hit[:, None] * d_hit - rel
            u = np.einsum("ij,ij->i", scene.proj_u[row], w)
            v = np.einsum("ij,ij->i", scene.proj_v[row], w)
            bary[hit, 0] = 1.0 - u - v
            bary[hit, 1] = u
            bary[hit, 2] = v
        return geom, face, t, bary
    geom, face = _cast_brute_force(scene, origins, dirs)
    t = np.full(len(origins), np.inf)
    bary = np.zeros((len(origins), 3))
    hit_mask = face >= 0
    if hit_mask.any():
        t[hit_mask], bary[hit_mask] = _refine_hits(
            scene, origins[hit_mask], dirs[hit_mask], geom[hit_mask], face[hit_mask]
        )
    return geom, face, t, bary


def _cast_brute_force(
    scene: MeshScene, origins: FloatArray, dirs: FloatArray, chunk: int = 4_000_000
) -> tuple[IndexArray, IndexArray]:
    """Exact first hits without Embree: Moller-Trumbore of ray chunks x all faces."""
    tri = np.concatenate(
        [v[f] for v, f in zip(scene.vertices, scene.faces, strict=True)]
    )
    geom_of = np.concatenate(
        [np.full(len(f), g) for g, f in enumerate(scene.faces)]
    ).astype(np.int64)
    face_of = np.concatenate([np.arange(len(f)) for f in scene.faces]).astype(np.int64)
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    geom = np.full(len(origins), -1, dtype=np.int64)
    face = np.full(len(origins), -1, dtype=np.int64)
    step = max(1, chunk // max(1, len(tri)))
    for s0 in range(0, len(origins), step):  # loop over chunks of rays, not rays
        o, d = origins[s0 : s0 + step, None], dirs[s0 : s0 + step, None]
        p = np.cross(d, e2)
        det = np.einsum("rfk,fk->rf", p, e1)
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / det
            s = o - tri[:, 0]
            u = np.einsum("rfk,rfk->rf", s, p) * inv
            q = np.cross(s, e1)
            v = np.einsum("rfk,rfk->rf", np.broadcast_to(d, q.shape), q) * inv
            t = np.einsum("fk,rfk->rf", e2, q) * inv
            ok = (np.abs(det) > 1e-12) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
        t = np.where(ok, t, np.inf)
        best = np.argmin(t, axis=1)
        has = np.isfinite(t[np.arange(len(t)), best])
        geom[s0 : s0 + step][has] = geom_of[best[has]]
        face[s0 : s0 + step][has] = face_of[best[has]]
    return geom, face


def first_hits(
    scene: MeshScene, origins: FloatArray, dirs: FloatArray
) -> tuple[IndexArray, IndexArray, FloatArray, FloatArray]:
    """First hit of each ray.

    Args:
        scene: meshes to intersect.
        origins: (N, 3) float64 ray origins.
        dirs: (N, 3) float64 unit ray directions.

    Returns:
        geom_idx (N,) int64 and face_idx (N,) int64 (-1 on a miss), depth (N,)
        float64 (inf on a miss) and bary (N, 3) float64 (zeros on a miss).
    """
    _check_shape("origins", origins, (None, 3))
    _check_shape("dirs", dirs, (len(origins), 3))
    return _cast_once(scene, origins, dirs)


def all_hits(
    scene: MeshScene,
    origins: FloatArray,
    dirs: FloatArray,
    options: RaycastOptions | None = None,
) -> RayHits:
    """Every hit of every ray, up to ``options.max_hits`` per ray, sorted by depth.

    Args:
        scene: meshes to intersect.
        origins: (N, 3) float64 ray origins.
        dirs: (N, 3) float64 unit ray directions.
        options: ray-casting options.
    """
    options = options or RaycastOptions()
    _check_shape("origins", origins, (None, 3))
    _check_shape("dirs", dirs, (len(origins), 3))
    active = np.arange(len(origins))
    start = np.zeros(len(origins))  # distance already travelled along each ray
    chunks: list[tuple[IndexArray, ...]] = []
    depths: list[FloatArray] = []
    barys: list[FloatArray] = []
    for _ in range(options.max_hits):
        if len(active) == 0:
            break
        o = origins[active] + start[active, None] * dirs[active]
        geom, face, t_o, bary = _cast_once(scene, o, dirs[active])
        hit = face >= 0
        if not hit.any():
            break
        ray = active[hit]
        # Depth from the true origin (the cast started `start` further along).
        t, bary = t_o[hit] + start[ray], bary[hit]
        # A float32 re-hit of the surface just left does not advance: skip it, and
        # step that ray further instead of recording the hit twice.
        adv = t > start[ray]
        chunks.append((ray[adv], geom[hit][adv], face[hit][adv]))
        depths.append(t[adv])
        barys.append(bary[adv])
        start[ray[adv]] = t[adv] + options.epsilon_m
        start[ray[~adv]] += options.epsilon_m
        active = ray
    if not chunks:
        return RayHits(
            ray_idx=np.zeros(0, dtype=np.int64),
            geom_idx=np.zeros(0, dtype=np.int64),
            face_idx=np.zeros(0, dtype=np.int64),
            bary=np.zeros((0, 3)),
            depth=np.zeros(0),
        )
    ray_idx = np.concatenate([c[0] for c in chunks])
    depth = np.concatenate(depths)
    order = np.lexsort((depth, ray_idx))
    return RayHits(
        ray_idx=ray_idx[order],
        geom_idx=np.concatenate([c[1] for c in chunks])[order],
        face_idx=np.concatenate([c[2] for c in chunks])[order],
        bary=np.concatenate(barys)[order],
        depth=depth[order],
    )


def rays_cam(camera: pycolmap.Camera, xy_img: FloatArray) -> FloatArray:
    """Unit ray directions (N, 3) in the camera frame of pixels ``xy_img`` (N, 2)."""
    _check_shape("xy_img", xy_img, (None, 2))
    if len(xy_img) == 0:
        return np.zeros((0, 3))
    xy = camera.cam_from_img(np.asarray(xy_img, dtype=np.float64))
    # An (N, 2) array takes the batch overload, which never returns None (the stub's
    # single-point overload, listed first, is the one that may).
    assert xy is not None
    d = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def rays_world(
    camera: pycolmap.Camera, cam_from_world: FloatArray, xy_img: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Origins and unit directions (N, 3) in world of pixels ``xy_img`` (N, 2)."""
    R, t = cam_from_world[:, :3], cam_from_world[:, 3]
    dirs = rays_cam(camera, xy_img) @ R  # R^T d, row-wise
    centre = -R.T @ t
    return np.broadcast_to(centre, dirs.shape).copy(), dirs


def project(
    camera: pycolmap.Camera, cam_from_world: FloatArray, points_world: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Project world points -> (xy_img (N, 2), depth z (N,)); NaN behind the camera."""
    _check_shape("points_world", points_world, (None, 3))
    p_cam = points_world @ cam_from_world[:, :3].T + cam_from_world[:, 3]
    xy = np.full((len(p_cam), 2), np.nan)
    front = p_cam[:, 2] > 1e-9
    if front.any():
        xy[front] = camera.img_from_cam(p_cam[front], check_cheirality=False)
    return xy, p_cam[:, 2]


def pixel_grid(width: int, height: int, step: int = 1) -> FloatArray:
    """Pixel centres (COLMAP convention, +0.5) of a ``step``-strided grid, row-major."""
    xs = np.arange(0, width, step) + 0.5
    ys = np.arange(0, height, step) + 0.5
    gx, gy = np.meshgrid(xs, ys)
    return np.stack([gx.ravel(), gy.ravel()], axis=1)


def surface_points(
    vertices: FloatArray, faces: IndexArray, face_idx: IndexArray, bary: FloatArray
) -> FloatArray:
    """Points (N, 3) at barycentric ``bary`` (N, 3) of triangles ``face_idx`` (N,)."""
    return np.einsum("nk,nkd->nd", bary, vertices[faces[face_idx]])
