"""How `map`'s time grows with the instants of static cameras.

Users film for minutes with static cameras; `colmap-vc frames` takes instants
from the videos and `map --static-cameras` holds one pose per camera over all of
them. Every instant adds people to each camera's one image, and the camera check
tests every person's left and right (docs/benchmark.md). This bench times the
user's path at a growing number of instants of the pose2sim_single videos
(`bench/static_instants.py`'s Demo_SinglePerson, four calibrated cameras), with
candidate instants every frame (the videos hold 96), so that 60 instants exist:
neighbours 17 ms apart are near copies, so accuracy is not what this measures.
The databases hold SIFT keypoints and no classic matches (exhaustive matching of
240 frames takes longer than the rest); the refinement's cost is the people's.

    .venv/bin/python bench/static_scaling.py [--instants 20 40 60]

The speed is a ratio against the first row, measured in the same run. Writes
bench/out/static_scaling.json and the section "static-scaling" of
docs/benchmark.md: per row, `map`'s own timings (its map_options.json), the
ratio of time and of instants to the first row, the exponent between them, and
AUC@15 against the calibration.
"""

from __future__ import annotations

import argparse
import logging

import numpy as np
from common import DOCS, OUT, machine, replace_section, setup_logging, write_json
from static_instants import SHARED, frames_and_priors, run

logger = logging.getLogger("bench.static_scaling")

CAMERAS = ("cam01", "cam02", "cam03", "cam04")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--instants", nargs="+", type=int, default=[20, 40, 60])
    parser.add_argument("--map-only", action="store_true")
    args = parser.parse_args()
    setup_logging()
    work = OUT / "static_scaling"
    data = SHARED / "pose2sim_single"
    frames, priors, instants, _ = frames_and_priors(
        "single", work, max(args.instants), step=1
    )
    rows = {}
    for n in sorted(args.instants):
        out = run(
            data,
            n,
            instants,
            work,
            frames,
            priors,
            CAMERAS,
            args.map_only,
            variants={"map": []},
            match=False,
        )["map"]
        rows[n] = out
        logger.info("%d instants: %s", n, out["map_timings_s"])
    write_json("static_scaling.json", {"machine": machine(), "results": rows})
    first = min(rows)
    t0 = rows[first]["map_timings_s"]
    lines = [
        "| instants | images | `augment` (s) | `map` (s) | its refinement (s) "
        "| refinement / first row | instants / first row | exponent | AUC@15 |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for n, r in rows.items():
        t = r["map_timings_s"]
        ratio = t["refinement"] / t0["refinement"]
        grow = n / first
        exponent = "" if n == first else f"{np.log(ratio) / np.log(grow):.2f}"
        lines.append(
            f"| {n} | {r['images']} | {r['seconds_augment']:.0f} "
            f"| {sum(t.values()):.0f} | {t['refinement']:.1f} | {ratio:.2f} "
            f"| {grow:.0f} | {exponent} | {r['auc']['15']:.1f} |"
        )
    lines += [
        "",
        f"Measured at commit {machine()['commit']} by `.venv/bin/python "
        f"bench/static_scaling.py --instants {' '.join(map(str, sorted(rows)))}`"
        " (the exponent: log of the refinement's ratio over log of the instants'"
        "; 1 is linear).",
    ]
    replace_section(DOCS / "benchmark.md", "static-scaling", "\n".join(lines))


if __name__ == "__main__":
    main()
