"""Static cameras through the CLI: all images of a capture in one folder.

The user's path for static cameras (docs/real-data.md, "Static cameras"): one COLMAP
database of every image (known intrinsics), `colmap-vc priors`, then `augment` and
`map` with `--static-cameras '(cam\\d+)_'`, evaluated per instant (the 4 images of an
instant, pairs pooled over the instants, as bench/realdata.py does for one instant).

    .venv/bin/python bench/static_cameras.py [--datasets single multi]

`map` runs three times on the same augmented database: with `--no-gravity`, with
`--no-weigh-repeats` (every instant's keypoints independent) and as is (each
camera's up from the scene's vertical lines, colmap_vc/gravity.py).
Then the whole path runs again with the images written into the database in
reverse order, and the largest change of a camera's rotation is reported (same
input, same output).

Writes bench/out/static_cameras.json and the "static" section of docs/results.md.
"""

from __future__ import annotations

import argparse
import logging
import shutil
import time

import numpy as np
from common import (
    DOCS,
    OUT,
    add_pose2sim_run_args,
    machine,
    replace_section,
    setup_logging,
    variant_dir,
    write_json,
)
from realdata import INSTANTS, SHARED, _largest_model, load_calibration, make_database
from realdata import pooled as pool

from colmap_vc import cli
from colmap_vc.evaluation import camera_distance_ratio, evaluate_poses, poses_by_name

logger = logging.getLogger("bench.static_cameras")
PATTERN = r"(cam\d+)_"
VARIANTS = {
    "map --no-gravity": ["--no-gravity"],
    "map --no-weigh-repeats": ["--no-weigh-repeats"],
    "map": [],
}


def run(
    ds: str, out_dir: str, reverse: bool = False, map_args: tuple[str, ...] = ()
) -> dict:
    data = SHARED / f"pose2sim_{ds}"
    cameras, gt = load_calibration(data)
    images = sorted(gt, reverse=reverse)  # the order COLMAP writes them
    work = OUT / out_dir / ds / ("reversed" if reverse else "")
    db = work / "database.db"
    t0 = time.perf_counter()
    make_database(data, images, cameras, db)
    priors = OUT / out_dir / ds / "priors"  # per image: the same in any order
    if not (priors / "priors.json").exists():
        args = ["priors", str(data / "images"), "--output", str(priors)]
        assert cli.main([*args, "--database", str(db), "--no-progress"]) == 0
    t_priors = time.perf_counter() - t0
    t0 = time.perf_counter()
    code = cli.main(
        [
            "augment",
            str(db),
            "--priors",
            str(priors),
            "--static-cameras",
            PATTERN,
            "--no-show-progress",
        ]
    )
    assert code == 0, f"augment failed ({code})"
    t_augment = time.perf_counter() - t0
    out = {}
    for variant, extra in VARIANTS.items():
        if reverse and extra:
            continue  # the order check maps as is only
        out[variant] = _map(ds, data, work, db, gt, [*extra, *map_args])
        out[variant]["seconds"] = {
            "database_and_priors": t_priors,
            "augment": t_augment,
            "map": out[variant].pop("map_seconds"),
        }
    return out


def _map(ds: str, data, work, db, gt: dict, extra: list[str]) -> dict:
    sparse = variant_dir(work, "sparse", extra)
    shutil.rmtree(sparse, ignore_errors=True)  # the bench's own output
    t0 = time.perf_counter()
    code = cli.main(
        [
            "map",
            str(db),
            "--image-path",
            str(data / "images"),
            "--output-path",
            str(sparse),
            "--static-cameras",
            PATTERN,
            "--no-show-progress",
            *extra,
        ]
    )
    seconds = time.perf_counter() - t0
    rec = _largest_model(sparse) if code == 0 else None
    pred = {} if rec is None else poses_by_name(rec)
    per_instant = [
        evaluate_poses(
            {n: p for n, p in pred.items() if instant in n},
            {n: g for n, g in gt.items() if instant in n},
        )
        for instant in INSTANTS
    ]
    out = pool(per_instant)
    out["registered_all"] = len(pred)
    out["poses"] = {n: p.tolist() for n, p in sorted(pred.items())}
    out["distance_ratio"] = camera_distance_ratio(pred, gt)  # metric scale
    out["map_seconds"] = seconds
    logger.info(
        "%s %s: AUC@15 %.1f, median %.2f deg",
        ds,
        " ".join(["map", *extra]),
        out["auc"]["15"],
        out["median_error_deg"],
    )
    return out


