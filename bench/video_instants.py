"""Each instant of the pose2sim videos mapped on its own: 20 instants, not 5.

`bench/realdata.py` and `bench/evidence.py` map the five instants of
../shared/data/pose2sim_single (and _multi) one at a time; one instant there
(single t090) decides most comparisons of two refinements. The demos' videos
(`bench/static_instants.py`: Pose2Sim's Demo_SinglePerson / Demo_MultiPerson,
pose2sim 0.10.49 on PyPI, the same four calibrated cameras) hold 20 instants
that `colmap-vc frames` can take (one every 5 frames at 60 fps, 83 ms apart, so
neighbours are not independent draws; the five of ../shared/data are among
them). Here every one of them is the user's path for four photos: a database
with the known intrinsics (SIFT, exhaustive matching), `augment` (no
``--static-cameras``), then `map` three ways on the same database: the
keypoints alone (no surface point), as is, and `--gba`.

    .venv/bin/python bench/video_instants.py [--dataset single|multi] [--map-only]

The frames and priors are `bench/static_instants.py`'s (made there, or here the
first time). Writes bench/out/video_instants[_multi].json and the section
"video-instants[-multi]" of docs/results.md: each arm's AUC@15 pooled over the
instants' 120 pairs and per instant, and each arm's difference to `map`,
paired per instant, ± one standard error, (instants won - lost).
"""

from __future__ import annotations

import argparse
import logging
import shutil
import time
from pathlib import Path

import numpy as np
import pycolmap
from common import (
    DOCS,
    OUT,
    WRONG_DEG,
    machine,
    replace_section,
    setup_logging,
    variant_dir,
    write_json,
    wrong_cameras,
)
from realdata import SHARED, _largest_model, load_calibration, make_database
from static_instants import (
    DEMOS,
    _evaluate,
    cam_of,
    frames_and_priors,
    pooled,
    subset_priors,
)

from colmap_vc import cli
from colmap_vc.evaluation import evaluate_poses

logger = logging.getLogger("bench.video_instants")

NO_SURFACE = ["--surface-per-image", "0"]
ARMS: dict[str, list[str]] = {
    "keypoints alone (no surface point)": NO_SURFACE,
    "`map`": [],
    "`map --gba`": ["--gba"],
}
REFERENCE = "`map`"


def run_instant(
    calibration: tuple[dict, dict],
    t: int,
    frames: Path,
    priors: Path,
    row: Path,
    map_only: bool,
) -> dict[str, dict]:
    """`augment` and every arm's `map` on the four frames of instant ``t``
    (``calibration``: :func:`realdata.load_calibration`'s)."""
    calib, gt_shared = calibration
    cameras = {cam_of(n): c for n, c in calib.items()}
    gt_cam = {cam_of(n): g for n, g in gt_shared.items()}
    names = sorted(f"{cam}_f{t:06d}.jpg" for cam in cameras)
    db = row / "database.db"
    done = row / "augmented"  # written once augment has finished on ``db``
    if not (map_only and done.exists()):
        if row.exists():
            shutil.rmtree(row)  # the bench's own output
        shutil.copytree(
            frames, row / "images", ignore=lambda d, fs: set(fs) - set(names)
        )
        make_database(row, names, {n: cameras[cam_of(n)] for n in names}, db)
        sub = subset_priors(priors, names, row / "priors")
        code = cli.main(
            ["augment", str(db), "--priors", str(sub), "--no-show-progress"]
        )
        assert code == 0, f"augment failed ({code})"
        done.write_text("done\n")
    out = {}
    for arm, extra in ARMS.items():  # the same augmented database
        sparse = variant_dir(row, "sparse", extra)
        shutil.rmtree(sparse, ignore_errors=True)  # the bench's own output
        code = cli.main(
            [
                *("map", str(db), "--image-path", str(row / "images")),
                *("--output-path", str(sparse), "--no-show-progress", *extra),
            ]
        )
        rec = _largest_model(sparse) if code == 0 else None
        out[arm] = _evaluate(rec, gt_cam) | {"images": len(names)}
        out[arm]["wrong"] = _wrong(rec, gt_cam)
    return out


