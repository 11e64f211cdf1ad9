"""More instants of static cameras: 1, 2, 5, 10, 20 instants from the pose2sim videos.

The user's path for videos of static cameras (docs/real-data.md, "Static cameras"):
`colmap-vc frames` on the four videos of Pose2Sim's Demo_SinglePerson (or, with
``--dataset multi``, Demo_MultiPerson: two people and a bystander) with their frame
offsets, `colmap-vc priors`, then `augment` and `map` with
``--static-cameras '(cam\\d+)_f'``, against the calibration of ../shared/data/
pose2sim_single or pose2sim_multi (the same cameras). The videos ship inside the
`pose2sim` wheel on PyPI (version 0.10.49); the bench downloads that wheel once into
bench/out/cache.

The instants are chosen once, 20 of them, by `frames`' farthest-point sampling; its
order is greedy, so its first N instants are the N it would choose, and each row uses
them. Priors are computed once for the 80 frames (the estimator works per image).

    .venv/bin/python bench/static_instants.py [--instants 1 2 5 10 20]
    .venv/bin/python bench/static_instants.py --dataset multi   # the second demo
    .venv/bin/python bench/static_instants.py --cameras 2 --instants 20   # every pair

`map` runs four times on each augmented database: with `--no-gravity`, with
`--no-weigh-repeats` (every instant's keypoints as independent, the default before
the still people's weights), as is, and with `--gba` (the generalized bundle
adjustment, issue 12).

``--cameras 2`` (or 3) maps every subset of that many cameras on its own, each at
every number of instants: what two static cameras filming the same people give.

Writes bench/out/static_instants.json and the "instants" section of docs/results.md
(with ``--dataset multi``: static_instants_multi.json, "instants-multi"; with
``--cameras 2``: static_instants_c2.json, "instants-c2", and so on).
"""

from __future__ import annotations

import argparse
import json
import logging
import shutil
import subprocess
import sys
import time
import zipfile
from itertools import combinations
from pathlib import Path

import numpy as np
from common import (
    DOCS,
    OUT,
    machine,
    replace_section,
    setup_logging,
    variant_dir,
    write_json,
)
from realdata import SHARED, _largest_model, load_calibration, make_database

from colmap_vc import cli
from colmap_vc.evaluation import (
    THRESHOLDS_DEG,
    camera_distance_ratio,
    evaluate_poses,
    pose_auc,
)
from colmap_vc.frames import extract_frames

logger = logging.getLogger("bench.static_instants")

WHEEL = "pose2sim-0.10.49-py3-none-any.whl"
DEMOS = {"single": "Demo_SinglePerson", "multi": "Demo_MultiPerson"}
PATTERN = r"(cam\d+)_f"
VARIANTS = {
    "map --no-gravity": ["--no-gravity"],
    "map --no-weigh-repeats": ["--no-weigh-repeats"],
    "map": [],
    "map --gba": ["--gba"],
}
CACHE = OUT / "cache"


def videos(demo: str) -> list[Path]:
    """The four videos of one of pose2sim's demos, from the cached wheel."""
    wheel = CACHE / WHEEL
    if not wheel.exists():
        CACHE.mkdir(parents=True, exist_ok=True)
        logger.info("downloading %s once into %s", WHEEL, CACHE)
        subprocess.run(
            [
                *(sys.executable, "-m", "pip", "download", "pose2sim==0.10.49"),
                *("--no-deps", "--only-binary", ":all:", "-d", str(CACHE)),
            ],
            check=True,
        )
    out = CACHE / demo
    paths = [out / f"cam0{k}.mp4" for k in range(1, 5)]
    if not all(p.exists() for p in paths):
        out.mkdir(parents=True, exist_ok=True)
        with zipfile.ZipFile(wheel) as z:
            for p in paths:
                p.write_bytes(z.read(f"Pose2Sim/{demo}/videos/{p.name}"))
    return paths


def subset_priors(priors: Path, names: list[str], out: Path) -> Path:
    """A priors folder holding only ``names`` (the same per-image files)."""
    spec = json.loads((priors / "priors.json").read_text())
    spec["images"] = {n: spec["images"][n] for n in names}
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    for sub in ("images", "templates"):
        (out / sub).symlink_to((priors / sub).resolve(), target_is_directory=True)
    (out / "priors.json").write_text(json.dumps(spec))
    return out


def cam_of(name: str) -> str:
    """The camera of a frame's name (cam01_f000123.jpg -> cam01)."""
    return name.split("_")[0]


