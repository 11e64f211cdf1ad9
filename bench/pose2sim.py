"""Real photos: pose2sim_single (4 static cameras around one person, 5 instants).

End to end with the bundled offline estimator: MediaPipe priors, augment, map, eval
against the marker-based calibration. Side by side in the same harness on the same
images: classic COLMAP (SIFT, exhaustive matching, incremental mapping), a keypoint-
only baseline (the MediaPipe landmarks, mapped to the body template's joints, as the
only correspondences: 12 joints + nose, ears, heels and toes, left/right swaps
fixed by the estimator, 5-point RANSAC, multi-view mapping and the keypoint BA) and
colmap-vc (surface VCs + keypoints), both with `colmap-vc map`'s defaults.

- one instant: the 4 images of that instant (5 instants, reported each and pooled);
- five instants: the cameras are static, so the person at 5 instants is 5 people for
  each camera: one image per camera (the t010 photo), its priors holding the 5
  instants' people with the instant as person id, people not occluding each other.

    .venv/bin/python bench/pose2sim.py     (needs `make mediapipe`)

Writes bench/out/pose2sim.json and a section of docs/results.md.
"""

from __future__ import annotations

import json
import logging
import shutil
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pycolmap
from common import DOCS, OUT, ROOT, machine, replace_section, setup_logging, write_json

from colmap_vc import augment, mapping
from colmap_vc.evaluation import (
    THRESHOLDS_DEG,
    Metrics,
    evaluate_poses,
    pose_auc,
)
from colmap_vc.matching import MatchingOptions
from colmap_vc.meshalign import mesh_alignment_poses
from colmap_vc.priors import read_priors, write_priors
from colmap_vc.structs import ImagePrior, ScenePriors
from colmap_vc.verification import VerificationOptions

logger = logging.getLogger("bench.pose2sim")
DATA = ROOT.parent / "shared" / "data" / "pose2sim_single"
INSTANTS = ("t010", "t030", "t050", "t070", "t090")


def load_cameras() -> tuple[
    dict[str, pycolmap.Camera], dict[str, np.ndarray], list[str]
]:
    """pycolmap cameras and GT cam_from_world per image name; camera names."""
    spec = json.loads((DATA / "cameras.json").read_text())
    cameras, poses, names = {}, {}, []
    for cam in spec["cameras"]:
        names.append(cam["name"])
        K = np.array(cam["K"])
        w, h = cam["image_size_wh"]
        params = [K[0, 0], K[1, 1], K[0, 2], K[1, 2], *cam["dist_k1k2p1p2"]]
        for rel in cam["images"].values():
            name = Path(rel).name
            cameras[name] = pycolmap.Camera(
                model="OPENCV", width=w, height=h, params=params
            )
            poses[name] = np.c_[np.array(cam["R"]), np.array(cam["t"])]
    return cameras, poses, names


def make_database(
    images: list[str], cameras: dict[str, pycolmap.Camera], work: Path
) -> Path:
    """SIFT + exhaustive matching with the known intrinsics (what a user would run)."""
    work.mkdir(parents=True, exist_ok=True)
    db = work / "database.db"
    if db.exists():
        db.unlink()
    extraction = pycolmap.FeatureExtractionOptions(num_threads=2)
    extraction.sift.max_num_features = 8192
    for name in images:
        cam = cameras[name]
        reader = pycolmap.ImageReaderOptions(
            camera_model="OPENCV",
            camera_params=",".join(f"{p:.17g}" for p in cam.params),
        )
        pycolmap.extract_features(
            db,
            DATA / "images",
            image_names=[name],
            camera_mode=pycolmap.CameraMode.PER_IMAGE,
            reader_options=reader,
            extraction_options=extraction,
            device=pycolmap.Device.cpu,
        )
    pycolmap.match_exhaustive(
        db,
        matching_options=pycolmap.FeatureMatchingOptions(num_threads=2),
        device=pycolmap.Device.cpu,
    )
    return db


# The keypoint baseline has at most ~19 correspondences per pair: thresholds to match.
FEW = {
    "verification": VerificationOptions(min_num_inliers=8),
    "mapping": mapping.MappingOptions(
        show_progress=False,
        min_num_matches=8,
        init_min_num_inliers=8,
        abs_pose_min_num_inliers=8,
    ),
}


def run_method(
    db: Path,
    priors_dir: Path | None,
    work: Path,
    gt: dict[str, np.ndarray],
    matching: MatchingOptions | None,
    few: bool = False,
) -> Metrics:
    """augment (unless classic) + map + eval on a copy of the database."""
    work.mkdir(parents=True, exist_ok=True)
    run_db = work / "database.db"
    shutil.copyfile(db, run_db)
    if priors_dir is not None:
        augment.run(
            run_db,
            priors_dir,
            augment.AugmentOptions(
                matching=matching or MatchingOptions(),
                show_progress=False,
                verification=FEW["verification"] if few else VerificationOptions(),
                min_num_vcs=8 if few else augment.AugmentOptions().min_num_vcs,
            ),
        )
    options = (
        mapping.COLMAP_DEFAULTS
        if priors_dir is None
        else (FEW["mapping"] if few else mapping.MappingOptions(show_progress=False))
    )
    rec, _ = mapping.run_incremental(run_db, DATA / "images", work / "sparse", options)
    pred = (
        {}
        if rec is None
        else {
            im.name: im.cam_from_world().matrix()
            for im in rec.images.values()
            if im.has_pose
        }
    )
    return evaluate_poses(pred, gt)


