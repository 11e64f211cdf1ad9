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

import logging
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pycolmap

from colmap_vc import database
from colmap_vc.evaluation import (
    THRESHOLDS_DEG,
    camera_distance_ratio,
    evaluate_reconstruction,
    poses_by_name,
    relative_pose,
)
from colmap_vc.image_io import read_image
from colmap_vc.metric_scale import read_metric_scale
from colmap_vc.report_draw import (
    draw_pair,
    epipolar_errors_px,
    fundamental_errors_px,
)
from colmap_vc.report_figures import (
    PlotCameras,
    error_curve_uri,
    jpeg_uri,
    model_points,
    pose_figures,
    similarity,
)
from colmap_vc.report_html import (
    CSS,
    esc,
    fmt,
    metrics_rows,
    missing,
    table,
    timings_html,
)
from colmap_vc.structs import FloatArray, HitKind, PairVcMatches, VcKeypoints

logger = logging.getLogger(__name__)


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
    image = read_image(path)
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
            missing(
                "This database has no virtual correspondences "
                "(colmap-vc augment was not run on it): the pairs show "
                "classic inlier matches only."
            )
        )
    if not ranked:
        parts.append(missing("No image pair has matches: nothing to draw."))
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
            f"<b>{esc(ctx.names[pair[0]])} ↔ {esc(ctx.names[pair[1]])}</b>: "
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
            f'<img alt="pair {pair[0]}-{pair[1]}" src="{jpeg_uri(panel)}">'
            f"<figcaption>{caption}</figcaption></figure>"
        )
    parts.append("</div></section>")
    return "".join(parts)


def _who(name: str, identity: dict[int, int], unseen: dict[str, str]) -> str:
    """Caption of an image's people: each one's identity, or why it was left out
    (``unseen``: "image #person" -> the visibility check's reason)."""
    return ", ".join(
        f"person {p} = identity {i}"
        if i >= 0
        else f"person {p} left out"
        + (f": {unseen[f'{name} #{p}']}" if f"{name} #{p}" in unseen else "")
        for p, i in sorted(identity.items())
    )


def _people_section(ctx: _Context) -> str:
    """Each image's VC keypoints coloured by their person's identity."""
    from colmap_vc import report_people
    from colmap_vc.vc_records import person_identities

    identities = person_identities(
        database.read_person_associations(ctx.inputs.database_path)
    )
    unseen = database.read_run_info(ctx.inputs.database_path).get("left_out_people", {})
    parts = [
        '<section id="people"><h2>People</h2>',
        '<p class="sub">VC keypoints coloured by the identity the association '
        "gave their person: the same colour is the same person in every view; grey "
        "marks a person left out (no confident partner in any other view, or, as "
        "said under the image, not seen where it would be in view: augment's "
        "visibility check).</p>",
    ]
    if not ctx.vc_keypoints:
        parts.append(missing("No virtual correspondences: no people to show."))
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
        who = _who(
            ctx.names[image_id],
            dict(zip(kp.person_id.tolist(), identity.tolist(), strict=True)),
            unseen,
        )
        parts.append(
            f'<figure class="person" data-image="{image_id}">'
            f'<img alt="people in {esc(ctx.names[image_id])}" '
            f'src="{jpeg_uri(panel)}"><figcaption><b>{esc(ctx.names[image_id])}'
            f"</b>: {esc(who)}</figcaption></figure>"
        )
    parts.append("</div></section>")
    return "".join(parts)


def _gravity_section(ctx: _Context) -> str:
    """Each measured camera with the vertical lines its up rests on."""
    from colmap_vc import report_gravity

    ids = {n: i for i, n in ctx.names.items()}
    return report_gravity.gravity_section(
        ctx.inputs.model_path,
        {n: ctx.camera(i) for n, i in ids.items()},
        lambda name: _read_image(ctx, ids[name]),
        ctx.inputs.panel_height_px,
    )


