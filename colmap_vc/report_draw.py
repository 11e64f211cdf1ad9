"""The report's pair panels: two images side by side, VCs coloured by epipolar
error, classic inlier matches (the paper's Fig. 5)."""

from __future__ import annotations

import cv2
import numpy as np
import pycolmap

from colmap_vc.structs import FloatArray
from colmap_vc.verification import epipolar_line_distances, skew

CLASSIC_BGR = (255, 140, 0)  # azure: classic inlier matches (VCs use green..red)
UNKNOWN_BGR = (170, 170, 170)  # grey: VCs of a pair without any geometry
NUM_COLOR_LEVELS = 16  # error colours are quantised so dots are drawn per colour
PANEL_GAP_PX = 8  # white gap between the two images of a pair panel


def epipolar_errors_px(
    xy1: FloatArray,
    xy2: FloatArray,
    camera1: pycolmap.Camera,
    camera2: pycolmap.Camera,
    cam2_from_cam1: FloatArray,
) -> FloatArray:
    """Symmetric epipolar distance of matches under a relative pose, in pixels.

    Args:
        xy1, xy2: (N, 2) float64 pixels, COLMAP convention.
        camera1, camera2: the cameras (distortion is undone by ``cam_from_img``).
        cam2_from_cam1: (3, 4) [R | t]; the scale of t does not matter.

    Returns:
        (N,) float64: mean of the distances to the epipolar line in each image,
        converted from normalized units by each camera's mean focal length; NaN
        where undefined (pure rotation, failed undistortion).
    """
    xy1, xy2 = np.asarray(xy1, np.float64), np.asarray(xy2, np.float64)
    if xy1.shape != xy2.shape or xy1.ndim != 2 or xy1.shape[1] != 2:
        raise ValueError(f"{xy1.shape=} and {xy2.shape=} must both be (N, 2)")
    if len(xy1) == 0:
        return np.zeros(0, np.float64)
    ones = np.ones((len(xy1), 1))
    # (N, 2) overload of cam_from_img: normalized coordinates, distortion undone.
    p1 = np.hstack([np.asarray(camera1.cam_from_img(xy1), np.float64), ones])
    p2 = np.hstack([np.asarray(camera2.cam_from_img(xy2), np.float64), ones])
    E = skew(cam2_from_cam1[:, 3]) @ cam2_from_cam1[:, :3]
    d = epipolar_line_distances(p1, p2, E)
    focal = np.array([camera1.mean_focal_length(), camera2.mean_focal_length()])
    errors = np.mean(d * focal, axis=1)
    return np.where(np.isfinite(errors), errors, np.nan)


def fundamental_errors_px(
    xy1: FloatArray, xy2: FloatArray, F: FloatArray
) -> FloatArray:
    """(N,) symmetric epipolar distance in pixels under a fundamental matrix.

    ``F`` maps COLMAP-convention pixels, as COLMAP estimates it from stored keypoints.
    """
    ones = np.ones((len(xy1), 1))
    d = epipolar_line_distances(np.hstack([xy1, ones]), np.hstack([xy2, ones]), F)
    errors = np.mean(d, axis=1)
    return np.where(np.isfinite(errors), errors, np.nan)


def error_colors_bgr(errors_px: FloatArray, max_error_px: float) -> np.ndarray:
    """(N, 3) uint8 BGR: 0 px pure green, max/2 yellow, >= max pure red, NaN grey."""
    t = np.clip(np.asarray(errors_px, np.float64) / max_error_px, 0.0, 1.0)
    bgr = np.column_stack(
        [np.zeros_like(t), 255 * np.clip(2 * (1 - t), 0, 1), 255 * np.clip(2 * t, 0, 1)]
    )
    bgr[np.isnan(t)] = UNKNOWN_BGR
    return np.round(bgr).astype(np.uint8)


# ---------------------------------------------------------------- drawing


def polylines(
    image: np.ndarray, segments: np.ndarray, colors: np.ndarray, thickness: int
) -> None:
    """Draw (N, 2, 2) pixel segments (OpenCV convention) in place, one call per colour.

    A segment with equal ends is a disk of diameter ``thickness``. Colours are drawn
    in the order they first appear, so callers sort segments to put some on top.
    """
    if len(segments) == 0:
        return
    fixed = np.round(segments * 16).astype(np.int32)  # 4 fractional bits (shift=4)
    keys = colors.astype(np.int64) @ np.array([1, 256, 65536])
    _, first, inverse = np.unique(keys, return_index=True, return_inverse=True)
    for group in np.argsort(first):  # loop over <= NUM_COLOR_LEVELS + 2 colours
        color = tuple(int(c) for c in colors[first[group]])
        cv2.polylines(
            image,
            list(fixed[inverse == group]),
            False,
            color,
            thickness,
            cv2.LINE_AA,
            4,
        )


