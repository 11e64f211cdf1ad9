"""COLMAP's own mapper on the augmented database, beside `map`.

The README's second path maps the database `augment` wrote with `colmap mapper`:
COLMAP reads the VCs as two-view matches and maps them with its own incremental
mapper and bundle adjustment, without `map`'s checks and keypoint bundle
adjustment. This bench measures that path on the accuracy bench's augmented
databases (`bench/accuracy.py` keeps them: VCs only, and VCs verified with the
SIFT matches) with COLMAP at its defaults, intrinsics held fixed
(`colmap_vc.baselines.colmap_incremental`), and evaluates `map`'s models of the
same databases (the accuracy bench's "VC + keypoint BA") on the same pairs.

    .venv/bin/python bench/colmap_mapper.py   # after bench/accuracy.py

Writes bench/out/colmap_mapper.json and the "colmap-mapper" section of
docs/results.md.
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

import pycolmap
from accuracy import pooled
from common import DOCS, OUT, machine, replace_section, setup_logging, write_json

from colmap_vc.baselines import colmap_incremental
from colmap_vc.evaluation import Metrics, evaluate_reconstruction

logger = logging.getLogger("bench.colmap_mapper")

RUNS = OUT / "runs" / "accuracy"
KINDS = {
    "dome_p1": "dome, 1 person",
    "dome_p3": "dome, 3 people",
    "dense_p1": "dense, 1 person",
}
ARMS = {  # label -> (augmented database, `map`'s run folder) under a level's folder
    "VCs": ("augmented_classic0.db", "VC_p_keypoint_BA"),
    "VCs + classic": ("augmented_classic1.db", "VC_p_classic_p_keypoint_BA"),
}


def map_model(folder: Path) -> pycolmap.Reconstruction | None:
    """`map`'s final model in ``folder`` (its sparse/0), None when it wrote none."""
    model = folder / "sparse" / "0"
    return pycolmap.Reconstruction(model) if (model / "images.bin").exists() else None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--levels", nargs="+", default=["realistic", "fitted"])
    args = parser.parse_args()
    setup_logging()
    t0 = time.perf_counter()
    rows: list[dict] = []
    for kind, label in KINDS.items():
        for level in args.levels:
            for arm, (db_name, map_run) in ARMS.items():
                colmap: list[Metrics] = []
                ours: list[Metrics] = []
                for seed in args.seeds:
                    run = RUNS / f"acc_{kind}_s{seed}" / level
                    if not (run / db_name).exists():
                        raise SystemExit(f"{run / db_name} missing: run accuracy.py")
                    scene = OUT / "scenes" / f"acc_{kind}_s{seed}"
                    gt = pycolmap.Reconstruction(scene / "gt" / "sparse")
                    rec = colmap_incremental(
                        run / db_name,
                        scene / "images",
                        OUT
                        / "runs"
                        / "colmap_mapper"
                        / f"{kind}_s{seed}_{level}_{arm}",
                    )
                    colmap.append(evaluate_reconstruction(rec, gt))
                    ours.append(evaluate_reconstruction(map_model(run / map_run), gt))
                row = {
                    "scenes": label,
                    "priors": level,
                    "matches": arm,
                    "colmap mapper": pooled(colmap),
                    "map": pooled(ours),
                }
                rows.append(row)
                logger.info(
                    "%s, %s, %s: COLMAP %.1f, map %.1f AUC@15",
                    label,
                    level,
                    arm,
                    row["colmap mapper"]["auc"]["15"],
                    row["map"]["auc"]["15"],
                )
    lines = [
        "| scenes | priors | matches | `colmap mapper`: registered, AUC@15/30/45 "
        "(median deg) | `colmap-vc map`: registered, AUC@15/30/45 (median deg) |",
        "|---|---|---|---|---|",
    ]

    def cell(r: dict) -> str:
        return (
            f"{r['registered']}/{r['images']}, {r['auc']['15']:.1f}/"
            f"{r['auc']['30']:.1f}/{r['auc']['45']:.1f} ({r['median_error_deg']:.1f})"
        )

    for r in rows:
        lines.append(
            f"| {r['scenes']} | {r['priors']} | {r['matches']} "
            f"| {cell(r['colmap mapper'])} | {cell(r['map'])} |"
        )
    lines.append(
        f"\nMeasured at commit {machine()['commit']} by `.venv/bin/python "
        "bench/colmap_mapper.py` on the augmented databases `bench/accuracy.py` "
        f"left (seeds {' '.join(map(str, args.seeds))}, pairs pooled): COLMAP's "
        "incremental mapper at its defaults with the intrinsics held fixed "
        "(`baselines.colmap_incremental`), as `colmap mapper` maps a database "
        "`augment` wrote, beside `map`'s model of the same database; raw numbers "
        "in `bench/out/colmap_mapper.json`."
    )
    write_json(
        "colmap_mapper.json",
        {
            "machine": machine(),
            "results": rows,
            "elapsed_s": time.perf_counter() - t0,
        },
    )
    replace_section(DOCS / "results.md", "colmap-mapper", "\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