def _wrong(rec: pycolmap.Reconstruction | None, gt_cam: dict) -> list[str]:
    """The model's wrong cameras (:func:`common.wrong_cameras`)."""
    if rec is None:
        return []
    pred = {
        cam_of(im.name): im.cam_from_world().matrix()
        for im in rec.images.values()
        if im.has_pose
    }
    return wrong_cameras(evaluate_poses(pred, gt_cam).pairs, set(pred))


def table(results: dict[int, dict[str, dict]]) -> list[str]:
    """Pooled and per-instant AUC@15 of each arm, and its paired difference."""
    instants = list(results)
    lines = [
        "| refinement | registered (wrong) | AUC@15 / 30 / 45, pairs pooled "
        "| median pair error (deg) | mean of the instants' AUC@15 "
        "| - `map`, paired per instant (won-lost) | AUC@15 per instant |",
        "|---|---|---|---|---|---|---|",
    ]
    ref = np.array([results[t][REFERENCE]["auc"]["15"] for t in instants])
    for arm in ARMS:
        runs = [results[t][arm] for t in instants]
        p = pooled(runs)
        auc = np.array([r["auc"]["15"] for r in runs])
        d = auc - ref
        se = d.std(ddof=1) / np.sqrt(len(d)) if len(d) > 1 else 0.0
        diff = (
            "-"
            if arm == REFERENCE
            else f"{d.mean():+.1f} ± {se:.1f} ({(d > 0).sum()}-{(d < 0).sum()})"
        )
        a = p["auc"]
        wrong = sum(len(r["wrong"]) for r in runs)
        lines.append(
            f"| {arm} | {p['registered']}/{p['images']} ({wrong}) "
            f"| {a['15']:.1f} / {a['30']:.1f} / {a['45']:.1f} "
            f"| {p['median_error_deg']:.2f} | {auc.mean():.1f} | {diff} "
            f"| {' '.join(f'{x:.0f}' for x in auc)} |"
        )
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--dataset", choices=sorted(DEMOS), default="single")
    parser.add_argument(
        "--map-only",
        action="store_true",
        help="reuse each instant's augmented database (map changed, augment did not)",
    )
    parser.add_argument("--no-docs", action="store_true")
    args = parser.parse_args()
    setup_logging()
    t0 = time.perf_counter()
    suffix = "" if args.dataset == "single" else f"_{args.dataset}"
    data = SHARED / f"pose2sim_{args.dataset}"
    frames, priors, instants, _ = frames_and_priors(
        args.dataset, OUT / f"static_instants{suffix}", 20
    )
    work = OUT / f"video_instants{suffix}"
    calibration = load_calibration(data)
    results = {}
    for t in sorted(instants):  # frame order: the table reads along the video
        logger.info("%s: frame %d", args.dataset, t)
        results[t] = run_instant(
            calibration, t, frames, priors, work / f"f{t:06d}", args.map_only
        )
    elapsed = time.perf_counter() - t0
    write_json(
        f"video_instants{suffix}.json",
        {"machine": machine(), "elapsed_s": elapsed, "results": results},
    )
    lines = table(results)
    lines += [
        "",
        f"Measured at commit {machine()['commit']} by `.venv/bin/python "
        "bench/video_instants.py"
        f"{'' if args.dataset == 'single' else ' --dataset ' + args.dataset}"
        f"{' --map-only' if args.map_only else ''}` ({elapsed / 60:.0f} min): "
        f"the {len(results)} instants of Pose2Sim's {DEMOS[args.dataset]} videos "
        f"that `colmap-vc frames` takes (frames {min(results)}-{max(results)}, "
        "83 ms apart), each instant's four frames mapped on their own (a database "
        "with the calibration's intrinsics, `augment`, `map`), the six camera "
        "pairs of each against the calibration of "
        f"../shared/data/{data.name}; the instants' pairs pooled, and per instant. "
        "Differences to `map` paired per instant, ± one standard error; a wrong "
        "camera: registered, with a median pair error above "
        f"{WRONG_DEG:.0f} deg; "
        "neighbouring instants are 5 frames apart, so not independent draws.",
    ]
    title = "## Each instant of the videos on its own" + (
        "" if args.dataset == "single" else ", two people and a bystander"
    )
    if not args.no_docs:
        replace_section(
            DOCS / "results.md",
            "video-instants" + suffix.replace("_", "-"),
            title + "\n\n" + "\n".join(lines),
        )
    print("\n".join(lines))


if __name__ == "__main__":
    main()