def fit_height(image: np.ndarray, height: int) -> tuple[np.ndarray, float]:
    scale = height / image.shape[0]
    width = max(1, round(image.shape[1] * scale))
    return cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA), scale


def draw_pair(
    image1: np.ndarray,
    image2: np.ndarray,
    *,
    vc_xy1: FloatArray,
    vc_xy2: FloatArray,
    vc_errors_px: FloatArray,
    vc_is_inlier: np.ndarray | None = None,
    classic_xy1: FloatArray | None = None,
    classic_xy2: FloatArray | None = None,
    height: int = 360,
    max_error_px: float = 8.0,
    max_vc_lines: int = 40,
    max_vc_dots: int = 600,
) -> np.ndarray:
    """Two BGR images side by side with their VCs and classic inlier matches.

    Each image is resized to ``height``; image 2 starts ``PANEL_GAP_PX`` right of
    image 1. Up to ``max_vc_dots`` VCs (an even spread) are dots in both images,
    coloured by epipolar error (see
    :func:`error_colors_bgr`; inliers larger and outlined, the largest errors on
    top); an evenly spread subset of ``max_vc_lines`` VCs is also joined by a line.
    Classic inlier matches are thin azure lines. Points are (N, 2) float64 pixels,
    COLMAP convention.

    Returns:
        (height, W, 3) uint8 BGR panel.
    """
    im1, s1 = fit_height(image1, height)
    im2, s2 = fit_height(image2, height)
    offset = im1.shape[1] + PANEL_GAP_PX
    panel = np.full((height, offset + im2.shape[1], 3), 255, np.uint8)
    panel[:, : im1.shape[1]] = im1
    panel[:, offset:] = im2

    def to_panel(xy1: FloatArray, xy2: FloatArray) -> tuple[FloatArray, FloatArray]:
        # COLMAP pixel edges scale exactly; OpenCV puts the first pixel centre at 0.
        return xy1 * s1 - 0.5, xy2 * s2 - 0.5 + [offset, 0.0]

    if classic_xy1 is not None and classic_xy2 is not None and len(classic_xy1):
        c1, c2 = to_panel(classic_xy1, classic_xy2)
        color = np.tile(CLASSIC_BGR, (len(c1), 1))
        polylines(panel, np.stack([c1, c2], 1), color, 1)
        polylines(panel, np.stack([np.r_[c1, c2]] * 2, 1), np.r_[color, color], 4)

    if len(vc_xy1):
        inlier = (
            np.ones(len(vc_xy1), bool)
            if vc_is_inlier is None
            else np.asarray(vc_is_inlier, bool)
        )
        errors = np.asarray(vc_errors_px, np.float64)
        # Quantise so that dots are drawn in a few colour batches; NaN sorts first.
        level = np.round(np.clip(errors / max_error_px, 0, 1) * NUM_COLOR_LEVELS)
        colors = error_colors_bgr(level / NUM_COLOR_LEVELS * max_error_px, max_error_px)
        order = np.argsort(np.nan_to_num(level, nan=-1.0), kind="stable")
        if len(order) > max_vc_dots:  # an even spread keeps the error distribution
            spread = np.unique(
                np.linspace(0, len(order) - 1, max_vc_dots).astype(np.int64)
            )
            order = spread[
                np.argsort(np.nan_to_num(level[spread], nan=-1.0), kind="stable")
            ]
        v1, v2 = to_panel(vc_xy1, vc_xy2)
        if max_vc_lines > 0:
            keep = np.unique(
                np.linspace(0, len(v1) - 1, min(max_vc_lines, len(v1))).astype(np.int64)
            )
            lines = keep[
                np.argsort(np.nan_to_num(level[keep], nan=-1.0), kind="stable")
            ]
            polylines(panel, np.stack([v1[lines], v2[lines]], 1), colors[lines], 1)
        for is_in, size in ((False, 3), (True, 4)):
            idx = order[inlier[order] == is_in]
            dots = np.r_[v1[idx], v2[idx]]
            dot_colors = np.r_[colors[idx], colors[idx]]
            if is_in:  # dark outline first, so light colours stand out on skin
                polylines(
                    panel, np.stack([dots] * 2, 1), np.zeros_like(dot_colors), size + 2
                )
            polylines(panel, np.stack([dots] * 2, 1), dot_colors, size)
    return panel
