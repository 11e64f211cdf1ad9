"""Adapters: outputs of common human networks -> the priors format (docs/adapters.md).

- Mesh recovery (HMR, SPIN, EFT, PARE, CLIFF, 4D-Humans, ...): body vertices in the
  network's frame plus a camera, weak-perspective ``pred_cam = [s, tx, ty]`` on a
  square crop or a full-perspective translation ``cam_t``, become vertices in the real
  camera frame (metres, OpenCV axes) with the known intrinsics, distortion included.
- DensePose: per-pixel (I, U, V), with a table that maps (part, u, v) to a surface
  point (face, barycentric coordinates) of the template mesh, becomes a
  :class:`~colmap_vc.structs.SurfaceMap`.
- Faces files (``.npy``, ``.npz``, ``.obj``) for the template's topology.
"""

from __future__ import annotations

import enum
import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap
from scipy.spatial import cKDTree

from colmap_vc.structs import FloatArray, IndexArray, SurfaceMap, _check_shape

logger = logging.getLogger(__name__)

NUM_DENSEPOSE_PARTS = 24


class PixelConvention(enum.StrEnum):
    """Where a network puts pixel centres."""

    OPENCV = "opencv"  # top-left pixel centre at (0, 0): most networks and detectors
    COLMAP = "colmap"  # top-left pixel centre at (0.5, 0.5)


class Axes(enum.StrEnum):
    """The axes of a network's body/camera frame."""

    OPENCV = "opencv"  # x right, y down, z forward (HMR, SPIN, EFT, CLIFF, 4D-Humans)
    OPENGL = "opengl"  # x right, y up, z backward (pyrender-style renderers)


def _to_colmap(xy: FloatArray, convention: PixelConvention) -> FloatArray:
    return xy + 0.5 if convention is PixelConvention.OPENCV else xy


def _to_opencv_axes(vertices: FloatArray, axes: Axes) -> FloatArray:
    return vertices * [1.0, -1.0, -1.0] if axes is Axes.OPENGL else vertices


def _place(
    vertices: FloatArray,
    origin_xy: FloatArray,
    px_per_m: float,
    camera: pycolmap.Camera,
) -> FloatArray:
    """Move a body so its origin (0, 0, 0) projects to ``origin_xy`` at that scale.

    The depth z = f / px_per_m (f: the camera's mean focal length) makes a metre at the
    body's depth span ``px_per_m`` pixels; the origin goes on the ray of its pixel
    (``cam_from_img`` removes the distortion).
    """
    if not (np.isfinite(px_per_m) and px_per_m > 0):
        raise ValueError(f"scale {px_per_m} px/m must be positive (s > 0, size > 0)")
    focal = float(np.mean(camera.calibration_matrix()[[0, 1], [0, 1]]))
    depth = focal / px_per_m
    ray = np.asarray(
        camera.cam_from_img(np.asarray(origin_xy, dtype=np.float64)[None])
    )[0]
    return vertices + depth * np.array([ray[0], ray[1], 1.0])


