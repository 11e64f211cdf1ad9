"""Fewer cameras, fewer instants: pose2sim through the CLI on every subset.

Users do not bring four cameras and five instants. This bench runs the user's path
(bench/realdata.py: a database with the known intrinsics, `augment`, `map`) on
subsets of pose2sim_single and pose2sim_multi, on the priors the other pose2sim
benches cached (the priors folder holds every image; `augment` ignores those the
database lacks):

- *one instant*: every 2- and 3-camera subset of each instant (10 per instant);
- *static cameras* (`--static-cameras '(cam\\d+)_'`): every camera pair over two
  instants, every 3-camera subset over the five instants, and one capture with
  uneven instants per camera (cam01 at all five, cam02 at two, cam03 and cam04 at
  one each, not the same one).

Per group: how many runs `map` finished (exit 0), the images registered, and the
pairs' rotation errors against the calibration pooled over runs and instants (a
pair with an unregistered image counts as 180 deg).

    .venv/bin/python bench/subsets.py [--datasets single multi] [--groups ...]

Needs the priors of bench/realdata.py and bench/static_cameras.py (run them first).
Writes bench/out/subsets.json and the "subsets" section of docs/results.md.
"""

from __future__ import annotations

import argparse
import itertools
import json
import logging
import shutil
import time
from pathlib import Path

import numpy as np
from common import (
    DOCS,
    OUT,
    add_pose2sim_run_args,
    machine,
    replace_section,
    setup_logging,
    write_json,
)
from realdata import INSTANTS, SHARED, _largest_model, load_calibration, make_database
from realdata import pooled as pool

from colmap_vc import cli
from colmap_vc.evaluation import THRESHOLDS_DEG, evaluate_poses, pose_auc, poses_by_name

logger = logging.getLogger("bench.subsets")
CAMERAS = ("cam01", "cam02", "cam03", "cam04")
PATTERN = r"(cam\d+)_"


def runs(group: str) -> list[tuple[str, list[str]]]:
    """(name, image names) of every run of a group."""
    if group == "one instant":
        return [
            (f"{t}_{'-'.join(sub)}", [f"{c}_{t}.jpg" for c in sub])
            for t in INSTANTS
            for k in (2, 3)
            for sub in itertools.combinations(CAMERAS, k)
        ]
    pairs = [
        (f"{a}-{b}_2", [f"{c}_{t}.jpg" for t in INSTANTS[:2] for c in (a, b)])
        for a, b in itertools.combinations(CAMERAS, 2)
    ]
    triples = [
        ("-".join(sub) + "_5", [f"{c}_{t}.jpg" for t in INSTANTS for c in sub])
        for sub in itertools.combinations(CAMERAS, 3)
    ]
    uneven = [f"cam01_{t}.jpg" for t in INSTANTS] + [
        "cam02_t010.jpg",
        "cam02_t050.jpg",
        "cam03_t030.jpg",
        "cam04_t090.jpg",
    ]
    return [*pairs, *triples, ("uneven", uneven)]


