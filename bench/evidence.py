"""Each kind of evidence on real photos: keypoints, surface VCs and the cameras' up.

The same augmented databases are mapped with one kind of evidence added at a time:
pose2sim_single and pose2sim_multi, each instant on its own (the databases of
`bench/realdata.py`) and all 20 images with static cameras (those of
`bench/static_cameras.py`). Run those two benches first; this one only re-maps.

Arms (`colmap-vc map` options):

- keypoints alone: ``--surface-per-image 0 --no-gravity``
  (the mapper still uses the surface VCs to find its model; the refinement then
  keeps the keypoint tracks and classic points only);
- keypoints + up: the same with the cameras' up (`map`'s gravity step);
- keypoints + surface: ``--no-gravity``;
- keypoints + surface + up: `map` as is;
- the GBA: ``--gba`` (surface tracks by identity, correlated noise model) with the up.

    .venv/bin/python bench/evidence.py      (about 3 min)

Writes bench/out/evidence.json and the "evidence" section of docs/results.md.

``--seeds 0 1 ...`` maps the per-instant databases of ``bench/realdata.py
--seeds`` (augment's RANSAC and the mapper at that seed) with every arm instead,
and compares each arm with `map` paired per seed: whether an arm's difference is
more than the run-to-run noise. Writes bench/out/evidence_seeds.json and the
"evidence-seeds" section.
"""

from __future__ import annotations

import argparse
import logging
import shutil
import time
from pathlib import Path

import numpy as np
from common import DOCS, OUT, machine, replace_section, setup_logging, write_json
from realdata import INSTANTS, SHARED, _largest_model, load_calibration, pooled
from static_cameras import PATTERN

from colmap_vc import cli
from colmap_vc.evaluation import evaluate_poses, poses_by_name, tilt_errors_deg

logger = logging.getLogger("bench.evidence")

UP_WORLD = np.array([0.0, 0.0, 1.0])  # pose2sim's world (cameras.json): Z up

NO_SURFACE = ["--surface-per-image", "0"]
ARMS: dict[str, list[str]] = {
    "keypoints alone": [*NO_SURFACE, "--no-gravity"],
    "keypoints + up": NO_SURFACE,
    "keypoints + surface": ["--no-gravity"],
    "keypoints + surface + up (`map`)": [],
    "GBA (`map --gba`): surface tracks by identity + up": ["--gba"],
}


def _map(db: Path, images: Path, sparse: Path, extra: list[str]) -> dict:
    """`map` on ``db`` into ``sparse`` -> the registered poses by name (none: {})."""
    shutil.rmtree(sparse, ignore_errors=True)  # the bench's own output
    code = cli.main(
        [
            "map",
            str(db),
            "--image-path",
            str(images),
            "--output-path",
            str(sparse),
            "--no-show-progress",
            *extra,
        ]
    )
    rec = _largest_model(sparse) if code == 0 else None
    return {} if rec is None else poses_by_name(rec)


def run_seed(ds: str, arm: list[str], seed: int, work: Path) -> list[float]:
    """One arm on one dataset's per-instant databases of one seed -> AUC@15 each."""
    data = SHARED / f"pose2sim_{ds}"
    _, gt = load_calibration(data)
    aucs = []
    for instant in INSTANTS:
        where = "order0" if seed == 0 else f"seed{seed}"
        db = OUT / "realdata" / ds / instant / where / "database.db"
        if not db.exists():
            raise SystemExit(f"{db} missing: run bench/realdata.py --seeds first")
        pred = _map(db, data / "images", work / instant, [*arm, "--seed", str(seed)])
        now = {n: g for n, g in gt.items() if instant in n}
        aucs.append(float(evaluate_poses(pred, now).auc["15"]))
    return aucs


