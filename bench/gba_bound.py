"""What the surface VCs could add to the refinement, at best: a bound from the truth.

Issue 12 asks the generalized BA to beat the keypoint BA by 5 points of AUC@15 on
the 1-person domes with realistic priors. This bench asks how much any weighting of
the surface evidence could give there. On the six realistic-prior scenes of
bench/accuracy.py (run it first: this bench starts from its augmented databases),
`map`'s default model is adjusted again from its own poses with the evidence named:

- keypoints alone: the model's keypoint points (the camera check's left/right
  exchanges applied), without surface points;
- the default: the model as `map` leaves it (keypoints and the mapper's surface
  points, each image's weighing 6 keypoint observations together);
- `map --gba`: every surface sample, weighted by its spread and its correlation
  with its neighbours (colmap_vc/gba/correlated.py), from the same database;
- the visible surface samples the truth keeps: within 8 px of the projection of
  the point the true cameras triangulate, at the keypoints' weight (outliers
  removed by an oracle);
- the same, with each image's similarity (shift, scale, turn) of their error
  removed with the truth (what a perfect per-image correction could remove);
- the same samples at the true projection of their point plus independent 3 px
  noise: surface evidence as precise as the keypoints and independent of them.

The last row against the others says where the limit is: in the surface samples'
errors, which are correlated over their neighbours (the dense map slides smoothly),
not in their weighting. Writes bench/out/gba_bound.json and the table in
docs/gba.md (section gba-bound).

With ``--level fitted`` the same scenes' `fitted` priors (the bundled estimator's
fit to landmarks, docs/synthetic.md) give the first three rows only (the truth's
rows are calibrated to the realistic keypoints' noise): bench/out/gba_bound_fitted.json
and section gba-bound-fitted of docs/gba.md.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import shutil
import time
from pathlib import Path

import numpy as np
import pycolmap
from common import DOCS, OUT, machine, replace_section, setup_logging, write_json

from colmap_vc import database, mapping
from colmap_vc import keypoint_tracks as kt
from colmap_vc.evaluation import evaluate_reconstruction, pose_auc
from colmap_vc.gba.ceres import bundle_adjust_inplace
from colmap_vc.keypoint_ba import KeypointBaOptions, surface_noise, with_loss_scale
from colmap_vc.structs import HitKind
from colmap_vc.vc_records import read_vc_records

logger = logging.getLogger("bench.gba_bound")

SCENES = {
    "dome, 1 person": ["acc_dome_p1_s0", "acc_dome_p1_s1"],
    "dome, 3 people": ["acc_dome_p3_s0", "acc_dome_p3_s1"],
    "dense, 1 person": ["acc_dense_p1_s0", "acc_dense_p1_s1"],
}
ROWS = {
    "keypoints": "keypoints alone",
    "default": "keypoints + surface points weighing 6 observations per image (`map`)",
    "gba": "keypoints + every surface sample, correlated noise (`map --gba`)",
    "truth_kept": "keypoints + visible surface samples within 8 px of the truth",
    "truth_weighted": "the same, weighted as `map --gba` weighs its samples",
    "truth_similarity": "the same at the keypoints' weight, each image's similarity "
    "of their error removed",
    "independent": "the same samples at their true projection + independent 3 px",
}
TRUTH_PX = 8.0
"""An observation the truth keeps is within this of the projection of the point
the true cameras triangulate (2.7 sigma of the realistic keypoints' 3 px)."""
INDEPENDENT_PX = 3.0
"""Noise of the simulated independent surface evidence: the realistic priors'
keypoint noise (colmap_vc/synthetic/noise.py)."""


def visibility(db: Path) -> dict[int, np.ndarray]:
    """Per image, each VC keypoint: 1 seen, 2 hidden, 0 unknown. A pair's VC is
    co-visible when both images see its point, virtual when one does; seen and
    hidden spread through the virtual VCs, and where neither is known the side
    with more virtual partners is the one that sees the point (one view seeing a
    sample that others only hide behind the body)."""
    kps, pairs = database.read_virtual_correspondences(db)
    vis = {v.image_id: np.zeros(len(v.track_id), np.int8) for v in kps}
    degree = {k: np.zeros(len(v), np.int64) for k, v in vis.items()}
    for p in pairs:  # loop over image pairs, vectorized over VCs
        c = p.kind == HitKind.COVISIBLE
        vis[p.image_id1][p.idx1[c]] = 1
        vis[p.image_id2][p.idx2[c]] = 1
        v = p.kind == HitKind.VIRTUAL
        np.add.at(degree[p.image_id1], p.idx1[v], 1)
        np.add.at(degree[p.image_id2], p.idx2[v], 1)
    for _ in range(3):  # a few sweeps: seen <-> hidden across virtual VCs
        for p in pairs:
            v = p.kind == HitKind.VIRTUAL
            i1, i2 = p.idx1[v], p.idx2[v]
            a, b = vis[p.image_id1][i1].copy(), vis[p.image_id2][i2].copy()
            vis[p.image_id2][i2[(a == 1) & (b == 0)]] = 2
            vis[p.image_id1][i1[(b == 1) & (a == 0)]] = 2
            vis[p.image_id2][i2[(a == 2) & (b == 0)]] = 1
            vis[p.image_id1][i1[(b == 2) & (a == 0)]] = 1
    for p in pairs:
        v = p.kind == HitKind.VIRTUAL
        i1, i2 = p.idx1[v], p.idx2[v]
        open_ = (vis[p.image_id1][i1] == 0) & (vis[p.image_id2][i2] == 0)
        d1, d2 = degree[p.image_id1][i1], degree[p.image_id2][i2]
        vis[p.image_id1][i1[open_ & (d1 > d2)]] = 1
        vis[p.image_id2][i2[open_ & (d1 > d2)]] = 2
        vis[p.image_id1][i1[open_ & (d2 > d1)]] = 2
        vis[p.image_id2][i2[open_ & (d2 > d1)]] = 1
    return vis


def projections(
    rec: pycolmap.Reconstruction, tracks: kt.KeypointTracks, keep: np.ndarray
) -> np.ndarray:
    """(O, 2) projection of each track's point, triangulated by ``rec``'s poses
    from the observations in ``keep``."""
    X, _ = kt.triangulate_tracks(rec, kt.subset(tracks, keep))
    X = np.vstack([X, np.full((tracks.num_tracks + 1 - len(X), 3), np.nan)])
    out = np.full((len(tracks.track), 2), np.nan)
    for i in np.unique(tracks.image_id):  # loop over images
        sel = tracks.image_id == i
        image = rec.image(int(i))
        T = image.cam_from_world()
        Xc = X[tracks.track[sel]] @ T.rotation.matrix().T + T.translation
        ok = np.isfinite(Xc).all(axis=1)
        proj = np.full((sel.sum(), 2), np.nan)
        proj[ok] = rec.camera(image.camera_id).img_from_cam(Xc[ok])
        out[sel] = proj
    return out


def truth_kept(gt: pycolmap.Reconstruction, tracks: kt.KeypointTracks):
    """The observations within TRUTH_PX of the projection of their point, as the
    true cameras triangulate it from the kept ones (three rounds) -> (tracks,
    their true projections)."""
    keep = np.ones(len(tracks.track), dtype=bool)
    for _ in range(3):
        proj = projections(gt, tracks, keep)
        err = np.linalg.norm(proj - tracks.xy_img, axis=1)
        keep = np.nan_to_num(err, nan=np.inf) < TRUTH_PX
    kept = kt.subset(tracks, keep)
    return kept, projections(gt, kept, np.ones(len(kept.track), dtype=bool))


def with_pixels(tracks: kt.KeypointTracks, xy: np.ndarray) -> kt.KeypointTracks:
    return dataclasses.replace(tracks, xy_img=xy)


def similarity_design(c: np.ndarray) -> np.ndarray:
    """(2N, 4) design of a small 2D similarity (shift x, y; scale; turn) at the
    centred pixels ``c`` (N, 2), rows interleaved x, y."""
    A = np.zeros((2 * len(c), 4))
    A[0::2, 0], A[1::2, 1] = 1, 1
    A[0::2, 2], A[1::2, 2] = c[:, 0], c[:, 1]
    A[0::2, 3], A[1::2, 3] = -c[:, 1], c[:, 0]
    return A


def similarity_removed(tracks: kt.KeypointTracks, truth: np.ndarray) -> np.ndarray:
    """Pixels less each image's least-squares similarity of their error."""
    xy = tracks.xy_img.copy()
    err = tracks.xy_img - truth
    for i in np.unique(tracks.image_id):  # loop over images
        sel = tracks.image_id == i
        A = similarity_design(tracks.xy_img[sel] - tracks.xy_img[sel].mean(axis=0))
        p, *_ = np.linalg.lstsq(A, err[sel].ravel(), rcond=None)
        xy[sel] -= (A @ p).reshape(-1, 2)
    return xy


def adjusted(
    base: pycolmap.Reconstruction,
    keypoints: kt.KeypointTracks,
    extra: kt.KeypointTracks | None,
    loss_px: float,
    weighted: bool = False,
) -> pycolmap.Reconstruction:
    """``base`` without its surface points, plus ``extra`` (its pixels written
    into the images) under the keypoints' loss and weight, or ``weighted`` as
    `map --gba` weighs surface samples, bundle-adjusted."""
    keypoint_obs = set(
        zip(keypoints.image_id.tolist(), keypoints.point2D_idx.tolist(), strict=True)
    )
    rec = pycolmap.Reconstruction(base)
    for point_id, point in list(rec.points3D.items()):  # loop over model points
        if not any(
            (e.image_id, e.point2D_idx) in keypoint_obs for e in point.track.elements
        ):
            rec.delete_point3D(point_id)
    if extra is not None:
        extra = kt.subset(extra, kt.observed_in_posed_images(rec, extra))
        for i in np.unique(extra.image_id):  # loop over images
            sel = extra.image_id == i
            points2D = rec.image(int(i)).points2D
            for idx, xy in zip(
                extra.point2D_idx[sel].tolist(), extra.xy_img[sel], strict=True
            ):
                points2D[idx].xy = xy
        kt.add_keypoint_points(rec, extra, 2)
    people = None
    if weighted and extra is not None:
        options = KeypointBaOptions(loss_scale_px=loss_px)
        people = surface_noise(rec, keypoints, extra, options)
    bundle_adjust_inplace(rec, loss_px, people)
    return rec


def map_scene(
    scene: str, gba: bool, level: str
) -> tuple[Path, pycolmap.Reconstruction]:
    """`map` (default, or ``--gba``) on a copy of the accuracy bench's augmented
    database of the scene's priors of ``level``."""
    source = OUT / "runs" / "accuracy" / scene / level / "augmented_classic0.db"
    if not source.exists():
        raise SystemExit(f"{source} is missing: run bench/accuracy.py first")
    work = OUT / "runs" / "gba_bound" / scene / level / ("gba" if gba else "default")
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    db = work / "database.db"
    shutil.copyfile(source, db)
    rec, _ = mapping.run_incremental(
        db,
        OUT / "scenes" / scene / "images",
        work / "sparse",
        mapping.MappingOptions(
            keypoint_ba_options=KeypointBaOptions(surface_tracks=gba),
            show_progress=False,
        ),
    )
    assert rec is not None, f"{scene}: no model"
    return db, rec


def scene_errors(
    scene: str, rng: np.random.Generator, level: str
) -> dict[str, list[float]]:
    """Pair errors (deg) of every row on one scene (the first three only, but
    for the realistic priors)."""
    gt = pycolmap.Reconstruction(OUT / "scenes" / scene / "gt" / "sparse")
    db, base = map_scene(scene, False, level)
    _, gba = map_scene(scene, True, level)
    views = database.read_views(db)
    for i, name in zip(views.image_ids.tolist(), views.image_names, strict=True):
        assert gt.image(i).name == name, "the truth's image ids are the database's"
    ids = np.array(sorted(base.reg_image_ids()), dtype=np.int64)
    first_vc = dict(
        zip(views.image_ids.tolist(), views.num_keypoints.tolist(), strict=True)
    )
    records = read_vc_records(db)
    keypoints = kt.keypoint_tracks(records, ids)
    surface = kt.surface_tracks(records, ids)
    vis = visibility(db)
    seen = np.array(
        [
            vis[i][k - first_vc[i]]
            for i, k in zip(
                surface.image_id.tolist(), surface.point2D_idx.tolist(), strict=True
            )
        ],
        dtype=np.int8,
    )
    loss = with_loss_scale(KeypointBaOptions(), base).loss_scale_px
    assert loss is not None
    models = {
        "keypoints": adjusted(base, keypoints, None, loss),
        "default": base,
        "gba": gba,
    }
    if level != "realistic":
        return {
            row: [p.error_deg for p in evaluate_reconstruction(rec, gt).pairs]
            for row, rec in models.items()
        }
    kept, truth = truth_kept(gt, kt.subset(surface, seen == 1))
    models |= {
        "truth_kept": adjusted(base, keypoints, kept, loss),
        "truth_weighted": adjusted(base, keypoints, kept, loss, weighted=True),
        "truth_similarity": adjusted(
            base, keypoints, with_pixels(kept, similarity_removed(kept, truth)), loss
        ),
        "independent": adjusted(
            base,
            keypoints,
            with_pixels(kept, truth + rng.normal(0, INDEPENDENT_PX, truth.shape)),
            loss,
        ),
    }
    return {
        row: [p.error_deg for p in evaluate_reconstruction(rec, gt).pairs]
        for row, rec in models.items()
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--no-docs", action="store_true")
    parser.add_argument(
        "--level",
        choices=("realistic", "fitted"),
        default="realistic",
        help="the accuracy bench's priors to start from",
    )
    args = parser.parse_args()
    setup_logging()
    t0 = time.perf_counter()
    rng = np.random.default_rng(0)
    errors = {
        s: scene_errors(s, rng, args.level) for group in SCENES.values() for s in group
    }
    rows = {r: ROWS[r] for r in next(iter(errors.values()))}
    summary: dict[str, dict[str, dict[str, float]]] = {}
    for group, scenes in SCENES.items():
        summary[group] = {}
        for row in rows:
            e = np.concatenate([errors[s][row] for s in scenes])
            summary[group][row] = {
                "auc15": 100 * float(pose_auc(e, [15.0])[0]),
                "median_deg": float(np.median(e)),
            }
    elapsed = time.perf_counter() - t0
    suffix = "" if args.level == "realistic" else f"_{args.level}"
    write_json(
        f"gba_bound{suffix}.json",
        {
            "machine": machine(),
            "summary": summary,
            "errors": errors,
            "elapsed_s": elapsed,
        },
    )
    lines = [
        "| evidence, from `map`'s model | "
        + " | ".join(f"{g}: AUC@15 (median deg)" for g in SCENES)
        + " |",
        "|---|" + "---|" * len(SCENES),
    ]
    for row, label in rows.items():
        cells = [
            f"{summary[g][row]['auc15']:.1f} ({summary[g][row]['median_deg']:.2f})"
            for g in SCENES
        ]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    lines += [
        "",
        f"Measured at commit {machine()['commit']} by `.venv/bin/python "
        f"bench/gba_bound.py{'' if not suffix else ' --level ' + args.level}` "
        f"({elapsed / 60:.0f} min; pair errors in "
        f"`bench/out/gba_bound{suffix}.json`), {args.level} priors. Seeds 0 and 1 "
        "of each scene, pairs pooled.",
    ]
    table = "\n".join(lines)
    print(table)
    if not args.no_docs:
        replace_section(DOCS / "gba.md", f"gba-bound{suffix.replace('_', '-')}", table)


if __name__ == "__main__":
    main()
