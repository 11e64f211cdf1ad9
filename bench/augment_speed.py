"""Speed of `augment`: ray casting against raw Embree, and the whole command.

1. Ray-casting throughput: colmap_vc.raycast (first hits with float64 refinement, and
   all hits) on the pixel rays of a body-sized scene, as a ratio to raw Embree
   first-hit throughput on the same rays in the same run (goal: at least 0.7 for
   first hits; all hits are reported per hit found).
2. Wall time of `augment` (read, observe, match + verify, write) on a 16-view,
   3-person dome scene (goal: at most 10 s on 2 cores).

    .venv/bin/python bench/augment_speed.py [--repeats 3]

Writes bench/out/augment_speed.json and a table in docs/benchmark.md.
"""

from __future__ import annotations

import argparse
import logging
import shutil
import time

import numpy as np
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

from colmap_vc import raycast
from colmap_vc.augment import AugmentOptions, run
from colmap_vc.priors import read_priors

logger = logging.getLogger("bench.augment_speed")


def raycast_ratio(scene, repeats: int) -> dict:
    """Throughput of our casting vs raw Embree on the pixel rays of one image."""
    from embreex import mesh_construction, rtcore_scene

    priors = read_priors(scene / "gt" / "priors")
    rec = pycolmap.Reconstruction(scene / "gt" / "sparse")
    image = sorted(rec.images.values(), key=lambda im: im.name)[0]
    meshes = [(p.vertices_cam, p.faces) for p in priors.images[image.name].persons]
    ours = raycast.build_scene(meshes)
    raw = rtcore_scene.EmbreeScene()
    for v, f in meshes:
        mesh_construction.TriangleMesh(
            scene=raw, vertices=v.astype(np.float32), indices=f.astype(np.int32)
        )
    xy = raycast.pixel_grid(image.camera.width, image.camera.height)
    dirs = raycast.rays_cam(image.camera, xy)
    origins = np.zeros_like(dirs)
    o32, d32 = origins.astype(np.float32), dirs.astype(np.float32)
    t_raw, t_first, t_all, n_hits = [], [], [], 0
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = raw.run(o32, d32, output=1)
        t_raw.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        raycast.first_hits(ours, origins, dirs)
        t_first.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        hits = raycast.all_hits(ours, origins, dirs)
        t_all.append(time.perf_counter() - t0)
        n_hits = len(hits)
    n_first = int((out["primID"] >= 0).sum())
    raw_rate = len(xy) / min(t_raw)
    return {
        "num_rays": len(xy),
        "num_first_hits": n_first,
        "num_all_hits": n_hits,
        "raw_embree_rays_per_s": raw_rate,
        "first_hits_rays_per_s": len(xy) / min(t_first),
        "all_hits_rays_per_s": len(xy) / min(t_all),
        "all_hits_hits_per_s": n_hits / min(t_all),
        "raw_embree_hits_per_s": n_first / min(t_raw),
        "ratio_first_hits": (len(xy) / min(t_first)) / raw_rate,
        "ratio_all_hits_per_hit": (n_hits / min(t_all)) / (n_first / min(t_raw)),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    setup_logging()
    scene = speed_scene()
    rays = raycast_ratio(scene, args.repeats)
    runs = []
    for _ in range(args.repeats):
        db = OUT / "runs" / "augment_speed.db"
        db.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(scene / "database.db", db)
        t0 = time.perf_counter()
        summary = run(db, scene / "priors", AugmentOptions(show_progress=False))
        runs.append(
            {
                "total_s": time.perf_counter() - t0,
                "timings_s": summary.timings_s,
                "pairs": len(summary.pairs),
                "verified": summary.num_verified_pairs,
            }
        )
    best = min(runs, key=lambda r: r["total_s"])
    write_json(
        "augment_speed.json",
        {"machine": machine(), "raycast": rays, "augment_runs": runs},
    )
    body = "\n".join(
        [
            "| measure | value | goal |",
            "|---|---|---|",
            "| first hits (float64-refined) / raw Embree first hits, rays/s | "
            f"**{rays['ratio_first_hits']:.2f}** "
            f"({rays['first_hits_rays_per_s'] / 1e6:.2f} M vs "
            f"{rays['raw_embree_rays_per_s'] / 1e6:.2f} M rays/s) | >= 0.7 |",
            "| all hits / raw Embree first hits, hits/s | "
            f"{rays['ratio_all_hits_per_hit']:.2f} "
            f"({rays['num_all_hits']} hits from {rays['num_rays']} rays) | |",
            f"| `augment` wall time, 16 views, 3 people | **{best['total_s']:.1f} s** "
            f"({', '.join(f'{k} {v:.1f}' for k, v in best['timings_s'].items())})"
            " | <= 10 s |",
            f"| pairs with VCs / verified | {best['pairs']} / {best['verified']} | |",
            "",
            f"Best of {args.repeats} runs at commit {machine()['commit']}, "
            "`.venv/bin/python bench/augment_speed.py`; "
            "raw numbers in `bench/out/augment_speed.json`.",
        ]
    )
    replace_section(DOCS / "benchmark.md", "augment-speed", body)
    print(body)


if __name__ == "__main__":
    main()