def seeds_table(results: dict, seeds: list[int]) -> str:
    """Mean per-instant AUC@15 over seeds and each arm's paired difference to `map`."""
    ref = "keypoints + surface + up (`map`)"
    datasets = list(next(iter(results.values())))
    lines = [
        "| evidence in the refinement | "
        + " | ".join(
            f"pose2sim_{ds}: mean AUC@15 (per seed) | - `map` (seeds won-lost)"
            for ds in datasets
        )
        + " |",
        "|---|" + "---|---|" * len(datasets),
    ]
    for arm, per_ds in results.items():
        cells = []
        for ds in datasets:
            # A seed's score: the mean of its instants' AUC@15 (4 images each).
            mine = np.array([np.mean(per_ds[ds][str(s)]) for s in seeds])
            base = np.array([np.mean(results[ref][ds][str(s)]) for s in seeds])
            d = mine - base
            se = d.std(ddof=1) / np.sqrt(len(d)) if len(d) > 1 else 0.0
            each = " ".join(f"{x:.1f}" for x in mine)
            cells.append(f"{mine.mean():.1f} ({each})")
            cells.append(
                "-"
                if arm == ref
                else f"{d.mean():+.1f} ± {se:.1f} ({(d > 0).sum()}-{(d < 0).sum()})"
            )
        lines.append(f"| {arm} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main_seeds(datasets: list[str], seeds: list[int], no_docs: bool) -> None:
    t0 = time.perf_counter()
    results: dict[str, dict] = {}
    for name, arm in ARMS.items():
        key = f"arm{list(ARMS).index(name)}"
        for ds in datasets:
            for seed in seeds:
                work = OUT / "evidence_seeds" / ds / key / f"seed{seed}"
                aucs = run_seed(ds, arm, seed, work)
                results.setdefault(name, {}).setdefault(ds, {})[str(seed)] = aucs
                logger.info("%s %s seed %d: %s", ds, name, seed, aucs)
    seconds = time.perf_counter() - t0
    info = machine()
    write_json(
        "evidence_seeds.json",
        {"machine": info, "seconds": seconds, "seeds": seeds, "results": results},
    )
    body = seeds_table(results, seeds)
    print(body)
    if no_docs:
        return
    replace_section(
        DOCS / "results.md",
        "evidence-seeds",
        "### Each kind of evidence, over seeds\n\n"
        + body
        + "\n\nThe per-instant arms of the table above, on the databases of "
        "`bench/realdata.py --seeds` (augment's RANSAC and the mapper at each "
        "seed; seed 0 is the table above's). A seed's score is the mean of its "
        "five instants' AUC@15 (4 images each); differences to `map` are paired "
        "per seed, ± one standard error. "
        f"Measured at commit {info['commit']} by `.venv/bin/python "
        f"bench/evidence.py --seeds {' '.join(map(str, seeds))}` "
        f"({seconds / 60:.0f} min); raw numbers in "
        "`bench/out/evidence_seeds.json`.",
    )


def run(ds: str, arm: list[str], work: Path) -> dict[str, dict]:
    """One arm on one dataset: per instant (4 images each) and static cameras."""
    data = SHARED / f"pose2sim_{ds}"
    _, gt = load_calibration(data)
    per_instant, tilt = [], []
    for instant in INSTANTS:
        db = OUT / "realdata" / ds / instant / "order0" / "database.db"
        if not db.exists():
            raise SystemExit(f"{db} missing: run bench/realdata.py first")
        pred = _map(db, data / "images", work / instant, arm)
        now = {n: g for n, g in gt.items() if instant in n}
        per_instant.append(evaluate_poses(pred, now))
        tilt.extend(tilt_errors_deg(pred, now, UP_WORLD).values())
    db = OUT / "static_cameras" / ds / "database.db"
    if not db.exists():
        raise SystemExit(f"{db} missing: run bench/static_cameras.py first")
    pred = _map(
        db, data / "images", work / "static", [*arm, "--static-cameras", PATTERN]
    )
    static, static_tilt = [], []
    for instant in INSTANTS:
        now = {n: g for n, g in gt.items() if instant in n}
        mine = {n: p for n, p in pred.items() if instant in n}
        static.append(evaluate_poses(mine, now))
        static_tilt.extend(tilt_errors_deg(mine, now, UP_WORLD).values())
    return {
        "per_instant": {**pooled(per_instant), "tilt_deg": _median(tilt)},
        "per_instant_each": [round(m.auc["15"], 1) for m in per_instant],
        "static": {**pooled(static), "tilt_deg": _median(static_tilt)},
    }


def _median(values: list[float]) -> float | None:
    return float(np.median(values)) if values else None


def _cell(r: dict) -> str:
    tilt = "-" if r.get("tilt_deg") is None else f"{r['tilt_deg']:.2f}"
    return (
        f"{r['auc']['15']:.1f} ({r['median_error_deg']:.2f}; {tilt}), "
        f"{r['registered']}/{r['images']}"
    )


def table(results: dict) -> str:
    datasets = list(next(iter(results.values())))
    head = " | ".join(
        f"pose2sim_{ds}, {where}"
        for ds in datasets
        for where in ("per instant", "static cameras")
    )
    lines = [
        f"| evidence in the refinement | {head} |",
        "|---|" + "---|" * (2 * len(datasets)),
    ]
    for arm, per_ds in results.items():
        cells = " | ".join(
            f"{_cell(per_ds[ds]['per_instant'])} | {_cell(per_ds[ds]['static'])}"
            for ds in datasets
        )
        lines.append(f"| {arm} | {cells} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--datasets", nargs="+", default=["single", "multi"])
    parser.add_argument("--no-docs", action="store_true")
    parser.add_argument(
        "--seeds",
        nargs="+",
        type=int,
        help="per instant only, on the databases of `bench/realdata.py --seeds`",
    )
    args = parser.parse_args()
    setup_logging()
    if args.seeds:
        main_seeds(args.datasets, args.seeds, args.no_docs)
        return
    t0 = time.perf_counter()
    results: dict[str, dict] = {}
    for name, arm in ARMS.items():
        for ds in args.datasets:
            key = f"arm{list(ARMS).index(name)}"
            results.setdefault(name, {})[ds] = run(ds, arm, OUT / "evidence" / ds / key)
            r = results[name][ds]
            logger.info(
                "%s %s: per instant %.1f, static %.1f",
                ds,
                name,
                r["per_instant"]["auc"]["15"],
                r["static"]["auc"]["15"],
            )
    seconds = time.perf_counter() - t0
    info = machine()
    write_json(
        "evidence.json", {"machine": info, "seconds": seconds, "results": results}
    )
    body = table(results)
    print(body)
    if args.no_docs:
        return
    replace_section(
        DOCS / "results.md",
        "evidence",
        "## Each kind of evidence on real photos\n\n"
        + body
        + "\n\nCells: AUC@15 (median pair error; median camera tilt error, deg), "
        "registered images. A camera's tilt error is the angle between the "
        "world's up as it sees it and as its calibration does, after the one "
        "world rotation that best aligns the model to the calibration "
        "(colmap_vc.evaluation.tilt_errors_deg): what the cameras' up fixes. Pairs "
        "pooled over the 5 instants (per instant: each instant's 4 images mapped "
        "on their own; static cameras: all 20 images with `--static-cameras`, "
        "evaluated per instant). The mapper is the same in every arm (it finds "
        "its model with every VC); the arms differ in what the refinement keeps: "
        "keypoint tracks by identity, the mapper's surface-VC points weighing 6 "
        "keypoint observations per image, the cameras' up from the scene's "
        "vertical lines (docs/real-data.md). "
        f"Measured at commit {info['commit']} by `.venv/bin/python "
        f"bench/evidence.py` ({seconds / 60:.0f} min) on the databases of "
        "`bench/realdata.py` and `bench/static_cameras.py`; raw numbers in "
        "`bench/out/evidence.json`. The synthetic counterpart (keypoints alone, "
        "`map`, `map --gba` over twelve domes per prior level) is in "
        'docs/gba.md, "Synthetic benchmark".',
    )


if __name__ == "__main__":
    main()