def frames_and_priors(
    dataset: str, work: Path, most: int, step: int = 5
) -> tuple[Path, Path, list[int], list[int]]:
    """The videos' frames at ``most`` instants (`colmap-vc frames`, farthest-point
    order, candidates every ``step`` frames) and their priors, made once in
    ``work`` -> (frames folder, priors folder, the instants in that order, the
    cameras' frame offsets)."""
    data = SHARED / f"pose2sim_{dataset}"
    frames = work / "frames"
    offsets = [
        c["video_frame_offset"]
        for c in json.loads((data / "cameras.json").read_text())["cameras"]
    ]
    summary = extract_frames(
        videos(DEMOS[dataset]), frames, offsets=offsets, num_instants=most, step=step
    )
    instants = [int(t) for t in summary.instants]  # farthest-point order
    priors = work / "priors"
    spec = priors / "priors.json"
    have = set(json.loads(spec.read_text())["images"]) if spec.exists() else set()
    if not set(summary.written) <= have:  # none yet, or made for fewer instants
        names = sorted(summary.written)
        calib, _ = load_calibration(data)
        cameras = {n.split("_")[0]: c for n, c in calib.items()}
        db = work / "all.db"
        (work / "_all").mkdir(exist_ok=True)
        link = work / "_all" / "images"
        if not link.exists():
            link.symlink_to(frames.resolve(), target_is_directory=True)
        make_database(  # the priors read its cameras: no matching
            work / "_all",
            names,
            {n: cameras[n.split("_")[0]] for n in names},
            db,
            match=False,
        )
        code = cli.main(
            [
                *("priors", str(frames), "--output", str(priors)),
                *("--database", str(db), "--no-progress"),
                *(["--overwrite"] if have else []),
            ]
        )
        assert code == 0, f"priors failed ({code})"
    return frames, priors, instants, offsets


def run(
    data: Path,
    num: int,
    instants: list[int],
    work: Path,
    frames: Path,
    priors: Path,
    cams: tuple[str, ...],
    map_only: bool = False,
    variants: dict[str, list[str]] | None = None,
    match: bool = True,
) -> dict:
    """``augment`` and ``map`` on the frames of cameras ``cams`` at the first ``num``
    instants -> variant -> accuracy against the calibration of those cameras.
    ``variants``: `map`'s arms (default :data:`VARIANTS`); ``match=False``: no
    classic matches in the database."""
    calib, gt_shared = load_calibration(data)
    cameras = {cam_of(n): c for n, c in calib.items()}
    gt_cam = {cam_of(n): g for n, g in gt_shared.items() if cam_of(n) in cams}
    names = sorted(f"{cam}_f{t:06d}.jpg" for cam in cams for t in instants[:num])
    every = len(cams) == len(cameras)
    row = work / (f"n{num:02d}" if every else f"n{num:02d}_{'-'.join(cams)}")
    db = row / "database.db"
    args = ["--static-cameras", PATTERN, "--no-show-progress"]
    seconds = 0.0
    done = row / "augmented"  # written once augment has finished on ``db``
    if not (map_only and done.exists()):
        if row.exists():
            shutil.rmtree(row)  # the bench's own output
        shutil.copytree(
            frames, row / "images", ignore=lambda d, fs: set(fs) - set(names)
        )
        make_database(row, names, {n: cameras[cam_of(n)] for n in names}, db, match)
        sub = subset_priors(priors, names, row / "priors")
        t0 = time.perf_counter()
        code = cli.main(["augment", str(db), "--priors", str(sub), *args])
        assert code == 0, f"augment failed ({code})"
        seconds = time.perf_counter() - t0
        done.write_text(f"{seconds:.1f} s\n")
    out = {}
    for variant, extra in (variants or VARIANTS).items():  # the same database
        sparse = variant_dir(row, "sparse", extra)
        shutil.rmtree(sparse, ignore_errors=True)  # the bench's own output
        t0 = time.perf_counter()
        code = cli.main(
            [
                *("map", str(db), "--image-path", str(row / "images")),
                *("--output-path", str(sparse), *args, *extra),
            ]
        )
        out[variant] = _evaluate(_largest_model(sparse) if code == 0 else None, gt_cam)
        out[variant] |= {
            "instants": instants[:num],
            "cameras": list(cams),
            "images": len(names),
            "seconds_augment_map": seconds + time.perf_counter() - t0,
            "seconds_augment": seconds,  # 0: reused (--map-only)
            "map_timings_s": _map_timings(sparse),
        }
    return out


def _map_timings(sparse: Path) -> dict[str, float]:
    """`map`'s own timings (its map_options.json), {} when it wrote no model."""
    spec = sparse / "0" / "map_options.json"
    return json.loads(spec.read_text())["timings_s"] if spec.exists() else {}


def _scores(errors: np.ndarray) -> dict:
    """AUC at each threshold (percent) and the median of pair errors (deg)."""
    aucs = pose_auc(errors, THRESHOLDS_DEG)
    return {
        "auc": {f"{t:g}": 100 * a for t, a in zip(THRESHOLDS_DEG, aucs, strict=True)},
        "median_error_deg": float(np.median(errors)),
    }