def vertices_from_weak_perspective(
    vertices: FloatArray,
    pred_cam: FloatArray,
    bbox_center_xy: FloatArray,
    bbox_size_px: float,
    camera: pycolmap.Camera,
    *,
    pixels: PixelConvention = PixelConvention.OPENCV,
    axes: Axes = Axes.OPENCV,
) -> FloatArray:
    """Vertices in the camera frame from an HMR/SPIN/EFT weak-perspective camera.

    The network projects a body point X to crop coordinates in [-1, 1]:
    ``u = s (X_x + tx)``, ``v = s (X_y + ty)``, over a square crop of
    ``bbox_size_px`` pixels centred on ``bbox_center_xy`` (SPIN: ``scale * 200``).
    So the body origin is at pixel ``center + size / 2 * s * (tx, ty)`` and a metre
    spans ``size / 2 * s`` pixels; its depth follows from the camera's focal length
    (the usual ``tz = 2 f / (size s)`` of CLIFF's ``cam_crop2full``), distortion
    included.

    Args:
        vertices: (V, 3) metres, the network's body frame (axes: ``axes``).
        pred_cam: (3,) ``[s, tx, ty]``.
        bbox_center_xy: (2,) crop centre in the full image, pixels (``pixels``).
        bbox_size_px: side of the square crop in full-image pixels.
        camera: the image's camera (COLMAP model).
        pixels: pixel convention of ``bbox_center_xy``.
        axes: axes of ``vertices``.

    Returns:
        (V, 3) float64 vertices in the camera frame, metres, OpenCV axes.
    """
    vertices = _to_opencv_axes(np.asarray(vertices, dtype=np.float64), axes)
    _check_shape("vertices", vertices, (None, 3))
    pred_cam = np.asarray(pred_cam, dtype=np.float64)
    _check_shape("pred_cam", pred_cam, (3,))
    s, tx, ty = pred_cam
    half = 0.5 * float(bbox_size_px)
    center = _to_colmap(np.asarray(bbox_center_xy, dtype=np.float64), pixels)
    _check_shape("bbox_center_xy", center, (2,))
    origin_xy = center + half * s * np.array([tx, ty])
    return _place(vertices, origin_xy, half * s, camera)


def vertices_from_cam_t(
    vertices: FloatArray,
    cam_t: FloatArray,
    camera: pycolmap.Camera | None = None,
    *,
    focal_px: float | None = None,
    principal_point_xy: FloatArray | None = None,
    pixels: PixelConvention = PixelConvention.OPENCV,
    axes: Axes = Axes.OPENCV,
) -> FloatArray:
    """Vertices in the camera frame from a full-perspective translation ``cam_t``.

    If ``cam_t`` was computed for the real camera, the result is ``vertices + cam_t``.
    Networks often assume their own pinhole (4D-Humans: a focal length of 5000 px
    scaled to the image, principal point at the centre): give it as ``focal_px`` and
    ``principal_point_xy`` and the body is moved so that its origin projects to the
    same pixel at the same scale through the real ``camera`` (distortion included).

    Returns:
        (V, 3) float64 vertices in the camera frame, metres, OpenCV axes.
    """
    vertices = _to_opencv_axes(np.asarray(vertices, dtype=np.float64), axes)
    cam_t = _to_opencv_axes(np.asarray(cam_t, dtype=np.float64), axes)
    _check_shape("vertices", vertices, (None, 3))
    _check_shape("cam_t", cam_t, (3,))
    if focal_px is None:
        return vertices + cam_t
    if camera is None or principal_point_xy is None:
        raise ValueError("focal_px needs principal_point_xy and the real camera")
    if cam_t[2] <= 0:
        raise ValueError(f"cam_t {cam_t} puts the body behind the camera (z <= 0)")
    pp = _to_colmap(np.asarray(principal_point_xy, dtype=np.float64), pixels)
    # The network's pinhole: origin pixel and pixels per metre at the origin's depth.
    origin_xy = focal_px * cam_t[:2] / cam_t[2] + pp
    return _place(vertices, origin_xy, focal_px / cam_t[2], camera)


