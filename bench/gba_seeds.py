"""The GBA against the keypoint BA over many scene draws: paired differences.

bench/accuracy.py pools two seeds per row, and a row of two 1-person domes moves
by 10 points of AUC@15 from one draw of the priors to the next. This bench asks
whether `map --gba` beats `map` (and the keypoints alone) by more than that: on
N fresh 1-person domes per prior level (VCs only, no SIFT), it maps each scene's
augmented database three ways from the same database and reports per-scene
AUC@15 and the paired difference of each two arms, with its standard error and
how many scenes it wins.

    .venv/bin/python bench/gba_seeds.py [--seeds 0 1 ... 11] [--levels realistic fitted]
        [--people 1] [--no-docs]

Writes bench/out/gba_seeds.json (gba_seeds_p<people>.json with --people) and the
table of docs/gba.md (section gba-seeds, gba-seeds-p<people>).
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
    WRONG_DEG,
    machine,
    replace_section,
    scene_is_current,
    setup_logging,
    write_json,
    wrong_cameras,
)

from colmap_vc import augment, mapping
from colmap_vc.evaluation import evaluate_reconstruction, pose_auc
from colmap_vc.keypoint_ba import KeypointBaOptions
from colmap_vc.synthetic import SynthOptions, generate

logger = logging.getLogger("bench.gba_seeds")

ARMS = {
    "keypoints": KeypointBaOptions(surface_per_image=0.0),
    "default": KeypointBaOptions(),
    "gba": KeypointBaOptions(surface_tracks=True),
}
LABELS = {
    "keypoints": "keypoints alone",
    "default": "`map`",
    "gba": "`map --gba`",
}


def scene_auc(level: str, people: int, seed: int) -> dict[str, dict]:
    """Per arm on one fresh dome (made once, kept under bench/out): AUC@15, the
    registered images and the wrong cameras among them."""
    path = OUT / "scenes" / f"seeds_dome_p{people}_s{seed}_{level}"
    stale = not ((path / "database.db").exists() and scene_is_current(path))
    if stale:
        generate(
            "dome",
            path,
            SynthOptions(
                seed=seed,
                num_people=people,
                noise=level,  # type: ignore[arg-type]
                sift=False,
                bystander=people >= 3,
                close_pair=people >= 3,
                overwrite=True,
            ),
        )
    gt = pycolmap.Reconstruction(path / "gt" / "sparse")
    work = OUT / "runs" / "gba_seeds" / path.name
    augmented = work / "augmented.db"
    if stale or not augmented.exists():
        work.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(path / "database.db", work / "tmp.db")
        augment.run(
            work / "tmp.db",
            path / "priors",
            augment.AugmentOptions(show_progress=False, use_classic_matches=False),
        )
        (work / "tmp.db").rename(augmented)
    out = {}
    for arm, options in ARMS.items():
        run = work / arm
        shutil.rmtree(run, ignore_errors=True)
        run.mkdir(parents=True)
        shutil.copyfile(augmented, run / "database.db")
        rec, _ = mapping.run_incremental(
            run / "database.db",
            path / "images",
            run / "sparse",
            mapping.MappingOptions(keypoint_ba_options=options, show_progress=False),
        )
        pairs = evaluate_reconstruction(rec, gt).pairs
        errors = np.array([p.error_deg for p in pairs])
        posed = {im.name for im in rec.images.values() if im.has_pose}
        wrong = wrong_cameras(pairs, posed)
        out[arm] = {
            "auc15": 100 * float(pose_auc(errors, [15.0])[0]),
            "registered": len(posed),
            "wrong": wrong,
        }
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=list(range(12)))
    parser.add_argument(
        "--levels", nargs="+", default=["realistic", "fitted"], help="prior levels"
    )
    parser.add_argument("--people", type=int, default=1)
    parser.add_argument("--no-docs", action="store_true")
    args = parser.parse_args()
    setup_logging()
    t0 = time.perf_counter()
    results: dict[str, dict[int, dict[str, dict]]] = {}
    for level in args.levels:
        for seed in args.seeds:
            logger.info("%s priors, seed %d", level, seed)
            results.setdefault(level, {})[seed] = scene_auc(level, args.people, seed)
    rows = [
        "| priors | scenes | mean AUC@15: keypoints alone / `map` / `map --gba` "
        "| `map --gba` - `map` | `map --gba` - keypoints | `map` - keypoints "
        "| wrong cameras / registered: keypoints, `map`, `map --gba` |",
        "|---|---|---|---|---|---|---|",
    ]
    summary: dict[str, dict] = {}
    for level, by_seed in results.items():
        auc = {a: np.array([by_seed[s][a]["auc15"] for s in args.seeds]) for a in ARMS}
        wrong = {a: sum(len(by_seed[s][a]["wrong"]) for s in args.seeds) for a in ARMS}
        posed = {a: sum(by_seed[s][a]["registered"] for s in args.seeds) for a in ARMS}
        diffs = {}
        for a, b in (
            ("gba", "default"),
            ("gba", "keypoints"),
            ("default", "keypoints"),
        ):
            d = auc[a] - auc[b]
            diffs[f"{a}-{b}"] = {
                "mean": float(d.mean()),
                "se": float(d.std(ddof=1) / np.sqrt(len(d))) if len(d) > 1 else 0.0,
                "wins": int((d > 0).sum()),
                "losses": int((d < 0).sum()),
            }
        summary[level] = {
            "mean_auc": {a: float(v.mean()) for a, v in auc.items()},
            "diffs": diffs,
            "wrong_cameras": wrong,
            "registered": posed,
        }
        cells = [
            f"{v['mean']:+.1f} ± {v['se']:.1f} ({v['wins']}-{v['losses']})"
            for v in diffs.values()
        ]
        means = " / ".join(f"{auc[a].mean():.1f}" for a in ARMS)
        bad = ", ".join(f"{wrong[a]}/{posed[a]}" for a in ARMS)
        rows.append(
            f"| {level} | {len(args.seeds)} | {means} | "
            + " | ".join(cells)
            + f" | {bad} |"
        )
    elapsed = time.perf_counter() - t0
    write_json(
        "gba_seeds.json" if args.people == 1 else f"gba_seeds_p{args.people}.json",
        {
            "machine": machine(),
            "seeds": args.seeds,
            "people": args.people,
            "results": {
                lv: {str(s): r for s, r in d.items()} for lv, d in results.items()
            },
            "summary": summary,
            "elapsed_s": elapsed,
        },
    )
    seeds = " ".join(map(str, args.seeds))
    body = "\n".join(
        [
            *rows,
            "",
            f"Measured at commit {machine()['commit']} by `.venv/bin/python "
            f"bench/gba_seeds.py --seeds {seeds} --people {args.people}` "
            f"({elapsed / 60:.0f} min): {args.people}-person domes"
            + (" (a bystander, two people close)" if args.people >= 3 else "")
            + ", VCs only, one "
            "scene per seed and level; differences are paired per scene, ± one "
            "standard error, (scenes won - lost). A wrong camera: registered, "
            f"with a median pair error above {WRONG_DEG:.0f} deg.",
        ]
    )
    print(body)
    if not args.no_docs:
        section = "gba-seeds" if args.people == 1 else f"gba-seeds-p{args.people}"
        replace_section(DOCS / "gba.md", section, body)


if __name__ == "__main__":
    main()