def pooled(ms: list[Metrics]) -> dict:
    errors = np.array([p.error_deg for m in ms for p in m.pairs])
    aucs = pose_auc(errors, THRESHOLDS_DEG)
    return {
        "auc": {f"{t:g}": 100 * a for t, a in zip(THRESHOLDS_DEG, aucs, strict=True)},
        "median_error_deg": float(np.median(errors)),
        "registered": sum(m.num_registered for m in ms),
        "images": sum(m.num_images for m in ms),
        "pairs": [round(p.error_deg, 2) for m in ms for p in m.pairs],
    }


def main() -> None:
    setup_logging()
    t0 = time.perf_counter()
    out = OUT / "pose2sim"
    cameras, gt_all, cam_names = load_cameras()
    priors_dir = out / "priors"
    if not (priors_dir / "priors.json").exists():
        from colmap_vc.estimators import EstimatorOptions, run_estimator

        run_estimator(
            DATA / "images",
            priors_dir,
            cameras=cameras,
            options=EstimatorOptions(show_progress=False),
        )
    priors = read_priors(priors_dir)
    methods = {
        "keypoint-only baseline": MatchingOptions(use_surface_samples=False),
        "colmap-vc (VCs + keypoints)": MatchingOptions(),
    }
    results: dict[str, dict[str, list[Metrics]]] = {}
    for instant in INSTANTS:
        images = [f"{c}_{instant}.jpg" for c in cam_names]
        gt = {n: gt_all[n] for n in images}
        db = make_database(images, cameras, out / instant)
        results.setdefault("classic COLMAP", {}).setdefault(instant, []).append(
            run_method(db, None, out / instant / "classic", gt, None)
        )
        sub = out / instant / "priors"
        write_priors(
            ScenePriors(images={n: priors.images[n] for n in images}),
            sub,
            templates={"anny": next(iter(priors.images.values())).persons[0].faces},
        )
        results.setdefault("mesh alignment", {}).setdefault(instant, []).append(
            evaluate_poses(mesh_alignment_poses(read_priors(sub)), gt)
        )
        for name, opts in methods.items():
            results.setdefault(name, {}).setdefault(instant, []).append(
                run_method(
                    db,
                    sub,
                    out / instant / name.split()[0],
                    gt,
                    opts,
                    few=name.startswith("keypoint"),
                )
            )
    # Five instants: one image per camera holding the person of every instant.
    rep = {c: f"{c}_t010.jpg" for c in cam_names}
    merged = {}
    for c in cam_names:
        persons = []
        for k, instant in enumerate(INSTANTS):
            for p in priors.images[f"{c}_{instant}.jpg"].persons[
                :1
            ]:  # one person per instant
                persons.append(replace(p, person_id=k))
        merged[rep[c]] = ImagePrior(image_name=rep[c], persons=tuple(persons))
    merged_dir = out / "all" / "priors"
    write_priors(
        ScenePriors(images=merged),
        merged_dir,
        templates={"anny": next(iter(priors.images.values())).persons[0].faces},
    )
    gt = {rep[c]: gt_all[rep[c]] for c in cam_names}
    db = make_database(list(rep.values()), cameras, out / "all")
    five = {
        "classic COLMAP": run_method(db, None, out / "all" / "classic", gt, None),
        "mesh alignment": evaluate_poses(
            mesh_alignment_poses(read_priors(merged_dir)), gt
        ),
    }
    for name, opts in methods.items():
        five[name] = run_method(
            db,
            merged_dir,
            out / "all" / name.split()[0],
            gt,
            replace(opts, people_occlude=False),
            few=name.startswith("keypoint"),
        )
    summary = {
        "one_instant_pooled": {
            m: pooled([x for ms in by_i.values() for x in ms])
            for m, by_i in results.items()
        },
        "one_instant_each": {
            m: {i: pooled(ms) for i, ms in by_i.items()} for m, by_i in results.items()
        },
        "five_instants": {m: pooled([x]) for m, x in five.items()},
    }
    write_json(
        "pose2sim.json",
        {
            "machine": machine(),
            "summary": summary,
            "elapsed_s": time.perf_counter() - t0,
        },
    )
    lines = [
        "| setting | method | registered | AUC@15 | AUC@30 | AUC@45 "
        "| median pair error (deg) |",
        "|---|---|---|---|---|---|---|",
    ]
    for setting, table in (
        ("one instant (5 instants pooled, 30 pairs)", summary["one_instant_pooled"]),
        ("five instants (6 pairs)", summary["five_instants"]),
    ):
        for method, r in table.items():
            auc = r["auc"]
            lines.append(
                f"| {setting} | {method} | {r['registered']}/{r['images']} "
                f"| {auc['15']:.1f} | {auc['30']:.1f} | {auc['45']:.1f} "
                f"| {r['median_error_deg']:.1f} |"
            )
    lines += [
        "",
        "Per instant (AUC@15/30/45, 6 pairs each):",
        "",
        "| method | " + " | ".join(INSTANTS) + " |",
        "|---|" + "---|" * len(INSTANTS),
    ]
    for method, by_i in summary["one_instant_each"].items():
        lines.append(
            f"| {method} | "
            + " | ".join(
                f"{r['auc']['15']:.0f}/{r['auc']['30']:.0f}/{r['auc']['45']:.0f}"
                for r in by_i.values()
            )
            + " |"
        )
    lines += [
        "",
        "Per-pair errors (deg), five instants: "
        + "; ".join(f"{m}: {r['pairs']}" for m, r in summary["five_instants"].items()),
        "",
        f"Measured at commit {machine()['commit']} by "
        "`.venv/bin/python bench/pose2sim.py` (after `make mediapipe`); raw numbers in "
        "`bench/out/pose2sim.json`.",
    ]
    replace_section(
        DOCS / "results.md",
        "pose2sim",
        "## Real photos: pose2sim_single\n\n" + "\n".join(lines),
    )
    print("\n".join(lines))


if __name__ == "__main__":
    main()