def load_faces(path: Path) -> IndexArray:
    """(F, 3) int64 triangles from ``.npy``, ``.npz`` (key ``faces`` or ``f``, or the
    only array) or ``.obj`` (``f`` lines, 1-based, ``v/vt/vn`` and negative indices
    accepted, polygons fanned into triangles).

    Raises:
        FileNotFoundError: no such file.
        ValueError: unknown suffix, or no (F, 3) non-negative integer array inside.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"faces file {path} does not exist")
    suffix = path.suffix.lower()
    if suffix == ".npy":
        faces = np.load(path, allow_pickle=False)
    elif suffix == ".npz":
        with np.load(path, allow_pickle=False) as z:
            keys = [k for k in ("faces", "f") if k in z.files]
            if not keys and len(z.files) != 1:
                raise ValueError(f"{path}: no 'faces' array among {z.files}")
            faces = z[keys[0] if keys else z.files[0]]
    elif suffix == ".obj":
        faces = _obj_faces(path)
    else:
        raise ValueError(f"{path}: unknown faces format {suffix!r}; use .npy/.npz/.obj")
    faces = np.asarray(faces)
    if faces.ndim != 2 or faces.shape[1] != 3 or faces.dtype.kind not in "iu":
        raise ValueError(
            f"{path}: faces must be (F, 3) integers, got {faces.shape} {faces.dtype}"
        )
    if len(faces) == 0 or faces.min() < 0:
        raise ValueError(f"{path}: faces are empty or have negative indices")
    return faces.astype(np.int64)


def _obj_faces(path: Path) -> IndexArray:
    num_v = 0
    tris: list[list[int]] = []
    for line in path.read_text(encoding="utf-8", errors="replace").splitlines():
        parts = line.split()
        if not parts:
            continue
        if parts[0] == "v":
            num_v += 1
        elif parts[0] == "f":
            idx = [int(p.split("/")[0]) for p in parts[1:]]
            idx = [i - 1 if i > 0 else num_v + i for i in idx]  # 1-based or relative
            tris.extend([idx[0], idx[k], idx[k + 1]] for k in range(1, len(idx) - 1))
    return np.array(tris, dtype=np.int64).reshape(-1, 3)


@dataclass(frozen=True, slots=True)
class UvSurfaceTable:
    """Samples of a template surface with their DensePose chart coordinates.

    Row i: the surface point ``bary[i]`` of template face ``face[i]`` has chart
    coordinates (``u[i]``, ``v[i]``) on body part ``part[i]`` (1-24).
    """

    part: IndexArray  # (M,) int64, 1..24
    u: FloatArray  # (M,) float64 in [0, 1]
    v: FloatArray  # (M,) float64 in [0, 1]
    face: IndexArray  # (M,) int64, template face
    bary: FloatArray  # (M, 3) float64
    _trees: dict[int, tuple[cKDTree, IndexArray]] = field(
        default_factory=dict, repr=False, compare=False
    )

    def __post_init__(self) -> None:
        _check_shape("part", self.part, (None,))
        m = len(self.part)
        for name in ("u", "v", "face"):
            _check_shape(name, getattr(self, name), (m,))
        _check_shape("bary", self.bary, (m, 3))

    def arrays(self) -> dict[str, np.ndarray]:
        """The arrays to ``np.savez`` (read back by :func:`load_uv_table`)."""
        return {
            "part": self.part,
            "u": self.u,
            "v": self.v,
            "face": self.face,
            "bary": self.bary,
        }

    def tree(self, part: int) -> tuple[cKDTree, IndexArray] | None:
        """KD-tree over (u, v) of one part and the rows it indexes (None: no rows)."""
        if part not in self._trees:
            rows = np.flatnonzero(self.part == part)
            if len(rows) == 0:
                return None
            self._trees[part] = (
                cKDTree(np.stack([self.u[rows], self.v[rows]], 1)),
                rows,
            )
        return self._trees[part]


def load_uv_table(path: Path) -> UvSurfaceTable:
    """Read a table saved as ``.npz`` with ``part``, ``u``, ``v``, ``face``, ``bary``.

    Raises:
        FileNotFoundError: no such file.
        ValueError: missing arrays, bad shapes or values out of range.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"UV table {path} does not exist")
    with np.load(path, allow_pickle=False) as z:
        missing = {"part", "u", "v", "face", "bary"} - set(z.files)
        if missing:
            raise ValueError(f"{path}: missing array(s) {sorted(missing)}")
        try:
            table = UvSurfaceTable(
                part=z["part"].astype(np.int64).ravel(),
                u=z["u"].astype(np.float64).ravel(),
                v=z["v"].astype(np.float64).ravel(),
                face=z["face"].astype(np.int64).ravel(),
                bary=z["bary"].astype(np.float64),
            )
        except ValueError as exc:
            raise ValueError(f"{path}: {exc}") from exc
    if len(table.part) and not (
        (table.part.min() >= 1) and (table.part.max() <= NUM_DENSEPOSE_PARTS)
    ):
        raise ValueError(f"{path}: part must lie in 1..{NUM_DENSEPOSE_PARTS}")
    if len(table.part) and table.face.min() < 0:
        raise ValueError(f"{path}: face has negative indices")
    return table


