"""Camera models and rotations for GBA, with analytic derivatives.

Every supported COLMAP model is a special case of OPENCV, so intrinsics are stored as
one row ``[fx, fy, cx, cy, k1, k2, p1, p2]`` per image and a single vectorized code
path projects (and differentiates) all of them. The formulas follow COLMAP's
``ImgFromCam`` (src/colmap/sensor/models.h): normalise by depth, add the distortion
``(du, dv)`` of the normalised point, then scale and shift to pixels (pixel centre
convention of COLMAP, as pycolmap's ``Camera.img_from_cam``).

Rotations are ``R = exp([w]x) R0``: a rotation vector ``w`` applied on the left of a
reference rotation, differentiated exactly with the left Jacobian of SO(3), so the
Jacobian is exact at any ``w`` (needed by finite-difference tests and scipy's solver).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pycolmap

from ..structs import FloatArray

# model name -> where its parameters go in [fx, fy, cx, cy, k1, k2, p1, p2]
_OPENCV_SLOTS: dict[str, tuple[int, ...]] = {
    "SIMPLE_PINHOLE": (0, 2, 3),  # f, cx, cy (f goes to fx and fy)
    "PINHOLE": (0, 1, 2, 3),
    "SIMPLE_RADIAL": (0, 2, 3, 4),  # f, cx, cy, k
    "RADIAL": (0, 2, 3, 4, 5),  # f, cx, cy, k1, k2
    "OPENCV": (0, 1, 2, 3, 4, 5, 6, 7),
}
SUPPORTED_MODELS = tuple(_OPENCV_SLOTS)
NUM_INTRINSICS = 8


def opencv_params(camera: pycolmap.Camera) -> FloatArray:
    """(8,) float64 ``[fx, fy, cx, cy, k1, k2, p1, p2]`` equivalent to a camera.

    Raises:
        NotImplementedError: for models other than :data:`SUPPORTED_MODELS`.
    """
    name = camera.model.name
    if name not in _OPENCV_SLOTS:
        raise NotImplementedError(
            f"GBA supports the camera models {SUPPORTED_MODELS}, not {name} "
            f"(camera {camera.camera_id}): undistort the images or extend "
            "colmap_vc/gba/camera.py"
        )
    out = np.zeros(NUM_INTRINSICS)
    out[list(_OPENCV_SLOTS[name])] = camera.params
    if name in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
        out[1] = out[0]  # one focal length
    return out


def intrinsics_table(cameras: Sequence[pycolmap.Camera]) -> FloatArray:
    """(N, 8) float64 OPENCV-equivalent intrinsics of N cameras."""
    if not cameras:
        return np.zeros((0, NUM_INTRINSICS))
    return np.stack([opencv_params(c) for c in cameras])


def project(
    points_cam: FloatArray, params: FloatArray, *, with_jacobian: bool = True
) -> tuple[FloatArray, FloatArray | None]:
    """Pixels of camera-frame points and d(pixel)/d(point).

    Args:
        points_cam: (M, 3) float64 points in each camera's frame.
        params: (M, 8) float64 OPENCV-equivalent intrinsics per point.
        with_jacobian: also return the derivative.

    Returns:
        (M, 2) pixels (no cheirality check) and (M, 2, 3) d(pixel)/d(points_cam)
        (None without ``with_jacobian``).
    """
    xy, jac = project_rows(
        np.ascontiguousarray(points_cam.T),
        np.ascontiguousarray(params.T),
        with_jacobian=with_jacobian,
    )
    return xy.T, None if jac is None else jac.transpose(2, 0, 1)


def project_rows(
    points_cam: FloatArray, rows: FloatArray, *, with_jacobian: bool = True
) -> tuple[FloatArray, FloatArray | None]:
    """:func:`project` on (3, M) points and (8, M) intrinsics rows, point index last.

    Returns (2, M) pixels and the (2, 3, M) Jacobian.
    """
    fx, fy, cx, cy, k1, k2, p1, p2 = rows
    has_k2, has_tangential = bool(k2.any()), bool(p1.any() or p2.any())
    inv_z = 1.0 / points_cam[2]
    u = points_cam[0] * inv_z
    v = points_cam[1] * inv_z
    # Same operation order as COLMAP's OpenCVCameraModel::Distortion; the terms of
    # zero parameters are skipped (adding exact zeros would not change the result).
    u2, uv, v2 = u * u, u * v, v * v
    r2 = u2 + v2
    radial = k1 * r2 + k2 * r2 * r2 if has_k2 else k1 * r2
    du, dv = u * radial, v * radial
    if has_tangential:
        du = du + 2.0 * p1 * uv + p2 * (r2 + 2.0 * u2)
        dv = dv + 2.0 * p2 * uv + p1 * (r2 + 2.0 * v2)
    xy = np.stack([fx * (u + du) + cx, fy * (v + dv) + cy])
    if not with_jacobian:
        return xy, None
    dradial = (
        2.0 * (k1 + 2.0 * k2 * r2) if has_k2 else 2.0 * k1
    )  # d radial/du = u dradial
    one = 1.0 + radial
    dud_du = one + u2 * dradial
    dud_dv = uv * dradial
    dvd_du = dud_dv
    dvd_dv = one + v2 * dradial
    if has_tangential:
        dud_du = dud_du + 2.0 * p1 * v + 6.0 * p2 * u
        dud_dv = dud_dv + 2.0 * p1 * u + 2.0 * p2 * v
        dvd_du = dvd_du + 2.0 * p2 * v + 2.0 * p1 * u
        dvd_dv = dvd_dv + 2.0 * p2 * u + 6.0 * p1 * v
    # d(u, v)/d(X, Y, Z) = [[1/Z, 0, -u/Z], [0, 1/Z, -v/Z]]
    jac = np.zeros((2, 3, len(u)))
    a, b = fx * inv_z, fy * inv_z
    jac[0, 0] = a * dud_du
    jac[0, 1] = a * dud_dv
    jac[0, 2] = -a * (dud_du * u + dud_dv * v)
    jac[1, 0] = b * dvd_du
    jac[1, 1] = b * dvd_dv
    jac[1, 2] = -b * (dvd_du * u + dvd_dv * v)
    return xy, jac


def skew(w: FloatArray) -> FloatArray:
    """(..., 3, 3) cross-product matrices ``[w]x`` of (..., 3) vectors."""
    out = np.zeros((*w.shape[:-1], 3, 3))
    out[..., 0, 1], out[..., 0, 2] = -w[..., 2], w[..., 1]
    out[..., 1, 0], out[..., 1, 2] = w[..., 2], -w[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -w[..., 1], w[..., 0]
    return out


def _so3_coefficients(w: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """sin(t)/t, (1 - cos t)/t^2 and (t - sin t)/t^3 of t = |w|, Taylor near 0."""
    theta2 = np.einsum("...i,...i->...", w, w)
    theta = np.sqrt(theta2)
    small = theta < 1e-4
    safe = np.where(small, 1.0, theta)
    sinc = np.where(small, 1.0 - theta2 / 6.0, np.sin(safe) / safe)
    cosc = np.where(small, 0.5 - theta2 / 24.0, (1.0 - np.cos(safe)) / safe**2)
    sinc3 = np.where(small, 1.0 / 6.0 - theta2 / 120.0, (safe - np.sin(safe)) / safe**3)
    return sinc, cosc, sinc3


def exp_so3(w: FloatArray) -> FloatArray:
    """(N, 3, 3) rotation matrices of (N, 3) rotation vectors (Rodrigues)."""
    sinc, cosc, _ = _so3_coefficients(w)
    K = skew(w)
    return np.eye(3) + sinc[:, None, None] * K + cosc[:, None, None] * (K @ K)


def left_jacobian_so3(w: FloatArray) -> FloatArray:
    """(N, 3, 3) left Jacobians: exp([w + d]x) ~ exp([J d]x) exp([w]x)."""
    _, cosc, sinc3 = _so3_coefficients(w)
    K = skew(w)
    return np.eye(3) + cosc[:, None, None] * K + sinc3[:, None, None] * (K @ K)
