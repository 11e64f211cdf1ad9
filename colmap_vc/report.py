"""A self-contained HTML report of a colmap-vc run (the paper's Fig. 5, poses, AUC).

``build_report`` writes one HTML file with every image inlined as base64 JPEG and
no external URL, script or font, so it can be mailed or archived as is. It shows:
a summary (images, VCs, classic matches, registration, metrics per method, per-stage
timings), the camera poses (top and side views, GT aligned by a similarity, three
3D angles switched by CSS radio buttons, no JS), the cumulative pose-error curve
when GT is given, and per image pair the VCs coloured by epipolar error plus the
classic inlier matches. Sections say what is missing (no VCs, no model, no GT).

All database reads go through :mod:`colmap_vc.database`. matplotlib (the ``viz``
extra) is imported lazily, only when a figure is drawn.
"""

from __future__ import annotations

import base64
import html
import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np
import pycolmap

from colmap_vc import database
from colmap_vc.evaluation import (
    THRESHOLDS_DEG,
    Metrics,
    evaluate_reconstruction,
    relative_pose,
)
from colmap_vc.structs import FloatArray, HitKind, PairVcMatches, VcKeypoints
from colmap_vc.verification import epipolar_line_distances, skew

if TYPE_CHECKING:
    from matplotlib.figure import Figure

logger = logging.getLogger(__name__)

CLASSIC_BGR = (255, 140, 0)  # azure: classic inlier matches (VCs use green..red)
UNKNOWN_BGR = (170, 170, 170)  # grey: VCs of a pair without any geometry
NUM_COLOR_LEVELS = 16  # error colours are quantised so dots are drawn per colour
PANEL_GAP_PX = 8  # white gap between the two images of a pair panel
MAX_PLOT_POINTS = 20000  # sparse points drawn in the pose plots (strided subsample)
VIEW_ANGLES_DEG = {
    "oblique": (25.0, -60.0),
    "front": (5.0, -90.0),
    "top": (85.0, -90.0),
}


@dataclass(frozen=True, kw_only=True, slots=True)
class ReportInputs:
    """What the report shows; everything but the database and images is optional."""

    database_path: Path
    """Augmented COLMAP database (VCs + classic matches), or a plain one."""
    image_dir: Path
    """Folder of the images named in the database."""
    model_path: Path | None = None
    """Reconstructed COLMAP model folder (cameras/images/points3D .bin)."""
    gt_model_path: Path | None = None
    """Ground-truth COLMAP model folder, matched to the images by name."""
    timings_s: Mapping[str, float] | None = None
    """Seconds per pipeline stage, shown as a table with bars."""
    metrics: Mapping[str, Any] | None = None
    """Method name -> ``Metrics`` or ``Metrics.to_dict()``, shown as a table (and
    curves, for those with pairs). Without it, the model is evaluated against GT."""
    title: str = "colmap-vc report"
    max_pairs: int = 12
    """Image pairs drawn, those with the most VC (else classic) inliers first."""
    max_epipolar_error_px: float = 8.0
    """Epipolar errors at or above this are drawn pure red (0 px is pure green)."""
    max_vc_lines: int = 40
    """VCs per pair also drawn as a line between the two images."""
    max_vc_dots: int = 600
    """VCs per pair drawn as dots (an even spread; all errors are in the caption)."""
    panel_height_px: int = 360
    """Height of each image in a pair panel."""


# ---------------------------------------------------------------- geometry


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