def uv_table_from_uv_mesh(
    uv_faces: IndexArray,
    uv: FloatArray,
    face_part: IndexArray,
    uv_to_template_vertex: IndexArray,
    template_faces: IndexArray,
    samples_per_edge: int = 6,
) -> UvSurfaceTable:
    """Build the table from a UV-unwrapped copy of the template (DensePose's layout).

    DensePose's ``UV_Processed.mat`` is such a copy of SMPL: its vertices are SMPL
    vertices split along the chart seams (``All_vertices``, 1-based), each with
    (``All_U_norm``, ``All_V_norm``), and its faces (``All_Faces``, 1-based) carry a
    part (``All_FaceIndices``). Each UV face is matched to the template face with the
    same three vertices and sampled on a barycentric grid of ``samples_per_edge``.

    Args:
        uv_faces: (F, 3) faces of the UV mesh (0-based).
        uv: (Vu, 2) chart coordinates of the UV mesh's vertices.
        face_part: (F,) part of each UV face, 1..24.
        uv_to_template_vertex: (Vu,) template vertex of each UV-mesh vertex (0-based).
        template_faces: (Ft, 3) faces of the template mesh.
        samples_per_edge: n; a face gets (n + 1)(n + 2) / 2 samples.
    """
    uv_faces = np.asarray(uv_faces, dtype=np.int64)
    uv = np.asarray(uv, dtype=np.float64)
    template_faces = np.asarray(template_faces, dtype=np.int64)
    _check_shape("uv_faces", uv_faces, (None, 3))
    _check_shape("uv", uv, (None, 2))
    _check_shape("face_part", np.asarray(face_part), (len(uv_faces),))
    _check_shape("uv_to_template_vertex", np.asarray(uv_to_template_vertex), (len(uv),))
    corners = np.asarray(uv_to_template_vertex, dtype=np.int64)[uv_faces]  # (F, 3)
    # Match faces by their sorted vertex triplets (one integer key per face).
    base = int(max(template_faces.max(), corners.max())) + 1
    key_t = np.sort(template_faces, axis=1) @ np.array([base * base, base, 1])
    key_u = np.sort(corners, axis=1) @ np.array([base * base, base, 1])
    order = np.argsort(key_t)
    pos = np.searchsorted(key_t[order], key_u).clip(0, len(order) - 1)
    found = key_t[order][pos] == key_u
    if not found.all():
        logger.warning(
            "%d of %d UV faces match no template face: dropped",
            int((~found).sum()),
            len(found),
        )
    face_t = order[pos[found]]
    corners, uv_f = corners[found], uv_faces[found]
    # perm[f, k]: the corner of the UV face that is corner k of the template face.
    perm = np.argmax(template_faces[face_t][:, :, None] == corners[:, None, :], axis=2)
    n = samples_per_edge
    grid = np.array([(i, j, n - i - j) for i in range(n + 1) for j in range(n + 1 - i)])
    grid = grid / n  # (S, 3) barycentric samples in the UV face's corner order
    uv_pts = np.einsum("sk,fkd->fsd", grid, uv[uv_f])  # (F, S, 2)
    bary_t = grid[:, perm].transpose(1, 0, 2)  # (F, S, 3) in template corner order
    num_s = len(grid)
    return UvSurfaceTable(
        part=np.repeat(np.asarray(face_part, dtype=np.int64)[found], num_s),
        u=uv_pts[..., 0].ravel(),
        v=uv_pts[..., 1].ravel(),
        face=np.repeat(face_t, num_s),
        bary=bary_t.reshape(-1, 3),
    )


