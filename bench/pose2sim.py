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

    .venv/bin/python bench/pose2sim.py [--seeds 0 1 2]     (needs `make mediapipe`)

Writes bench/out/pose2sim.json and a section of docs/results.md.
"""

from __future__ import annotations

import argparse
import json
import logging
import shutil
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pycolmap
import realdata
from common import DOCS, OUT, ROOT, machine, replace_section, setup_logging, write_json

from colmap_vc import augment, mapping
from colmap_vc.baselines import colmap_incremental
from colmap_vc.evaluation import (
    THRESHOLDS_DEG,
    Metrics,
    evaluate_poses,
    pose_auc,
    poses_by_name,
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
    cameras, poses = realdata.load_calibration(DATA)
    spec = json.loads((DATA / "cameras.json").read_text())
    return cameras, poses, [cam["name"] for cam in spec["cameras"]]


def make_database(
    images: list[str], cameras: dict[str, pycolmap.Camera], work: Path
) -> Path:
    """SIFT + exhaustive matching with the known intrinsics (what a user would run)."""
    db = work / "database.db"
    realdata.make_database(DATA, images, cameras, db)
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
    seed: int = 0,
) -> Metrics:
    """augment (unless classic) + map + eval on a copy of the database.

    ``seed`` seeds the RANSAC of verification and COLMAP's mapper (the spread over
    seeds is the run-to-run noise of a result).
    """
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
                verification=replace(
                    FEW["verification"] if few else VerificationOptions(), seed=seed
                ),
                min_num_vcs=8 if few else augment.AugmentOptions().min_num_vcs,
            ),
        )
    shutil.rmtree(work / "sparse", ignore_errors=True)  # the bench's own output
    if priors_dir is None:  # classic: COLMAP itself
        rec = colmap_incremental(run_db, DATA / "images", work / "sparse", seed)
    else:
        options = FEW["mapping"] if few else mapping.MappingOptions(show_progress=False)
        rec, _ = mapping.run_incremental(
            run_db, DATA / "images", work / "sparse", replace(options, seed=seed)
        )
    pred = {} if rec is None else poses_by_name(rec)
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


def estimate(cameras: dict[str, pycolmap.Camera], out: Path) -> ScenePriors:
    """The MediaPipe priors of all 20 photos (made once, then read back)."""
    priors_dir = out / "priors"
    if not (priors_dir / "priors.json").exists():
        from colmap_vc.estimators import EstimatorOptions, run_estimator

        run_estimator(
            DATA / "images",
            priors_dir,
            cameras=cameras,
            options=EstimatorOptions(show_progress=False),
        )
    return read_priors(priors_dir)


def prepare(
    cameras: dict[str, pycolmap.Camera],
    cam_names: list[str],
    priors: ScenePriors,
    out: Path,
) -> dict[str, tuple[Path, Path]]:
    """Per setting (each instant, and "all"): its SIFT database and priors folder.

    "all" is the five instants of the static cameras: one image per camera (the t010
    photo), its priors holding the person of every instant, the instant as person id.
    """
    faces = {"anny": next(iter(priors.images.values())).persons[0].faces}
    setups = {}
    for instant in INSTANTS:
        images = [f"{c}_{instant}.jpg" for c in cam_names]
        db = make_database(images, cameras, out / instant)
        sub = out / instant / "priors"
        write_priors(
            ScenePriors(images={n: priors.images[n] for n in images}),
            sub,
            templates=faces,
        )
        setups[instant] = (db, sub)
    rep = {c: f"{c}_t010.jpg" for c in cam_names}
    merged = {}
    for c in cam_names:
        persons = [
            replace(p, person_id=k)
            for k, instant in enumerate(INSTANTS)
            for p in priors.images[f"{c}_{instant}.jpg"].persons[:1]  # one per instant
        ]
        merged[rep[c]] = ImagePrior(image_name=rep[c], persons=tuple(persons))
    merged_dir = out / "all" / "priors"
    write_priors(ScenePriors(images=merged), merged_dir, templates=faces)
    setups["all"] = (
        make_database(list(rep.values()), cameras, out / "all"),
        merged_dir,
    )
    return setups


def run_seed(
    seed: int,
    setups: dict[str, tuple[Path, Path]],
    gt_all: dict[str, np.ndarray],
    cam_names: list[str],
    out: Path,
) -> dict:
    """Every method on every setting with one seed -> the summary dict."""
    methods = {
        "keypoint-only baseline": MatchingOptions(use_surface_samples=False),
        "colmap-vc (VCs + keypoints)": MatchingOptions(),
    }
    results: dict[str, dict[str, list[Metrics]]] = {}
    five: dict[str, Metrics] = {}
    for setting, (db, sub) in setups.items():
        instant = "t010" if setting == "all" else setting
        gt = {f"{c}_{instant}.jpg": gt_all[f"{c}_{instant}.jpg"] for c in cam_names}
        work = out / f"seed{seed}" / setting
        row = {
            "classic COLMAP": run_method(
                db, None, work / "classic", gt, None, seed=seed
            ),
            "mesh alignment": evaluate_poses(
                mesh_alignment_poses(read_priors(sub)), gt
            ),
        }
        for name, opts in methods.items():
            row[name] = run_method(
                db,
                sub,
                work / name.split()[0],
                gt,
                replace(opts, people_occlude=setting != "all"),
                few=name.startswith("keypoint"),
                seed=seed,
            )
        for name, m in row.items():
            if setting == "all":
                five[name] = m
            else:
                results.setdefault(name, {}).setdefault(setting, []).append(m)
    return {
        "one_instant_pooled": {
            m: pooled([x for ms in by_i.values() for x in ms])
            for m, by_i in results.items()
        },
        "one_instant_each": {
            m: {i: pooled(ms) for i, ms in by_i.items()} for m, by_i in results.items()
        },
        "five_instants": {m: pooled([x]) for m, x in five.items()},
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument(
        "--seeds",
        type=int,
        nargs="+",
        default=[0, 1, 2],
        help="RANSAC and mapper seeds; the tables show the first, a line the spread",
    )
    args = parser.parse_args()
    setup_logging()
    t0 = time.perf_counter()
    out = OUT / "pose2sim"
    cameras, gt_all, cam_names = load_cameras()
    priors = estimate(cameras, out)
    setups = prepare(cameras, cam_names, priors, out)
    by_seed = {s: run_seed(s, setups, gt_all, cam_names, out) for s in args.seeds}
    summary = by_seed[args.seeds[0]]
    write_json(
        "pose2sim.json",
        {
            "machine": machine(),
            "seeds": args.seeds,
            "summary": summary,
            "by_seed": by_seed,
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
        f"Seeds {', '.join(map(str, args.seeds))} (RANSAC and mapper; the tables show "
        f"seed {args.seeds[0]}), AUC@15/30/45:",
        "",
        "| setting | method | " + " | ".join(f"seed {x}" for x in args.seeds) + " |",
        "|---|---|" + "---|" * len(args.seeds),
        *(
            f"| {label} | {method} | "
            + " | ".join(
                "/".join(f"{a:.1f}" for a in by_seed[x][key][method]["auc"].values())
                for x in args.seeds
            )
            + " |"
            for key, label in (
                ("one_instant_pooled", "one instant"),
                ("five_instants", "five instants"),
            )
            for method in ("keypoint-only baseline", "colmap-vc (VCs + keypoints)")
        ),
        "",
        "Per-pair errors (deg), five instants: "
        + "; ".join(f"{m}: {r['pairs']}" for m, r in summary["five_instants"].items()),
        "",
        f"Measured at commit {machine()['commit']} by "
        "`.venv/bin/python bench/pose2sim.py --seeds "
        f"{' '.join(map(str, args.seeds))}` (after `make mediapipe`); raw numbers in "
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
