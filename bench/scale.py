"""Scaling: wall time and peak memory per stage from 16 to 256 images (issue 14).

Scenes: `synth dome --cameras N --people 3 --no-sift` for N in --sizes (the
database holds the cameras with their known intrinsics and the images, no SIFT:
exhaustive SIFT matching grows with the square of the images and is COLMAP's
cost, not ours), and static cameras over several instants (`--cameras 32
--instants 4`). Each scene is made once under bench/out/scenes/.

Each run (`augment` then `map`, realistic anonymous priors) is a subprocess of its
own, so its peak memory (resident set, workers included) is its own. Stages:

| stage | what |
|---|---|
| read | database and priors reading |
| observe | per image: re-posing the priors, ray casting every person (all hits) |
| link | per pair: person matches and each link's own verification (RANSAC) |
| associate | people across all views at once |
| verify | per associated pair: joint verification (RANSAC), cycle check |
| write | VC keypoints, matches and geometries into the database |
| map | COLMAP's mapper (and the mesh-initialised fallback) |
| refine | keypoint BA, checks, the cameras' up, metric scale, model writing |

The log-log slope of each stage's time against the number of images is fitted
between 32 and the largest size: 1 is linear, 2 quadratic.

    .venv/bin/python bench/scale.py [--sizes 16 32 64 128 256] [--pairs all selected]

Writes bench/out/scale.json, docs/img/scale.png and the section `scale` of
docs/benchmark.md.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from common import (
    DOCS,
    OUT,
    ROOT,
    machine,
    replace_section,
    scene_is_current,
    setup_logging,
    write_json,
)

logger = logging.getLogger("bench.scale")

STAGES = ("read", "observe", "link", "associate", "verify", "write", "map", "refine")


def scene_dir(num_cameras: int, num_instants: int, seed: int) -> Path:
    """The scene, made once (its synth time is logged, not benchmarked)."""
    from colmap_vc.synthetic import SynthOptions, generate

    name = f"scale_dome{num_cameras}x{num_instants}_s{seed}"
    scene = OUT / "scenes" / name
    if not ((scene / "database.db").exists() and scene_is_current(scene)):
        t0 = time.perf_counter()
        generate(
            "dome",
            scene,
            SynthOptions(
                seed=seed,
                num_cameras=num_cameras,
                num_instants=num_instants,
                num_people=3,
                sift=False,
                overwrite=True,
            ),
        )
        logger.info("synth %s: %.0f s", name, time.perf_counter() - t0)
    return scene


def one_run(scene: Path, work: Path, pairs: str, static: bool) -> dict:
    """augment + map + eval of one scene in this process (called as a subprocess)."""
    import pycolmap

    from colmap_vc import augment, mapping
    from colmap_vc.evaluation import evaluate_poses, poses_by_name

    if work.exists():
        shutil.rmtree(work)
    work.mkdir(parents=True)
    db = work / "database.db"
    shutil.copyfile(scene / "database.db", db)
    regex = r"(cam\d+)_" if static else None
    t0 = time.perf_counter()
    summary = augment.run(
        db,
        scene / "priors",
        augment.AugmentOptions(
            show_progress=False,
            static_cameras=regex,
            max_partners=None
            if pairs == "all"
            else augment.AugmentOptions().max_partners,
        ),
    )
    t_augment = time.perf_counter() - t0
    rss_augment = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t0 = time.perf_counter()
    rec, msum = mapping.run(
        db,
        scene / "images",
        work / "sparse",
        mapping.MappingOptions(show_progress=False, static_cameras=regex),
        priors_path=scene / "priors",
    )
    t_map = time.perf_counter() - t0
    gt = pycolmap.Reconstruction(scene / "gt" / "sparse")
    metrics = evaluate_poses(poses_by_name(rec), poses_by_name(gt))
    a, m = summary.timings_s, msum.timings_s
    stages = {
        "read": a.get("read", 0.0),
        "observe": a.get("observe", 0.0),
        "link": a.get("link", 0.0),
        "associate": a.get("associate", 0.0) - a.get("link", 0.0),
        "verify": a.get("verify", 0.0),
        "write": a.get("write", 0.0) + a.get("assemble", 0.0),
        "map": m.get("read", 0.0) + m.get("mapper", 0.0),  # with the mesh fallback
        "refine": m.get("refinement", 0.0)
        + m.get("checks", 0.0)
        + m.get("gravity", 0.0)
        + m.get("scale_write", 0.0),
    }
    self_kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    child_kib = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    return {
        "num_images": len(poses_by_name(gt)),
        "pairs_with_vcs": len(summary.pairs),
        "pairs_verified": summary.num_verified_pairs,
        "augment_s": t_augment,
        "map_s": t_map,
        "stages_s": stages,
        "peak_rss_mib": {
            "augment": rss_augment / 1024,
            "total": self_kib / 1024,
            "workers": child_kib / 1024,
        },
        "registered": metrics.num_registered,
        "auc": metrics.auc,
        "median_error_deg": metrics.median_error_deg,
    }


def run_subprocess(scene: Path, pairs: str, static: bool) -> dict:
    work = OUT / "runs" / "scale" / f"{scene.name}_{pairs}"
    out = work.parent / f"{scene.name}_{pairs}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    cmd = [
        sys.executable,
        str(Path(__file__).resolve()),
        "--one",
        str(scene),
        "--work",
        str(work),
        "--pairs",
        pairs,
        "--result",
        str(out),
    ]
    if static:
        cmd.append("--static-run")
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, cwd=ROOT / "bench")
    result = json.loads(out.read_text())
    result["wall_s"] = time.perf_counter() - t0
    return result


def slope(sizes: list[int], seconds: list[float]) -> float:
    """Least-squares slope of log(time) against log(images)."""
    x, y = np.log(sizes), np.log(np.maximum(seconds, 1e-3))
    return float(np.polyfit(x, y, 1)[0]) if len(x) >= 2 else float("nan")


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    dome = [r for r in rows if r["instants"] == 1]
    fig, ax = plt.subplots(1, 2, figsize=(11, 4.2))
    colours = dict(zip(STAGES, plt.get_cmap("tab10").colors, strict=False))
    for pairs, style in (("all", "--"), ("selected", "-")):
        sel = sorted(
            (r for r in dome if r["pairs"] == pairs), key=lambda r: r["num_images"]
        )
        if not sel:
            continue
        n = [r["num_images"] for r in sel]
        for stage in STAGES:
            ax[0].loglog(
                n,
                [max(r["stages_s"][stage], 1e-3) for r in sel],
                style,
                marker="o",
                color=colours[stage],
                label=stage if pairs == "selected" else None,
            )
        ax[1].plot(
            n,
            [r["peak_rss_mib"]["total"] + r["peak_rss_mib"]["workers"] for r in sel],
            style,
            marker="o",
            color="k",
            label=f"{pairs} pairs",
        )
    ax[0].plot([], [], "k-", label="selected pairs")
    ax[0].plot([], [], "k--", label="all pairs")
    ax[0].set_xticks([16, 32, 64, 128, 256], ["16", "32", "64", "128", "256"])
    ax[0].minorticks_off()
    ax[0].set(xlabel="images", ylabel="seconds", title="time per stage")
    ax[0].legend(fontsize=7, ncol=2)
    ax[1].set(xlabel="images", ylabel="MiB", title="peak resident memory")
    ax[1].legend()
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)


def table(rows: list[dict]) -> str:
    lines = [
        "| images | pairs | pairs with VCs / verified | "
        + " | ".join(STAGES)
        + " | augment + map | per image | peak RSS (MiB) | registered | AUC@15/30/45 |",
        "|" + "---|" * (len(STAGES) + 8),
    ]
    for r in rows:
        n = r["num_images"]
        label = (
            f"{n}"
            if r["instants"] == 1
            else f"{n} ({n // r['instants']} cams x {r['instants']})"
        )
        total = r["augment_s"] + r["map_s"]
        auc = r["auc"]
        lines.append(
            f"| {label} | {r['pairs']} "
            f"| {r['pairs_with_vcs']} / {r['pairs_verified']} | "
            + " | ".join(f"{r['stages_s'][s]:.1f}" for s in STAGES)
            + f" | **{total:.0f} s** | {1000 * total / n:.0f} ms "
            f"| {r['peak_rss_mib']['total'] + r['peak_rss_mib']['workers']:.0f} "
            f"| {r['registered']}/{n} "
            f"| {auc['15']:.1f}/{auc['30']:.1f}/{auc['45']:.1f} |"
        )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[16, 32, 64, 128, 256])
    parser.add_argument("--pairs", nargs="+", default=["all", "selected"])
    parser.add_argument(
        "--static", type=int, nargs=2, default=[32, 4], metavar=("CAMERAS", "INSTANTS")
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--keep", action="store_true", help="keep the rows of bench/out/scale.json"
    )
    parser.add_argument(
        "--max-all-pairs", type=int, default=128, help="largest size run with all pairs"
    )
    parser.add_argument("--one", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--work", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--result", type=Path, help=argparse.SUPPRESS)
    parser.add_argument(
        "--static-run", dest="static_flag", action="store_true", help=argparse.SUPPRESS
    )
    args = parser.parse_args()
    setup_logging()
    if args.one:
        result = one_run(args.one, args.work, args.pairs[0], args.static_flag)
        args.result.write_text(json.dumps(result, indent=1))
        return
    rows: list[dict] = []
    if args.keep:  # the rows of earlier runs that this one does not redo
        path = OUT / "scale.json"
        rows = json.loads(path.read_text())["rows"] if path.exists() else []
    plan = [
        (n, 1, p)
        for n in args.sizes
        for p in args.pairs
        if p != "all" or n <= args.max_all_pairs
    ]
    cams, instants = args.static
    if instants > 0:
        plan += [(cams, instants, p) for p in args.pairs]
    rows = [r for r in rows if (r["cameras"], r["instants"], r["pairs"]) not in plan]
    for cameras, k, pairs in plan:
        scene = scene_dir(cameras, k, args.seed)
        logger.info("run %s, %s pairs", scene.name, pairs)
        r = run_subprocess(scene, pairs, static=k > 1)
        r.update({"cameras": cameras, "instants": k, "pairs": pairs})
        rows.append(r)
        logger.info(
            "%d images (%s pairs): augment %.1f s, map %.1f s, AUC@15 %.1f",
            r["num_images"],
            pairs,
            r["augment_s"],
            r["map_s"],
            r["auc"]["15"],
        )
        write_json(
            "scale.json", {"machine": machine(), "cpus": os.cpu_count(), "rows": rows}
        )
    rows.sort(key=lambda r: (r["instants"], r["num_images"], r["pairs"]))
    slopes = {}
    for pairs in args.pairs:
        sel = sorted(
            (
                r
                for r in rows
                if r["instants"] == 1 and r["pairs"] == pairs and r["num_images"] >= 32
            ),
            key=lambda r: r["num_images"],
        )
        slopes[pairs] = {
            s: slope([r["num_images"] for r in sel], [r["stages_s"][s] for r in sel])
            for s in STAGES
        } | {
            "total": slope(
                [r["num_images"] for r in sel],
                [r["augment_s"] + r["map_s"] for r in sel],
            )
        }
    write_json("scale.json", {"machine": machine(), "rows": rows, "slopes": slopes})
    plot(rows, DOCS / "img" / "scale.png")
    slope_lines = [
        "| pairs | " + " | ".join(STAGES) + " | augment + map |",
        "|" + "---|" * (len(STAGES) + 2),
    ] + [
        f"| {p} | "
        + " | ".join(f"{v[s]:.2f}" for s in STAGES)
        + f" | {v['total']:.2f} |"
        for p, v in slopes.items()
    ]
    body = "\n".join(
        [
            table(rows),
            "",
            "Log-log slope of time against images (32 images and up; 1 is linear):",
            "",
            *slope_lines,
            "",
            "![time per stage and peak memory](img/scale.png)",
            "",
            f"{os.cpu_count()} cores, commit {machine()['commit']}, "
            "`.venv/bin/python bench/scale.py`; raw numbers in `bench/out/scale.json`.",
        ]
    )
    replace_section(DOCS / "benchmark.md", "scale", body)
    print(body)


if __name__ == "__main__":
    main()