def split_iuv_image(iuv: np.ndarray) -> tuple[IndexArray, FloatArray, FloatArray]:
    """(H, W, 3) uint8 IUV image (channels I, 255 U, 255 V) -> I, U, V arrays.

    This is the layout of DensePose's ``*_IUV.png`` files read with channels in file
    order (with OpenCV, ``cv2.imread(path)[:, :, ::-1]`` if it was written as BGR).
    """
    iuv = np.asarray(iuv)
    if iuv.ndim != 3 or iuv.shape[2] != 3:
        raise ValueError(f"IUV image has shape {iuv.shape}, expected (H, W, 3)")
    return (
        iuv[..., 0].astype(np.int64),
        iuv[..., 1].astype(np.float64) / 255.0,
        iuv[..., 2].astype(np.float64) / 255.0,
    )


def surface_map_from_iuv(
    part: IndexArray,
    u: FloatArray,
    v: FloatArray,
    table: UvSurfaceTable,
    *,
    offset_xy: tuple[int, int] = (0, 0),
    stride_px: int = 1,
    max_uv_distance: float = 0.05,
) -> SurfaceMap:
    """DensePose (I, U, V) per pixel -> a SurfaceMap on the table's template.

    Each foreground pixel (I in 1..24) takes the (face, bary) of the table sample of its
    part nearest in (u, v); pixels farther than ``max_uv_distance`` from every sample
    are dropped. One KD-tree query per part, over all its pixels at once.

    Args:
        part: (H, W) int part index I, 0 = background.
        u, v: (H, W) chart coordinates in [0, 1].
        table: the template's UV table.
        offset_xy: image column and row of the arrays' top-left pixel (DensePose
            returns per-box arrays: the box's integer top-left corner).
        stride_px: keep every n-th row and column.
        max_uv_distance: rejection radius in (u, v).
    """
    part = np.asarray(part)
    u, v = np.asarray(u, dtype=np.float64), np.asarray(v, dtype=np.float64)
    if part.ndim != 2 or u.shape != part.shape or v.shape != part.shape:
        raise ValueError(
            "I, U, V must be equal (H, W) arrays, got "
            f"{part.shape}, {u.shape}, {v.shape}"
        )
    rows, cols = np.nonzero((part >= 1) & (part <= NUM_DENSEPOSE_PARTS))
    keep = (rows % stride_px == 0) & (cols % stride_px == 0)
    rows, cols = rows[keep], cols[keep]
    pix_part = part[rows, cols].astype(np.int64)
    face = np.full(len(rows), -1, dtype=np.int64)
    bary = np.zeros((len(rows), 3))
    for p in np.unique(pix_part):  # a loop over the 24 parts, not over pixels
        entry = table.tree(int(p))
        if entry is None:
            continue
        tree, table_rows = entry
        sel = np.flatnonzero(pix_part == p)
        dist, nn = tree.query(
            np.stack([u[rows[sel], cols[sel]], v[rows[sel], cols[sel]]], 1),
            distance_upper_bound=max_uv_distance,
        )
        ok = np.isfinite(dist)
        face[sel[ok]] = table.face[table_rows[nn[ok]]]
        bary[sel[ok]] = table.bary[table_rows[nn[ok]]]
    hit = face >= 0
    # Array index (row, col) -> image pixel centre, COLMAP convention (+0.5).
    xy = np.stack([cols[hit] + offset_xy[0], rows[hit] + offset_xy[1]], 1) + 0.5
    return SurfaceMap(xy_img=xy.astype(np.float64), face_idx=face[hit], bary=bary[hit])
