"""The report's pictures as data URIs: JPEG images, camera-pose plots and the
cumulative pose-error curve (matplotlib, the ``viz`` extra, imported lazily)."""

from __future__ import annotations

import base64
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np
import pycolmap

from colmap_vc.evaluation import THRESHOLDS_DEG
from colmap_vc.structs import FloatArray

if TYPE_CHECKING:
    from matplotlib.figure import Figure

MAX_PLOT_POINTS = 20000  # sparse points drawn in the pose plots (strided subsample)
VIEW_ANGLES_DEG = {
    "oblique": (25.0, -60.0),
    "front": (5.0, -90.0),
    "top": (85.0, -90.0),
}


def similarity(
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


def jpeg_uri(image: np.ndarray, quality: int = 92) -> str:
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
    """A figure rasterised by Agg (no PIL, no zlib: see jpeg_uri) as a JPEG URI."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    rgba = np.asarray(canvas.buffer_rgba())
    return jpeg_uri(cv2.cvtColor(rgba, cv2.COLOR_RGBA2BGR), quality=95)


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
class PlotCameras:
    """Registered cameras of one model in some world frame."""

    names: tuple[str, ...]
    centers: FloatArray  # (N, 3)
    directions: FloatArray  # (N, 3) unit viewing directions
    image_up: FloatArray  # (N, 3) unit world direction of each image's "up"

    @classmethod
    def of(cls, rec: pycolmap.Reconstruction) -> PlotCameras:
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

    def transformed(self, s: float, R: FloatArray, t: FloatArray) -> PlotCameras:
        return PlotCameras(
            names=self.names,
            centers=s * self.centers @ R.T + t,
            directions=self.directions @ R.T,
            image_up=self.image_up @ R.T,
        )


def model_points(rec: pycolmap.Reconstruction) -> FloatArray:
    """(P, 3) sparse points, strided to at most MAX_PLOT_POINTS."""
    ids = sorted(rec.point3D_ids())
    ids = ids[:: max(1, math.ceil(len(ids) / MAX_PLOT_POINTS))]
    # pycolmap has no array accessor for points3D: one binding call per kept point.
    return np.array([rec.point3D(i).xyz for i in ids], np.float64).reshape(-1, 3)


def _plot_basis(cams: PlotCameras) -> FloatArray:
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


def pose_figures(
    pred: PlotCameras | None, gt: PlotCameras | None, points: FloatArray
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


def error_curve_uri(curves: Mapping[str, FloatArray]) -> str:
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