def _similarity(
    src: FloatArray, dst: FloatArray
) -> tuple[float, FloatArray, FloatArray]:
    """Umeyama: (s, R, t) minimising |dst - (s R src + t)|, for (N, 3) points."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    U, S, Vt = np.linalg.svd(b.T @ a / len(src))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])  # no reflections
    R = U @ D @ Vt
    s = float(np.trace(np.diag(S) @ D) / max(np.mean(np.sum(a**2, 1)), 1e-300))
    return s, R, mu_d - s * R @ mu_s


# ---------------------------------------------------------------- drawing


def _polylines(
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


def _fit_height(image: np.ndarray, height: int) -> tuple[np.ndarray, float]:
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
    im1, s1 = _fit_height(image1, height)
    im2, s2 = _fit_height(image2, height)
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
        _polylines(panel, np.stack([c1, c2], 1), color, 1)
        _polylines(panel, np.stack([np.r_[c1, c2]] * 2, 1), np.r_[color, color], 4)

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
            _polylines(panel, np.stack([v1[lines], v2[lines]], 1), colors[lines], 1)
        for is_in, size in ((False, 3), (True, 4)):
            idx = order[inlier[order] == is_in]
            dots = np.r_[v1[idx], v2[idx]]
            dot_colors = np.r_[colors[idx], colors[idx]]
            if is_in:  # dark outline first, so light colours stand out on skin
                _polylines(
                    panel, np.stack([dots] * 2, 1), np.zeros_like(dot_colors), size + 2
                )
            _polylines(panel, np.stack([dots] * 2, 1), dot_colors, size)
    return panel


def _jpeg_uri(image: np.ndarray, quality: int = 92) -> str:
    """A BGR image as a JPEG data URI.

    JPEG, never PNG: once ``import pycolmap`` has loaded the system libz (its
    extension exports zlib-ng symbols that libz's own calls then bind to), any
    later deflate (PNG in OpenCV or PIL, Python's zlib) aborts the process with
    "free(): invalid pointer". JPEG needs no zlib, so the report is safe in any
    import order.
    """
    # 4:4:4 chroma: the default 4:2:0 would smear the colour of few-pixel dots.
    params = [cv2.IMWRITE_JPEG_QUALITY, quality]
    params += [cv2.IMWRITE_JPEG_SAMPLING_FACTOR, cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444]
    ok, data = cv2.imencode(".jpg", image, params)
    if not ok:
        raise RuntimeError(f"cannot encode a {image.shape} image as JPEG")
    return "data:image/jpeg;base64," + base64.b64encode(data.tobytes()).decode()


def _figure_uri(fig: Figure) -> str:
    """A figure rasterised by Agg (no PIL, no zlib: see _jpeg_uri) as a JPEG URI."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    rgba = np.asarray(canvas.buffer_rgba())
    return _jpeg_uri(cv2.cvtColor(rgba, cv2.COLOR_RGBA2BGR), quality=95)


def _new_figure(width_in: float, height_in: float) -> Figure:
    try:
        from matplotlib.figure import Figure
    except ImportError as error:  # the viz extra
        raise ImportError(
            "the report's plots need matplotlib: pip install 'colmap-vc[viz]'"
        ) from error
    # A bare Figure (no pyplot): no global state, no GUI backend.
    return Figure(figsize=(width_in, height_in), dpi=100, layout="constrained")


# ---------------------------------------------------------------- models


@dataclass(frozen=True, kw_only=True, slots=True)
class _Cameras:
    """Registered cameras of one model in some world frame."""

    names: tuple[str, ...]
    centers: FloatArray  # (N, 3)
    directions: FloatArray  # (N, 3) unit viewing directions
    image_up: FloatArray  # (N, 3) unit world direction of each image's "up"

    @classmethod
    def of(cls, rec: pycolmap.Reconstruction) -> _Cameras:
        images = sorted(
            (im for im in rec.images.values() if im.has_pose), key=lambda im: im.name
        )
        rotations = np.array([im.cam_from_world().rotation.matrix() for im in images])
        return cls(
            names=tuple(im.name for im in images),
            centers=np.array([im.projection_center() for im in images]).reshape(-1, 3),
            directions=rotations[:, 2, :].reshape(-1, 3),  # camera +z in world
            image_up=-rotations[:, 1, :].reshape(-1, 3),  # camera -y in world
        )

    def transformed(self, s: float, R: FloatArray, t: FloatArray) -> _Cameras:
        return _Cameras(
            names=self.names,
            centers=s * self.centers @ R.T + t,
            directions=self.directions @ R.T,
            image_up=self.image_up @ R.T,
        )


def _points(rec: pycolmap.Reconstruction) -> FloatArray:
    """(P, 3) sparse points, strided to at most MAX_PLOT_POINTS."""
    ids = sorted(rec.point3D_ids())
    ids = ids[:: max(1, math.ceil(len(ids) / MAX_PLOT_POINTS))]
    # pycolmap has no array accessor for points3D: one binding call per kept point.
    return np.array([rec.point3D(i).xyz for i in ids], np.float64).reshape(-1, 3)


def _plot_basis(cams: _Cameras) -> FloatArray:
    """(3, 3) rows e1, e2, up: up from the images' mean up vector, e1/e2 by PCA."""
    up = cams.image_up.mean(0)
    centered = cams.centers - cams.centers.mean(0)
    if np.linalg.norm(up) < 0.3 and len(cams.centers) >= 3:  # no consensus: PCA
        up = np.linalg.svd(centered)[2][2]
    up = up / np.linalg.norm(up) if np.linalg.norm(up) > 0 else np.array([0.0, 0, 1])
    flat = centered - np.outer(centered @ up, up)
    e1 = np.linalg.svd(flat)[2][0] if len(flat) >= 2 and flat.any() else np.eye(3)[0]
    e1 = e1 - (e1 @ up) * up
    if np.linalg.norm(e1) < 1e-9:
        e1 = np.eye(3)[np.argmin(np.abs(up))] - up * up[np.argmin(np.abs(up))]
    e1 /= np.linalg.norm(e1)
    return np.array([e1, np.cross(up, e1), up])


def _pose_figures(
    pred: _Cameras | None, gt: _Cameras | None, points: FloatArray
) -> tuple[str, dict[str, str]]:
    """Top+side view PNG and the three 3D-angle PNGs, as data URIs."""
    main = pred if pred is not None else gt
    assert main is not None  # the caller checks
    basis = _plot_basis(main)
    origin = main.centers.mean(0)
    spread = np.ptp(main.centers, axis=0).max() if len(main.centers) > 1 else 1.0
    arrow = 0.12 * max(float(spread), 1e-6)
    # GT last and hollow, so a perfect reconstruction shows both markers.
    gt_label = "GT (aligned)" if pred is not None else "GT"
    sets = [
        (c, name, color)
        for c, name, color in (
            (pred, "reconstruction", "tab:blue"),
            (gt, gt_label, "tab:orange"),
        )
        if c is not None
    ]
    local_pts = (points - origin) @ basis.T
    if len(local_pts):  # drop far outliers so the cameras stay readable
        lo, hi = np.percentile(local_pts, [2, 98], axis=0)
        local_pts = local_pts[np.all((local_pts >= lo) & (local_pts <= hi), axis=1)]

    fig = _new_figure(12.0, 4.6)
    axes = fig.subplots(1, 2)
    for ax, (i, j), label in zip(
        axes, ((0, 1), (0, 2)), ("top view", "side view"), strict=True
    ):
        if len(local_pts):
            ax.scatter(
                local_pts[:, i],
                local_pts[:, j],
                s=1,
                c="0.65",
                lw=0,
                label="sparse points",
            )
        for cams, name, color in sets:
            c = (cams.centers - origin) @ basis.T
            d = cams.directions @ basis.T * arrow
            ax.quiver(
                c[:, i],
                c[:, j],
                d[:, i],
                d[:, j],
                color=color,
                angles="xy",
                scale_units="xy",
                scale=1,
                width=0.004,
            )
            hollow = cams is gt and pred is not None
            ax.scatter(
                c[:, i],
                c[:, j],
                s=70 if hollow else 30,
                label=name,
                zorder=3,
                facecolors="none" if hollow else color,
                edgecolors=color,
            )
            if cams is main:
                for n, x, y in zip(cams.names, c[:, i], c[:, j], strict=True):
                    ax.annotate(
                        Path(n).stem,
                        (x, y),
                        fontsize=7,
                        xytext=(3, 3),
                        textcoords="offset points",
                    )
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_title(label)
        ax.set_xlabel("horizontal axis 1")
        ax.set_ylabel("horizontal axis 2" if j == 1 else "up")
        ax.grid(alpha=0.3)
    axes[0].legend(loc="best", fontsize=8)
    flat = _figure_uri(fig)

    views = {}
    for view, (elev, azim) in VIEW_ANGLES_DEG.items():
        fig = _new_figure(6.0, 4.6)
        ax = fig.add_subplot(projection="3d")
        if len(local_pts):
            ax.scatter(*local_pts.T, s=1, c="0.65", lw=0)
        for cams, name, color in sets:
            c = (cams.centers - origin) @ basis.T
            d = cams.directions @ basis.T * arrow
            ax.quiver(*c.T, *d.T, color=color)
            hollow = cams is gt and pred is not None
            ax.scatter(
                *c.T,
                s=60 if hollow else 25,
                label=name,
                depthshade=False,
                facecolors="none" if hollow else color,
                edgecolors=color,
            )
        ax.view_init(elev=elev, azim=azim)
        ax.set_box_aspect(None)
        ax.set_title(f"{view} view", fontsize=10)
        ax.legend(loc="upper left", fontsize=7)
        views[view] = _figure_uri(fig)
    return flat, views


def _error_curve(curves: Mapping[str, FloatArray]) -> str:
    """Cumulative pose-error curves (fraction of pairs below each error), as a URI."""
    return _figure_uri(error_curve_figure(curves))


def error_curve_figure(curves: Mapping[str, FloatArray]) -> Figure:
    """Cumulative pose-error curves: per method, the share of pairs below each error."""
    fig = _new_figure(6.4, 4.6)
    ax = fig.add_subplot()
    grid = np.linspace(0.0, 180.0, 721)
    for name, errors in curves.items():
        frac = np.searchsorted(np.sort(errors), grid, side="right") / max(
            len(errors), 1
        )
        ax.step(grid, frac, where="post", label=f"{name} ({len(errors)} pairs)")
    for t in THRESHOLDS_DEG:
        ax.axvline(t, color="0.4", ls="--", lw=0.8)
        ax.text(t, 1.02, f"{t:g}°", ha="center", fontsize=8)
    ax.set_xlim(0, 183)  # room for the step of unregistered pairs at 180
    ax.set_ylim(0, 1.06)
    ax.set_xticks(np.arange(0, 181, 30))
    ax.set_xlabel("relative pose error (deg): max(rotation, translation angle)")
    ax.set_ylabel("fraction of image pairs")
    ax.grid(alpha=0.3)
    ax.legend(loc="lower right", fontsize=8)
    return fig


# ---------------------------------------------------------------- HTML pieces

CSS = """
body{font:14px/1.45 system-ui,-apple-system,'Segoe UI',Roboto,'DejaVu Sans',sans-serif;
 margin:0;color:#1d2330;background:#f4f5f7}
main{max-width:1360px;margin:0 auto;padding:12px 20px 40px}
h1{font-size:22px;margin:8px 0 2px}h2{font-size:18px;margin:0 0 8px}
h3{font-size:15px;margin:6px 0 4px}
section{background:#fff;border:1px solid #dde1e7;border-radius:6px;padding:12px 16px;
 margin:12px 0}
nav a{margin-right:14px;color:#2457a6}.sub{color:#5b6473;margin:0 0 6px}
table{border-collapse:collapse;margin:4px 0 8px}
td,th{border-bottom:1px solid #e6e8ec;padding:3px 10px;text-align:left;
 vertical-align:top}
th{background:#f0f2f5}td.num{text-align:right;font-variant-numeric:tabular-nums}
.missing{background:#fff6e0;border-left:4px solid #e0a200;padding:6px 10px;margin:6px 0}
.cols{display:flex;flex-wrap:wrap;gap:16px;align-items:flex-start}
.bar{height:12px;background:#4a7fd0;border-radius:2px;display:inline-block}
img{max-width:100%;height:auto;display:block}
.pairs{display:grid;grid-template-columns:repeat(auto-fill,minmax(620px,1fr));gap:14px}
figure{margin:0}figcaption{font-size:12.5px;color:#3b4350;margin-top:3px}
.legend{display:inline-block;width:180px;height:12px;vertical-align:middle;
 background:linear-gradient(90deg,#00ff00,#ffff00,#ff0000);border:1px solid #999}
.swatch{display:inline-block;width:22px;height:3px;background:#008cff;vertical-align:middle}
.views input{display:none}.views label{display:inline-block;padding:3px 10px;
 border:1px solid #aab;border-radius:4px;margin-right:6px;cursor:pointer}
.views .view{display:none}
#v-oblique:checked~.tabs label[for=v-oblique],#v-front:checked~.tabs label[for=v-front],
#v-top:checked~.tabs label[for=v-top]{background:#2457a6;color:#fff}
#v-oblique:checked~.view-oblique,#v-front:checked~.view-front,
#v-top:checked~.view-top{display:block}
"""


def _esc(value: object) -> str:
    return html.escape(str(value))


def _table(
    header: Sequence[str], rows: Sequence[Sequence[object]], numeric_from: int = 1
) -> str:
    head = "".join(f"<th>{_esc(h)}</th>" for h in header)
    body = "".join(
        "<tr>"
        + "".join(
            f"<td{' class=num' if i >= numeric_from else ''}>{_esc(v)}</td>"
            for i, v in enumerate(row)
        )
        + "</tr>"
        for row in rows
    )
    return f"<table><tr>{head}</tr>{body}</table>"


def _missing(text: str) -> str:
    return f'<p class="missing">{_esc(text)}</p>'


def _fmt(value: Any, digits: int = 1) -> str:
    if isinstance(value, int | np.integer):
        return str(int(value))
    if isinstance(value, float | np.floating):
        return "-" if math.isnan(value) else f"{value:.{digits}f}"
    return "-" if value is None else str(value)


def _metrics_rows(
    metrics: Mapping[str, Any],
) -> tuple[list[list[str]], dict[str, FloatArray]]:
    """Table rows and per-method pair errors (for the curve) from metrics dicts."""
    rows, curves = [], {}
    for name, m in metrics.items():
        m = m.to_dict() if isinstance(m, Metrics) else dict(m)
        auc = m.get("auc", {})
        rows.append(
            [
                name,
                f"{_fmt(m.get('num_registered'))}/{_fmt(m.get('num_images'))}",
                *(_fmt(auc.get(f"{t:g}")) for t in THRESHOLDS_DEG),
                _fmt(m.get("median_error_deg")),
            ]
        )
        if m.get("pairs"):
            curves[name] = np.array([p["error_deg"] for p in m["pairs"]], np.float64)
    return rows, curves


def _timings_html(timings: Mapping[str, float]) -> str:
    longest = max(max(timings.values(), default=0.0), 1e-9)
    rows = "".join(
        f"<tr><td>{_esc(stage)}</td><td class=num>{seconds:.2f} s</td><td>"
        f'<span class="bar" style="width:{max(1, round(300 * seconds / longest))}px">'
        "</span></td></tr>"
        for stage, seconds in timings.items()
    )
    total = sum(timings.values())
    return (
        f"<table><tr><th>stage</th><th>time</th><th></th></tr>{rows}"
        f"<tr><th>total</th><th class=num>{total:.2f} s</th><th></th></tr></table>"
    )


# ---------------------------------------------------------------- the report


@dataclass(kw_only=True, slots=True)
class _Context:
    """Everything read once, shared by the sections."""

    inputs: ReportInputs
    views: database.DatabaseViews
    names: dict[int, str]
    vc_keypoints: dict[int, VcKeypoints]
    vc_pairs: dict[tuple[int, int], PairVcMatches]
    classic_inliers: dict[tuple[int, int], np.ndarray]
    geometries: dict[tuple[int, int], database.TwoViewGeometryRow]
    model: pycolmap.Reconstruction | None
    gt: pycolmap.Reconstruction | None

    def camera(self, image_id: int) -> pycolmap.Camera:
        """The database camera of an image."""
        row = np.flatnonzero(self.views.image_ids == image_id)[0]
        return self.views.cameras[int(self.views.camera_ids[row])]


def _load_model(path: Path | None, what: str) -> pycolmap.Reconstruction | None:
    if path is None:
        return None
    path = Path(path)
    if not ((path / "images.bin").is_file() or (path / "images.txt").is_file()):
        raise FileNotFoundError(f"{what} {path} has no images.bin/images.txt")
    return pycolmap.Reconstruction(str(path))


def _read(inputs: ReportInputs) -> _Context:
    db = Path(inputs.database_path)
    views = database.read_views(db)
    names = dict(zip(views.image_ids.tolist(), views.image_names, strict=True))
    num_classic = dict(
        zip(views.image_ids.tolist(), views.num_keypoints.tolist(), strict=True)
    )
    vc_kp, vc_pairs = database.read_virtual_correspondences(db)
    geometries = database.read_two_view_geometries(db, include_vc=True)
    classic = {}
    for pair, row in geometries.items():
        m = row.inlier_matches  # classic + VC inliers: keep the classic rows only
        keep = (m[:, 0] < num_classic[pair[0]]) & (m[:, 1] < num_classic[pair[1]])
        classic[pair] = m[keep]
    return _Context(
        inputs=inputs,
        views=views,
        names=names,
        vc_keypoints={kp.image_id: kp for kp in vc_kp},
        vc_pairs={(p.image_id1, p.image_id2): p for p in vc_pairs},
        classic_inliers=classic,
        geometries=geometries,
        model=_load_model(inputs.model_path, "model_path"),
        gt=_load_model(inputs.gt_model_path, "gt_model_path"),
    )


def _relative(
    rec: pycolmap.Reconstruction | None, name1: str, name2: str
) -> tuple[pycolmap.Camera, pycolmap.Camera, FloatArray] | None:
    if rec is None:
        return None
    im1, im2 = rec.find_image_with_name(name1), rec.find_image_with_name(name2)
    if im1 is None or im2 is None or not (im1.has_pose and im2.has_pose):
        return None
    pose = relative_pose(im1.cam_from_world().matrix(), im2.cam_from_world().matrix())
    return rec.cameras[im1.camera_id], rec.cameras[im2.camera_id], pose


def _pair_errors(
    ctx: _Context, pair: tuple[int, int], xy1: FloatArray, xy2: FloatArray
) -> tuple[FloatArray, str]:
    """Epipolar errors of matches of a pair, and which geometry they are against."""
    n1, n2 = ctx.names[pair[0]], ctx.names[pair[1]]
    for rec, label in ((ctx.gt, "GT relative pose"), (ctx.model, "reconstructed pose")):
        found = _relative(rec, n1, n2)
        if found is not None:
            return epipolar_errors_px(xy1, xy2, *found), label
    row = ctx.geometries.get(pair)
    if row is not None and row.cam2_from_cam1 is not None:
        c1, c2 = ctx.camera(pair[0]), ctx.camera(pair[1])
        return epipolar_errors_px(xy1, xy2, c1, c2, row.cam2_from_cam1), "two-view pose"
    if row is not None and row.F is not None and row.F.any():
        return fundamental_errors_px(xy1, xy2, row.F), "two-view F"
    return np.full(len(xy1), np.nan), "no geometry"


def _read_image(ctx: _Context, image_id: int) -> np.ndarray:
    path = Path(ctx.inputs.image_dir) / ctx.names[image_id]
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is not None:
        return image
    logger.warning("cannot read %s: drawing on a grey canvas", path)
    cam = ctx.camera(image_id)
    return np.full((cam.height, cam.width, 3), 200, np.uint8)


def _pairs_section(ctx: _Context) -> str:
    inputs = ctx.inputs
    # Rank by (VC inliers, classic inliers, VCs): unverified VC pairs come last.
    score = {p: (int(vc.is_inlier.sum()), 0, len(vc)) for p, vc in ctx.vc_pairs.items()}
    for p, m in ctx.classic_inliers.items():
        vc_inliers, _, num_vcs = score.get(p, (0, 0, 0))
        score[p] = (vc_inliers, len(m), num_vcs)
    candidates = [p for p, s in score.items() if sum(s) > 0]
    ranked = sorted(candidates, key=lambda p: (*(-v for v in score[p]), p))
    ranked = ranked[: inputs.max_pairs]
    vc_legend = (
        "VCs: dots (inliers large and outlined) coloured by symmetric epipolar error "
        f'<span class="legend"></span> 0 → ≥{inputs.max_epipolar_error_px:g} px '
        f"(grey: no geometry), at most {inputs.max_vc_dots} per pair; "
        f"{inputs.max_vc_lines} of them joined by lines. "
        if ctx.vc_pairs
        else ""
    )
    parts = [
        '<section id="pairs"><h2>Image pairs</h2>',
        f'<p class="sub">{len(ranked)} of {len(candidates)} pairs with VCs or '
        f"classic inliers, most VC inliers first. {vc_legend}Classic inlier "
        'matches: <span class="swatch"></span> thin azure lines.</p>',
    ]
    if not ctx.vc_pairs:
        parts.append(
            _missing(
                "This database has no virtual correspondences "
                "(colmap-vc augment was not run on it): the pairs show "
                "classic inlier matches only."
            )
        )
    if not ranked:
        parts.append(_missing("No image pair has matches: nothing to draw."))
    parts.append('<div class="pairs">')
    for pair in ranked:
        vc = ctx.vc_pairs.get(pair)
        classic = ctx.classic_inliers.get(pair, np.zeros((0, 2), np.int64))
        c1 = c2 = np.zeros((0, 2))
        if len(classic):
            c1 = database.read_keypoints(inputs.database_path, pair[0])[classic[:, 0]]
            c2 = database.read_keypoints(inputs.database_path, pair[1])[classic[:, 1]]
        if vc is not None and len(vc):
            v1 = ctx.vc_keypoints[pair[0]].xy_img[vc.idx1]
            v2 = ctx.vc_keypoints[pair[1]].xy_img[vc.idx2]
            errors, source = _pair_errors(ctx, pair, v1, v2)
            inlier = vc.is_inlier
        else:
            v1 = v2 = np.zeros((0, 2))
            errors, inlier, source = np.zeros(0), np.zeros(0, bool), ""
        panel = draw_pair(
            _read_image(ctx, pair[0]),
            _read_image(ctx, pair[1]),
            vc_xy1=v1,
            vc_xy2=v2,
            vc_errors_px=errors,
            vc_is_inlier=inlier,
            classic_xy1=c1,
            classic_xy2=c2,
            height=inputs.panel_height_px,
            max_error_px=inputs.max_epipolar_error_px,
            max_vc_lines=inputs.max_vc_lines,
            max_vc_dots=inputs.max_vc_dots,
        )
        caption = (
            f"<b>{_esc(ctx.names[pair[0]])} ↔ {_esc(ctx.names[pair[1]])}</b>: "
            + (f"{len(v1)} VCs ({int(inlier.sum())} inliers), " if vc else "")
            + f"{len(classic)} classic inliers"
        )
        finite = errors[np.isfinite(errors)]
        if len(finite):
            caption += (
                f"; epipolar error vs {source}: median "
                f"{np.median(finite):.2f} px, 90% {np.percentile(finite, 90):.2f}"
                f" px, max {finite.max():.1f} px"
            )
        elif len(v1):
            caption += f"; epipolar errors unknown ({source})"
        parts.append(
            f'<figure class="pair" data-pair="{pair[0]}-{pair[1]}">'
            f'<img alt="pair {pair[0]}-{pair[1]}" src="{_jpeg_uri(panel)}">'
            f"<figcaption>{caption}</figcaption></figure>"
        )
    parts.append("</div></section>")
    return "".join(parts)


def _people_section(ctx: _Context) -> str:
    """Each image's VC keypoints coloured by their person's identity."""
    from colmap_vc import report_people
    from colmap_vc.keypoint_tracks import person_identities

    identities = person_identities(
        database.read_person_associations(ctx.inputs.database_path)
    )
    parts = [
        '<section id="people"><h2>People</h2>',
        '<p class="sub">VC keypoints coloured by the identity the association '
        "gave their person: the same colour is the same person in every view; grey "
        "marks a person left out (no confident partner in any other view).</p>",
    ]
    if not ctx.vc_keypoints:
        parts.append(_missing("No virtual correspondences: no people to show."))
        parts.append("</section>")
        return "".join(parts)
    parts.append('<div class="pairs">')
    for image_id in sorted(ctx.vc_keypoints, key=lambda i: ctx.names[i]):
        kp = ctx.vc_keypoints[image_id]
        identity = report_people.keypoint_identities(identities, image_id, kp.person_id)
        panel = report_people.draw_people(
            _read_image(ctx, image_id),
            kp.xy_img,
            identity,
            ctx.inputs.panel_height_px,
        )
        who = ", ".join(
            f"person {p} = identity {i}" if i >= 0 else f"person {p} left out"
            for p, i in sorted(
                {
                    int(p): int(i) for p, i in zip(kp.person_id, identity, strict=True)
                }.items()
            )
        )
        parts.append(
            f'<figure class="person" data-image="{image_id}">'
            f'<img alt="people in {_esc(ctx.names[image_id])}" '
            f'src="{_jpeg_uri(panel)}"><figcaption><b>{_esc(ctx.names[image_id])}'
            f"</b>: {_esc(who)}</figcaption></figure>"
        )
    parts.append("</div></section>")
    return "".join(parts)


def _summary_section(ctx: _Context, extra_metrics: Mapping[str, Any]) -> str:
    views, inputs = ctx.views, ctx.inputs
    vcs = list(ctx.vc_pairs.values())
    kinds = np.concatenate([vc.kind for vc in vcs]) if vcs else np.zeros(0, np.int64)
    by_kind = ", ".join(f"{k.name.lower()} {int((kinds == k).sum())}" for k in HitKind)
    rows: list[list[object]] = [
        [
            "database",
            f"{Path(inputs.database_path).name} (COLMAP {views.schema} schema)",
        ],
        ["images", len(views.image_ids)],
        ["classic keypoints", int(views.num_keypoints.sum())],
        [
            "verified pairs (classic inliers > 0)",
            sum(len(m) > 0 for m in ctx.classic_inliers.values()),
        ],
        ["classic inlier matches", sum(len(m) for m in ctx.classic_inliers.values())],
        ["VC keypoints", int(views.num_vc_keypoints.sum())],
        [
            "VCs (inliers) in pairs",
            f"{sum(len(v) for v in vcs)} "
            f"({sum(int(v.is_inlier.sum()) for v in vcs)}) in {len(vcs)} pairs",
        ],
    ]
    if vcs:
        rows.append(["VCs by kind", by_kind])
    if ctx.model is not None:
        rows += [
            [
                "registered images",
                f"{ctx.model.num_reg_images()}/{len(views.image_ids)}",
            ],
            ["sparse points", ctx.model.num_points3D()],
            [
                "mean reprojection error",
                f"{ctx.model.compute_mean_reprojection_error():.3f} px",
            ],
        ]
    parts = [
        '<section id="summary"><h2>Summary</h2><div class="cols"><div>',
        _table(["", "value"], [[k, _fmt(v)] for k, v in rows]),
        "</div><div>",
    ]
    metrics = {**(inputs.metrics or {}), **extra_metrics}
    if metrics:
        metric_rows, _ = _metrics_rows(metrics)
        parts += [
            "<h3>Pose accuracy</h3>",
            _table(
                [
                    "method",
                    "registered",
                    *(f"AUC@{t:g}°" for t in THRESHOLDS_DEG),
                    "median error (°)",
                ],
                metric_rows,
            ),
        ]
    else:
        parts.append(
            _missing(
                "No metrics given and no GT + model to compute them: "
                "no pose-accuracy table."
            )
        )
    if inputs.timings_s:
        parts += ["<h3>Per-stage timings</h3>", _timings_html(inputs.timings_s)]
    else:
        parts.append(_missing("No per-stage timings given (timings_s)."))
    parts.append("</div></div>")
    if ctx.model is None:
        parts.append(
            _missing(
                "No reconstructed model given (model_path): registration,"
                " camera poses and pose errors are not shown."
            )
        )
    parts.append("</section>")
    return "".join(parts)


def _poses_section(ctx: _Context) -> tuple[str, dict[str, Any]]:
    """Camera plot + error curve, and the metrics of the model vs GT (if both)."""
    parts = ['<section id="poses"><h2>Camera poses</h2>']
    extra: dict[str, Any] = {}
    pred = _Cameras.of(ctx.model) if ctx.model is not None else None
    gt = _Cameras.of(ctx.gt) if ctx.gt is not None else None
    if pred is None:
        parts.append(
            _missing(
                "No reconstructed model given: "
                + ("showing the GT cameras only." if gt else "no camera poses to show.")
            )
        )
    elif gt is None:
        parts.append(
            _missing(
                "No ground-truth model given (gt_model_path): GT cameras "
                "and the pose-error curve are not shown."
            )
        )
    if pred is not None and gt is not None:
        common = sorted(set(pred.names) & set(gt.names))
        if len(common) >= 3:
            src = gt.centers[[gt.names.index(n) for n in common]]
            dst = pred.centers[[pred.names.index(n) for n in common]]
            gt = gt.transformed(*_similarity(src, dst))
        else:
            parts.append(
                _missing(
                    f"Only {len(common)} registered images are in the GT: "
                    "too few to align GT (needs 3), GT cameras not drawn."
                )
            )
            gt = None
    main = pred if pred is not None else gt
    if main is not None and len(main.names):
        points = _points(ctx.model) if ctx.model is not None else np.zeros((0, 3))
        flat, views = _pose_figures(pred, gt, points)
        aligned = (
            " GT cameras (hollow) are aligned to the reconstruction by a "
            "similarity (Umeyama on camera centres)."
            if pred and gt
            else ""
        )
        parts.append(
            '<p class="sub">Up is the cameras\' mean image-up direction.'
            f"{aligned} Arrows: viewing directions.</p>"
            f'<img alt="camera poses" src="{flat}">'
        )
        radios = "".join(
            f'<input type="radio" name="view" id="v-{v}"{" checked" if i == 0 else ""}>'
            for i, v in enumerate(views)
        )
        tabs = "".join(f'<label for="v-{v}">{v}</label>' for v in views)
        imgs = "".join(
            f'<img class="view view-{v}" alt="{v} 3D view" src="{uri}">'
            for v, uri in views.items()
        )
        parts.append(
            f'<div class="cols"><div class="views"><h3>3D views</h3>{radios}'
            f'<div class="tabs">{tabs}</div>{imgs}</div>'
        )
    else:
        if main is not None:
            parts.append(_missing("The model has no registered image."))
        parts.append('<div class="cols">')

    parts.append('<div id="errors"><h3>Cumulative pose error</h3>')
    curves: dict[str, FloatArray] = {}
    # Given metrics already describe the methods; otherwise evaluate this model.
    if ctx.gt is not None and ctx.model is not None and not ctx.inputs.metrics:
        metrics = evaluate_reconstruction(ctx.model, ctx.gt)
        extra["this model (vs GT)"] = metrics
        curves["this model"] = np.array([p.error_deg for p in metrics.pairs])
    curves.update(_metrics_rows(ctx.inputs.metrics or {})[1])
    if curves:
        parts.append(
            f'<img alt="pose error curve" src="{_error_curve(curves)}">'
            '<p class="sub" style="max-width:640px">Fraction of GT image pairs '
            "whose relative pose error is below x; unregistered pairs count as "
            "180°. Dashed: the AUC thresholds.</p>"
        )
    else:
        parts.append(
            _missing(
                "No ground-truth model (or no reconstructed model) and no "
                "per-pair metrics given: no pose-error curve."
            )
        )
    parts.append("</div></div></section>")
    return "".join(parts), extra


def build_report(inputs: ReportInputs, out_path: Path) -> Path:
    """Write the self-contained HTML report of ``inputs`` to ``out_path``.

    Raises:
        FileNotFoundError: the database or a given model folder is missing.
        ValueError: the database is not a COLMAP database with keypoints.
    """
    if inputs.max_pairs < 0 or inputs.max_epipolar_error_px <= 0:
        raise ValueError(
            f"{inputs.max_pairs=} must be >= 0 and {inputs.max_epipolar_error_px=} > 0"
        )
    ctx = _read(inputs)
    poses, extra_metrics = _poses_section(ctx)
    sections = [
        _summary_section(ctx, extra_metrics),
        poses,
        _pairs_section(ctx),
        _people_section(ctx),
    ]
    nav = "".join(
        f'<a href="#{s}">{s}</a>'
        for s in ("summary", "poses", "errors", "pairs", "people")
    )
    page = (
        '<!DOCTYPE html><html lang="en"><head><meta charset="utf-8">'
        f"<title>{_esc(inputs.title)}</title><style>{CSS}</style></head><body><main>"
        f"<h1>{_esc(inputs.title)}</h1><p class=sub>{_esc(Path(inputs.database_path))}"
        f"</p><nav>{nav}</nav>{''.join(sections)}</main></body></html>"
    )
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    out_path.write_text(page, encoding="utf-8")
    logger.info(
        "Report (%d KiB; %d images, %d pairs with VCs, model %s, GT %s) written to %s",
        len(page) // 1024,
        len(ctx.names),
        len(ctx.vc_pairs),
        "yes" if ctx.model is not None else "no",
        "yes" if ctx.gt is not None else "no",
        out_path,
    )
    return out_path