def run_one(
    ds: str,
    group: str,
    name: str,
    images: list[str],
    priors: Path,
    out: str = "subsets",
    map_args: tuple[str, ...] = (),
) -> dict:
    """Database, augment, map (with ``map_args``), eval of one subset, under
    bench/out/``out``."""
    data = SHARED / f"pose2sim_{ds}"
    cameras, gt = load_calibration(data)
    work = OUT / out / ds / group.replace(" ", "_") / name
    shutil.rmtree(work, ignore_errors=True)  # the bench's own output
    db = work / "database.db"
    make_database(data, images, cameras, db)
    static = ["--static-cameras", PATTERN] if group == "static cameras" else []
    t0 = time.perf_counter()
    args = ["augment", str(db), "--priors", str(priors), "--no-show-progress"]
    code_augment = cli.main([*args, *static])
    sparse = work / "sparse"
    args = ["map", str(db), "--image-path", str(data / "images")]
    code_map = (
        cli.main(
            [
                *args,
                "--output-path",
                str(sparse),
                "--no-show-progress",
                *static,
                *map_args,
            ]
        )
        if code_augment == 0
        else None
    )
    seconds = time.perf_counter() - t0
    rec = _largest_model(sparse) if code_map == 0 else None
    pred = {} if rec is None else poses_by_name(rec)
    metrics = [
        evaluate_poses(
            {n: p for n, p in pred.items() if n in images and t in n},
            {n: gt[n] for n in images if t in n},
        )
        for t in INSTANTS
        if sum(t in n for n in images) >= 2
    ]
    errors = [p.error_deg for m in metrics for p in m.pairs]
    logger.info(
        "%s %s %s: augment %s, map %s, %d/%d registered, pair errors %s",
        ds,
        group,
        name,
        code_augment,
        code_map,
        len(pred),
        len(images),
        " ".join(f"{e:.1f}" for e in errors),
    )
    return {
        "images": images,
        "augment_exit": code_augment,
        "map_exit": code_map,
        "registered": len(pred),
        "pair_errors_deg": [round(float(e), 3) for e in errors],
        "metrics": pool(metrics) if metrics else None,
        "seconds": seconds,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--datasets", nargs="+", default=["single", "multi"])
    parser.add_argument(
        "--groups", nargs="+", default=["one instant", "static cameras"]
    )
    add_pose2sim_run_args(parser, "subsets", "folder under bench/out and JSON name")
    parser.add_argument(
        "--table-only",
        action="store_true",
        help="rewrite the results.md section from bench/out/subsets.json",
    )
    args = parser.parse_args()
    setup_logging()
    if args.table_only:
        saved = json.loads((OUT / f"{args.out}.json").read_text())
        write_table(
            saved["results"],
            saved["machine"]["commit"],
            saved.get("elapsed_s", 0),
            saved.get("map_args", ""),
            docs=not args.no_docs,
            out=args.out,
        )
        return
    t_start = time.perf_counter()
    results: dict[str, dict[str, dict]] = {}
    for ds in args.datasets:
        for group in args.groups:
            key = f"{ds}/{group}"
            results[key] = {}
            for name, images in runs(group):
                priors = (
                    OUT / "static_cameras" / ds / "priors"
                    if group == "static cameras"
                    else OUT / "realdata" / ds / name.split("_")[0] / "priors"
                )
                if not (priors / "priors.json").exists():
                    raise SystemExit(
                        f"{priors}: run bench/realdata.py and "
                        "bench/static_cameras.py first"
                    )
                results[key][name] = run_one(
                    ds,
                    group,
                    name,
                    images,
                    priors,
                    args.out,
                    tuple(args.map_args.split()),
                )
    elapsed = time.perf_counter() - t_start
    write_json(
        f"{args.out}.json",
        {
            "machine": machine(),
            "map_args": args.map_args,
            "results": results,
            "elapsed_s": elapsed,
        },
    )
    table = write_table(
        results,
        machine()["commit"],
        elapsed,
        args.map_args,
        docs=not args.no_docs,
        out=args.out,
    )
    print(table)


def _rows(results: dict[str, dict[str, dict]]) -> list[tuple[str, str, list[dict]]]:
    """(data, subsets, runs) per table row: one instant split by camera count."""
    rows = []
    for key, group_runs in results.items():
        ds, group = key.split("/")
        if group == "one instant":
            for k in (2, 3):
                runs_k = [r for r in group_runs.values() if len(r["images"]) == k]
                rows.append((ds, f"one instant, {k} cameras", runs_k))
        else:
            rows.append((ds, group, list(group_runs.values())))
    return rows


def write_table(
    results: dict[str, dict[str, dict]],
    commit: str,
    elapsed: float,
    map_args: str = "",
    docs: bool = True,
    out: str = "subsets",
) -> str:
    """The table of the runs (into docs/results.md's "subsets" section with
    ``docs``)."""
    lines = [
        "| data | subsets | runs | `map` finished | registered | pairs "
        "| AUC@15 | AUC@30 | AUC@45 | median pair error (deg) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for ds, group, group_runs in _rows(results):
        errors = [e for r in group_runs for e in r["pair_errors_deg"]]
        auc = pose_auc(errors, THRESHOLDS_DEG)
        lines.append(
            f"| pose2sim_{ds} | {group} | {len(group_runs)} "
            f"| {sum(r['map_exit'] == 0 for r in group_runs)} "
            f"| {sum(r['registered'] for r in group_runs)}/"
            f"{sum(len(r['images']) for r in group_runs)} "
            f"| {len(errors)} | {100 * auc[0]:.1f} | {100 * auc[1]:.1f} "
            f"| {100 * auc[2]:.1f} | {np.median(errors):.2f} |"
        )
    lines += [
        "",
        f"Measured at commit {commit} by `.venv/bin/python bench/subsets.py"
        f"{f' --map-args={map_args}' if map_args else ''}"
        f"{f' --out {out}' if out != 'subsets' else ''}` "
        f"({elapsed / 60:.0f} min; per run in `bench/out/{out}.json`). "
        "*one instant*: every 2- and 3-camera subset of each of the five instants; "
        "*static cameras*: every camera pair over two instants, every 3-camera "
        "subset over five, one capture with uneven instants per camera; pairs of "
        "one instant against the calibration, pooled over runs; a pair with an "
        "unregistered image counts as 180 deg.",
    ]
    if docs:
        replace_section(
            DOCS / "results.md",
            "subsets",
            "## Real photos: fewer cameras, fewer instants\n\n" + "\n".join(lines),
        )
    return "\n".join(lines)


if __name__ == "__main__":
    main()