def _rotation_deg(a: np.ndarray, b: np.ndarray) -> float:
    cos = (np.trace(a[:3, :3] @ b[:3, :3].T) - 1) / 2
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--datasets", nargs="+", default=["single", "multi"])
    add_pose2sim_run_args(
        parser, "static_cameras", "folder under bench/out and JSON name"
    )
    args = parser.parse_args()
    setup_logging()
    map_args = tuple(args.map_args.split())
    results = {ds: run(ds, args.out, map_args=map_args) for ds in args.datasets}
    orders = {}
    for ds in args.datasets:  # same input, same output: images written reversed
        again = run(ds, args.out, reverse=True, map_args=map_args)["map"]["poses"]
        first = results[ds]["map"]["poses"]
        orders[ds] = (
            max(
                _rotation_deg(np.asarray(first[n]), np.asarray(again[n])) for n in first
            )
            if set(first) == set(again)
            else float("inf")
        )
        logger.info(
            "%s: reversed image order, largest pose change %.3g deg", ds, orders[ds]
        )
    write_json(
        f"{args.out}.json",
        {"machine": machine(), "results": results, "reversed_order_max_deg": orders},
    )
    lines = [
        "| data | registered | AUC@15 | AUC@30 | AUC@45 | median pair error (deg) "
        "| camera distances / calibration |",
        "|---|---|---|---|---|---|---|",
    ]
    for ds, by_variant in results.items():
        for variant, r in by_variant.items():
            r.pop("poses")
            a = r["auc"]
            lines.append(
                f"| pose2sim_{ds}, 20 images, `{' '.join([variant, *map_args])}` "
                f"| {r['registered_all']}/20 | {a['15']:.1f} | {a['30']:.1f} "
                f"| {a['45']:.1f} | {r['median_error_deg']:.2f} "
                f"| {r['distance_ratio']:.3f} |"
            )
    lines += [
        "",
        f"Measured at commit {machine()['commit']} by `.venv/bin/python "
        f"bench/static_cameras.py --datasets {' '.join(args.datasets)}"
        + (f" --map-args='{args.map_args}'" if map_args else "")
        + "`: one database "
        "of the 20 images, `colmap-vc priors`, `augment --static-cameras "
        f"'{PATTERN}'`, then `map --static-cameras '{PATTERN}'` on it with "
        "`--no-gravity`, `--no-weigh-repeats` (every instant's keypoints "
        "independent) and as is (each camera's up from the scene's vertical "
        "lines); evaluated "
        "per instant (4 images, 6 pairs), pairs pooled over the 5 instants. "
        "Camera distances / calibration: the median over camera pairs of the "
        "model's distance between the two cameras over the calibration's (`map` "
        "scales the model to metres from the people, colmap_vc/metric_scale.py). "
        "Image order: the same run with the images written into the database in "
        "reverse order; largest change of a camera's rotation in `map`'s model: "
        + ", ".join(f"pose2sim_{ds} {d:.2g} deg" for ds, d in orders.items())
        + ".",
    ]
    print("\n".join(lines))
    if args.no_docs:
        return
    replace_section(
        DOCS / "results.md",
        "static",
        "## Static cameras, all instants through the CLI\n\n" + "\n".join(lines),
    )


if __name__ == "__main__":
    main()
