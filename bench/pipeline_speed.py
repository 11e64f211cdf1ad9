"""Wall time of `augment` + `map` (+ GBA) on a 16-view, 3-person dome scene.

Goal (issue 4): augment + map at most 20 s on 2 cores. GBA is timed separately.
Seconds follow the machine, so the same run also times COLMAP's own incremental
mapper (pycolmap, its default options and threads) on the same augmented
database: what a user who maps with `colmap mapper` instead spends, and the
reference that `map`'s time is a ratio to.

    .venv/bin/python bench/pipeline_speed.py [--repeats 2]

Writes bench/out/pipeline_speed.json and a section of docs/benchmark.md.
"""

from __future__ import annotations

import argparse
import shutil
import time

import pycolmap
from common import (
    DOCS,
    OUT,
    machine,
    replace_section,
    setup_logging,
    speed_scene,
    write_json,
)

from colmap_vc import augment, mapping
from colmap_vc.keypoint_ba import KeypointBaOptions


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=2)
    args = parser.parse_args()
    setup_logging()
    scene = speed_scene()
    runs = []
    for _ in range(args.repeats):
        work = OUT / "runs" / "pipeline_speed"
        shutil.rmtree(work, ignore_errors=True)
        work.mkdir(parents=True)
        db = work / "database.db"
        shutil.copyfile(scene / "database.db", db)
        t0 = time.perf_counter()
        augment.run(db, scene / "priors", augment.AugmentOptions(show_progress=False))
        t1 = time.perf_counter()
        _, summary = mapping.run(
            db,
            scene / "images",
            work / "sparse",
            mapping.MappingOptions(show_progress=False),
        )
        t2 = time.perf_counter()
        mapping.run(
            db,
            scene / "images",
            work / "sparse_gba",
            mapping.MappingOptions(
                show_progress=False,
                keypoint_ba_options=KeypointBaOptions(surface_tracks=True),
            ),
        )
        t3 = time.perf_counter()
        ref = work / "colmap"
        ref.mkdir()
        shutil.copyfile(db, ref / "database.db")  # the mapper may migrate it
        t4 = time.perf_counter()
        models = pycolmap.incremental_mapping(
            ref / "database.db", scene / "images", ref
        )
        t5 = time.perf_counter()
        runs.append(
            {
                "augment_s": t1 - t0,
                "map_s": t2 - t1,
                "map_gba_s": t3 - t2,
                "augment_map_s": t2 - t0,
                "registered": summary.num_registered,
                "colmap_mapper_s": t5 - t4,
                "colmap_registered": max(
                    (m.num_reg_images() for m in models.values()), default=0
                ),
            }
        )
    best = min(runs, key=lambda r: r["augment_map_s"])
    write_json("pipeline_speed.json", {"machine": machine(), "runs": runs})
    body = (
        f"16-view, 3-person dome: augment {best['augment_s']:.1f} s + "
        f"map {best['map_s']:.1f} s = "
        f"**{best['augment_map_s']:.1f} s** (goal <= 20 s), "
        f"{best['registered']}/16 registered; "
        f"`map --gba` instead {best['map_gba_s']:.1f} s. In the same run COLMAP's "
        f"own mapper on the augmented database took {best['colmap_mapper_s']:.1f} s "
        f"({best['colmap_registered']}/16 registered): `map` is "
        f"{best['map_s'] / best['colmap_mapper_s']:.2f}x it, `map --gba` "
        f"{best['map_gba_s'] / best['colmap_mapper_s']:.2f}x. Best of {args.repeats} "
        f"at commit {machine()['commit']}, "
        "`.venv/bin/python bench/pipeline_speed.py`."
    )
    replace_section(
        DOCS / "benchmark.md",
        "pipeline-speed",
        "## augment + map speed (`bench/pipeline_speed.py`)\n\n" + body,
    )
    print(body)


if __name__ == "__main__":
    main()
