"""Is the synthetic benchmark meaningful? Classic COLMAP on `dense` and on `dome`.

Classic COLMAP (pycolmap SIFT, exhaustive matching, incremental mapping, known
intrinsics) should work on `dense` (overlapping views) and fail on `dome` (extreme
views around one person), as it does on the paper's data.

    .venv/bin/python bench/classic.py [--seeds 0 1 2]

Writes bench/out/classic.json and the table in docs/benchmark.md.
"""

from __future__ import annotations

import argparse
import logging
import time

import numpy as np
from common import DOCS, OUT, machine, replace_section, setup_logging, write_json

from colmap_vc.baselines import run_classic
from colmap_vc.synthetic import SynthOptions, generate

logger = logging.getLogger("bench.classic")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--presets", nargs="+", default=["dense", "dome"])
    args = parser.parse_args()
    setup_logging()
    rows = []
    for preset in args.presets:
        for seed in args.seeds:
            scene = OUT / "scenes" / f"{preset}_p1_s{seed}"
            t0 = time.perf_counter()
            generate(
                preset, scene, SynthOptions(seed=seed, num_people=1, overwrite=True)
            )
            t_synth = time.perf_counter() - t0
            _, m = run_classic(scene, OUT / "runs" / f"classic_{preset}_s{seed}")
            rows.append(
                {
                    "preset": preset,
                    "seed": seed,
                    "num_images": m.num_images,
                    "num_registered": m.num_registered,
                    "registered_fraction": m.num_registered / m.num_images,
                    "auc": m.auc,
                    "median_error_deg": m.median_error_deg,
                    "synth_s": t_synth,
                }
            )
            logger.info(
                "%s seed %d: %d/%d registered, AUC@30 %.1f",
                preset,
                seed,
                m.num_registered,
                m.num_images,
                m.auc["30"],
            )
    summary = {}
    for preset in args.presets:
        sel = [r for r in rows if r["preset"] == preset]
        summary[preset] = {
            "registered_fraction": float(
                np.mean([r["registered_fraction"] for r in sel])
            ),
            **{
                f"auc{t}": float(np.mean([r["auc"][t] for r in sel]))
                for t in ("15", "30", "45")
            },
        }
    checks = {
        "dense: >=90% registered and AUC@30 >= 70": bool(
            "dense" in summary
            and summary["dense"]["registered_fraction"] >= 0.9
            and summary["dense"]["auc30"] >= 70
        ),
        "dome: <50% registered or AUC@30 < 20": bool(
            "dome" in summary
            and (
                summary["dome"]["registered_fraction"] < 0.5
                or summary["dome"]["auc30"] < 20
            )
        ),
    }
    path = write_json(
        "classic.json",
        {"machine": machine(), "rows": rows, "summary": summary, "checks": checks},
    )
    lines = [
        "| preset | seed | registered | AUC@15 | AUC@30 | AUC@45 | median err (deg) |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['preset']} | {r['seed']} | "
            f"{r['num_registered']}/{r['num_images']} | "
            f"{r['auc']['15']:.1f} | {r['auc']['30']:.1f} | {r['auc']['45']:.1f} | "
            f"{r['median_error_deg']:.1f} |"
        )
    for preset, s in summary.items():
        lines.append(
            f"| **{preset} mean** | | {100 * s['registered_fraction']:.0f}% | "
            f"{s['auc15']:.1f} | {s['auc30']:.1f} | {s['auc45']:.1f} | |"
        )
    lines.append("")
    lines += [f"- {k}: **{'yes' if v else 'NO'}**" for k, v in checks.items()]
    lines.append(
        f"\nMeasured at commit {machine()['commit']} by `.venv/bin/python "
        f"bench/classic.py --seeds {' '.join(map(str, args.seeds))}`; "
        "raw numbers in `bench/out/classic.json`."
    )
    replace_section(DOCS / "benchmark.md", "classic", "\n".join(lines))
    print("\n".join(lines))
    logger.info("wrote %s", path)


if __name__ == "__main__":
    main()
