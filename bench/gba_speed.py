"""GBA speed against COLMAP's own bundle adjustment on the same problem, same run.

The 16-view, 3-person dome (realistic priors) is augmented and mapped by COLMAP's
mapper; the model then gets what `map --gba` adjusts: the keypoint tracks and every
surface VC track by identity. On that model, interleaved, repeated:

- **COLMAP BA**: ``pycolmap.bundle_adjustment`` (Ceres, Cauchy loss, intrinsics
  fixed), every observation under one loss;
- **GBA**: the same Ceres problem, built by pycolmap, with the people's
  observations re-added with their noise (``colmap_vc.gba.ceres``).

Both run to convergence from the same start; the table gives the wall time, the
iterations and the time per iteration, and the ratio. The noise model (triangulate
the tracks, estimate each cluster's noise) is timed on its own. Goal: GBA / COLMAP
<= 1.2 (issue 12).

    .venv/bin/python bench/gba_speed.py [--repeats 9]

Writes bench/out/gba_speed.json and the section `gba-speed` of docs/benchmark.md.
"""

from __future__ import annotations

import argparse
import logging
import shutil
import statistics
import time
from pathlib import Path

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

from colmap_vc import augment, mapping
from colmap_vc.gba.ceres import ba_options, bundle_adjust_inplace
from colmap_vc.keypoint_ba import (
    KeypointBaOptions,
    add_weighted_surface,
    with_loss_scale,
)
from colmap_vc.keypoint_tracks import (
    add_keypoint_points,
    delete_points_observing,
    keypoint_observations,
    keypoint_tracks,
)
from colmap_vc.vc_records import read_vc_records

logger = logging.getLogger("bench.gba_speed")


def gba_model(db: Path, rec: pycolmap.Reconstruction, options: KeypointBaOptions):
    """The mapper's model with keypoint and surface tracks by identity, and their
    noise -> (model, people noise, noise-model seconds)."""
    out = pycolmap.Reconstruction(rec)
    registered = np.array(sorted(out.reg_image_ids()), dtype=np.int64)
    records = read_vc_records(db)
    tracks = keypoint_tracks(records, registered)
    num_classic = records.num_classic
    delete_points_observing(out, keypoint_observations(tracks))
    vc_only = [
        pid
        for pid, p in out.points3D.items()  # loop over the model's points
        if all(e.point2D_idx >= num_classic[e.image_id] for e in p.track.elements)
    ]
    for pid in vc_only:
        out.delete_point3D(pid)
    add_keypoint_points(out, tracks, options.min_track_length)
    bundle_adjust_inplace(out, options.loss_scale_px)
    t0 = time.perf_counter()
    people, _ = add_weighted_surface(records, out, tracks, options)
    return out, people, time.perf_counter() - t0


def timed(fn) -> tuple[float, int]:
    t0 = time.perf_counter()
    iterations = fn()
    return time.perf_counter() - t0, iterations


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=9)
    args = parser.parse_args()
    setup_logging()
    scene = speed_scene()
    work = OUT / "runs" / "gba_speed"
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    db = work / "database.db"
    shutil.copyfile(scene / "database.db", db)
    augment.run(db, scene / "priors", augment.AugmentOptions(show_progress=False))
    rec, _ = mapping.run_incremental(
        db,
        scene / "images",
        work / "sparse",
        mapping.MappingOptions(keypoint_ba=False, show_progress=False),
    )
    options = with_loss_scale(KeypointBaOptions(surface_tracks=True), rec)
    model, people, noise_s = gba_model(db, rec, options)
    num_obs = sum(len(p.track.elements) for p in model.points3D.values())

    def colmap_ba() -> int:
        copy = pycolmap.Reconstruction(model)
        pycolmap.bundle_adjustment(copy, ba_options(options.loss_scale_px))
        return -1  # pycolmap.bundle_adjustment reports no summary

    def colmap_problem() -> int:
        copy = pycolmap.Reconstruction(model)
        s = bundle_adjust_inplace(copy, options.loss_scale_px)
        return s.num_successful_steps + s.num_unsuccessful_steps

    def gba() -> int:
        copy = pycolmap.Reconstruction(model)
        s = bundle_adjust_inplace(copy, options.loss_scale_px, people)
        return s.num_successful_steps + s.num_unsuccessful_steps

    arms = {
        "COLMAP BA (pycolmap.bundle_adjustment)": colmap_ba,
        "COLMAP BA (its Ceres problem from Python)": colmap_problem,
        "GBA (the same problem, people re-weighted)": gba,
    }
    runs: dict[str, list[tuple[float, int]]] = {k: [] for k in arms}
    for _ in range(args.repeats):  # interleaved: the machine's load hits every arm
        for name, fn in arms.items():
            runs[name].append(timed(fn))
    rows = {
        name: {
            "seconds": statistics.median(t for t, _ in r),
            "iterations": statistics.median(i for _, i in r),
            "iterations_range": [min(i for _, i in r), max(i for _, i in r)],
        }
        for name, r in runs.items()
    }
    # Paired: the ratio within each repeat, then its median (the load of a shared
    # machine changes between repeats more than between the arms of one).
    ratio = statistics.median(
        g / c
        for (g, _), (c, _) in zip(
            runs["GBA (the same problem, people re-weighted)"],
            runs["COLMAP BA (pycolmap.bundle_adjustment)"],
            strict=True,
        )
    )
    write_json(
        "gba_speed.json",
        {
            "machine": machine(),
            "images": model.num_reg_images(),
            "points": model.num_points3D(),
            "observations": num_obs,
            "noise_model_s": noise_s,
            "rows": rows,
            "runs": runs,
            "ratio_gba_to_colmap": ratio,
        },
    )
    lines = [
        "| solver (same model, same observations) | wall time (s) | iterations "
        "(range over the repeats) | per iteration (s) |",
        "|---|---|---|---|",
    ]
    for name, row in rows.items():
        it, (lo, hi) = row["iterations"], row["iterations_range"]
        per = f"{row['seconds'] / it:.3f}" if it > 0 else "-"
        its = "-" if it <= 0 else f"{it:g}" if lo == hi else f"{it:g} ({lo}-{hi})"
        lines.append(f"| {name} | {row['seconds']:.2f} | {its} | {per} |")
    lines += [
        "",
        f"{model.num_reg_images()} images, {model.num_points3D()} points, {num_obs} "
        f"observations (keypoint and surface tracks by identity, plus the mapper's "
        f"classic points). **GBA / COLMAP BA: {ratio:.2f}** (median of the "
        f"per-repeat ratios; goal <= 1.2); the "
        f"noise model before it (triangulation, spread and correlation) "
        f"{noise_s:.2f} s. Median of {args.repeats} interleaved runs at commit "
        f"{machine()['commit']}, `.venv/bin/python bench/gba_speed.py`; raw numbers "
        "in `bench/out/gba_speed.json`.",
    ]
    replace_section(DOCS / "benchmark.md", "gba-speed", "\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