def _scale_text(model_path: Path | None) -> str:
    """The model's scale, as `map` wrote it beside the model."""
    scale = None if model_path is None else read_metric_scale(Path(model_path))
    if scale is None:
        return "arbitrary (no metric_scale.json beside the model)"
    return f"metres, from the people's size: {scale.describe()}"


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
            ["scale", _scale_text(inputs.model_path)],
        ]
        if ctx.gt is not None:
            ratio = camera_distance_ratio(
                poses_by_name(ctx.model), poses_by_name(ctx.gt)
            )
            if np.isfinite(ratio):
                rows.append(["camera distances / ground truth's", f"{ratio:.3f}"])
    parts = [
        '<section id="summary"><h2>Summary</h2><div class="cols"><div>',
        table(["", "value"], [[k, fmt(v)] for k, v in rows]),
        "</div><div>",
    ]
    metrics = {**(inputs.metrics or {}), **extra_metrics}
    if metrics:
        metric_rows, _ = metrics_rows(metrics)
        parts += [
            "<h3>Pose accuracy</h3>",
            table(
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
            missing(
                "No metrics given and no GT + model to compute them: "
                "no pose-accuracy table."
            )
        )
    if inputs.timings_s:
        parts += ["<h3>Per-stage timings</h3>", timings_html(inputs.timings_s)]
    else:
        parts.append(missing("No per-stage timings given (timings_s)."))
    parts.append("</div></div>")
    if ctx.model is None:
        parts.append(
            missing(
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
    pred = PlotCameras.of(ctx.model) if ctx.model is not None else None
    gt = PlotCameras.of(ctx.gt) if ctx.gt is not None else None
    if pred is None:
        parts.append(
            missing(
                "No reconstructed model given: "
                + ("showing the GT cameras only." if gt else "no camera poses to show.")
            )
        )
    elif gt is None:
        parts.append(
            missing(
                "No ground-truth model given (gt_model_path): GT cameras "
                "and the pose-error curve are not shown."
            )
        )
    if pred is not None and gt is not None:
        common = sorted(set(pred.names) & set(gt.names))
        if len(common) >= 3:
            src = gt.centers[[gt.names.index(n) for n in common]]
            dst = pred.centers[[pred.names.index(n) for n in common]]
            gt = gt.transformed(*similarity(src, dst))
        else:
            parts.append(
                missing(
                    f"Only {len(common)} registered images are in the GT: "
                    "too few to align GT (needs 3), GT cameras not drawn."
                )
            )
            gt = None
    main = pred if pred is not None else gt
    if main is not None and len(main.names):
        points = model_points(ctx.model) if ctx.model is not None else np.zeros((0, 3))
        flat, views = pose_figures(pred, gt, points)
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
            parts.append(missing("The model has no registered image."))
        parts.append('<div class="cols">')

    parts.append('<div id="errors"><h3>Cumulative pose error</h3>')
    curves: dict[str, FloatArray] = {}
    # Given metrics already describe the methods; otherwise evaluate this model.
    if ctx.gt is not None and ctx.model is not None and not ctx.inputs.metrics:
        metrics = evaluate_reconstruction(ctx.model, ctx.gt)
        extra["this model (vs GT)"] = metrics
        curves["this model"] = np.array([p.error_deg for p in metrics.pairs])
    curves.update(metrics_rows(ctx.inputs.metrics or {})[1])
    if curves:
        parts.append(
            f'<img alt="pose error curve" src="{error_curve_uri(curves)}">'
            '<p class="sub" style="max-width:640px">Fraction of GT image pairs '
            "whose relative pose error is below x; unregistered pairs count as "
            "180°. Dashed: the AUC thresholds.</p>"
        )
    else:
        parts.append(
            missing(
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
        _gravity_section(ctx),
    ]
    nav = "".join(
        f'<a href="#{s}">{s}</a>'
        for s in ("summary", "poses", "errors", "pairs", "people", "gravity")
        if f'id="{s}"' in "".join(sections)
    )
    page = (
        '<!DOCTYPE html><html lang="en"><head><meta charset="utf-8">'
        f"<title>{esc(inputs.title)}</title><style>{CSS}</style></head><body><main>"
        f"<h1>{esc(inputs.title)}</h1><p class=sub>{esc(Path(inputs.database_path))}"
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