def _evaluate(rec, gt_cam: dict) -> dict:
    """Pose accuracy of one model against the calibration (its cameras' pairs)."""
    pred = {}
    if rec is not None:
        pred = {
            cam_of(im.name): im.cam_from_world().matrix()
            for im in rec.images.values()
            if im.has_pose
        }
    metrics = evaluate_poses(pred, gt_cam)  # one pose per camera
    errors = np.array([p.error_deg for p in metrics.pairs])
    return {
        "registered": 0 if rec is None else int(rec.num_reg_images()),
        **_scores(errors),
        "rotation_deg": [round(p.rotation_deg, 2) for p in metrics.pairs],
        "pairs": [round(float(e), 2) for e in errors],
        "distance_ratio": camera_distance_ratio(pred, gt_cam),
    }


def pooled(runs: list[dict]) -> dict:
    """One table row from runs of camera subsets: their pairs pooled (one run: as
    it is)."""
    if len(runs) == 1:
        return runs[0]
    errors = np.array([e for r in runs for e in r["pairs"]])
    return {
        **_scores(errors),
        "pairs": errors.tolist(),
        "registered": sum(r["registered"] for r in runs),
        "images": sum(r["images"] for r in runs),
        "distance_ratio": float(np.nanmedian([r["distance_ratio"] for r in runs])),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--dataset", choices=sorted(DEMOS), default="single")
    parser.add_argument("--instants", nargs="+", type=int, default=[1, 2, 5, 10, 20])
    parser.add_argument(
        "--cameras",
        type=int,
        default=4,
        help="cameras per run: every subset of this many, each mapped on its own",
    )
    parser.add_argument(
        "--map-only",
        action="store_true",
        help="reuse each row's augmented database where augment finished on it (map "
        "changed, augment did not)",
    )
    args = parser.parse_args()
    setup_logging()
    suffix = "" if args.dataset == "single" else f"_{args.dataset}"
    data = SHARED / f"pose2sim_{args.dataset}"
    demo = DEMOS[args.dataset]
    work = OUT / f"static_instants{suffix}"
    frames, priors, instants, offsets = frames_and_priors(
        args.dataset, work, max(args.instants)
    )
    everyone = tuple(sorted({cam_of(n) for n in load_calibration(data)[0]}))
    subsets = list(combinations(everyone, args.cameras))
    results = {
        n: {
            "-".join(cams): run(
                data, n, instants, work, frames, priors, cams, args.map_only
            )
            for cams in subsets
        }
        for n in args.instants
    }
    tag = suffix + ("" if args.cameras == len(everyone) else f"_c{args.cameras}")
    write_json(f"static_instants{tag}.json", {"machine": machine(), "results": results})
    lines = [
        "| instants | `map` | images | registered | AUC@15 | AUC@30 | AUC@45 "
        "| median pair error (deg) | pair errors (deg) "
        "| camera distances / calibration |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for n, by_subset in results.items():
        for variant in VARIANTS:
            runs = [r[variant] for r in by_subset.values()]
            r = pooled(runs)
            a = r["auc"]
            lines.append(
                f"| {n} | `{variant}` | {r['images']} "
                f"| {r['registered']}/{r['images']} | {a['15']:.1f} "
                f"| {a['30']:.1f} | {a['45']:.1f} "
                f"| {r['median_error_deg']:.2f} "
                f"| {' '.join(f'{e:.1f}' for e in sorted(r['pairs']))} "
                f"| {r['distance_ratio']:.3f} |"
            )
    lines += [
        "",
        f"Measured at commit {machine()['commit']} by `.venv/bin/python "
        "bench/static_instants.py"
        f"{'' if args.dataset == 'single' else ' --dataset ' + args.dataset}"
        f"{'' if args.cameras == len(everyone) else f' --cameras {args.cameras}'}"
        f" --instants {' '.join(map(str, args.instants))}"
        f"{' --map-only' if args.map_only else ''}`: "
        f"the four videos of Pose2Sim's {demo} (pose2sim 0.10.49 on PyPI, "
        f"frame offsets {offsets} from ../shared/data/{data.name}/cameras.json), "
        "`colmap-vc frames` (20 instants by farthest-point sampling; the first N "
        "for N instants), `priors`, `augment --static-cameras "
        f"'{PATTERN}'`, then `map` with the same option on it, with `--no-gravity`, "
        "with `--no-weigh-repeats` (every instant's keypoints independent), as is "
        "and with `--gba`; "
        + (
            "the six camera pairs against the calibration."
            if args.cameras == len(everyone)
            else f"every {args.cameras} of the {len(everyone)} cameras mapped on "
            f"their own ({len(subsets)} runs per row), their pairs against the "
            "calibration, pooled; camera distances: the median over the runs."
        )
        + (
            " `--map-only`: `map` on the augmented databases of the previous run."
            if args.map_only
            else ""
        ),
    ]
    title = (
        "## Static cameras: more instants from the videos"
        + ("" if args.dataset == "single" else ", two people and a bystander")
        + ("" if args.cameras == len(everyone) else f", {args.cameras} cameras")
    )
    replace_section(
        DOCS / "results.md",
        "instants" + tag.replace("_", "-"),
        title + "\n\n" + "\n".join(lines),
    )
    print("\n".join(lines))


if __name__ == "__main__":
    main()
