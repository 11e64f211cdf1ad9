"""Pose accuracy of colmap-vc against the baselines, on the same images in the same run.

Scenes: `dome` with 1 and with 3 people, `dense`, and `pair` at angles in 30-degree
bins; priors `clean`, `realistic`, `hard` and `fitted` (the bundled estimator's
fit to landmarks with the noise measured on pose2sim, whose dense map repeats the
landmarks' errors as on real photos); several seeds. The priors are anonymous
and have the detection failures of their level (docs/synthetic.md), as a detector's
output; the 3-person domes add a bystander and two people standing close (dressed
alike on odd seeds), and are also run with the true ids given ("ids given": the same
scenes and priors with gt/persons.json's ids added), the upper bound of the
association. Methods:

- classic COLMAP: SIFT, exhaustive matching, COLMAP's incremental mapper at its
  defaults with the known intrinsics fixed (baselines.colmap_incremental);
- mesh alignment: Procrustes between the predicted meshes of the same person;
- VC init: VCs only, registration and triangulation without COLMAP's BA;
- VC + BA: VCs only, pycolmap incremental mapping (COLMAP's BA);
- VC + keypoint BA: then the keypoint bundle adjustment (`colmap-vc map`'s default);
- VC + GBA: the generalized bundle adjustment instead (`map --gba`, docs/gba.md);
- VC + classic + keypoint BA: VCs verified jointly with the classic matches, `map`;
- VC + classic + GBA: the same, with `map --gba`.

    .venv/bin/python bench/accuracy.py [--seeds 0 1 2] [--quick]
        [--groups "dome, 3 people"] [--cameras 8] [--no-docs]

Writes bench/out/accuracy.json and docs/results.md (tables shaped like the paper's
Tables 1 and 2, and the error against the ground-truth camera angle, Fig. 8/9 analog).
"""

from __future__ import annotations

import argparse
import itertools
import logging
import re
import shutil
import time
from pathlib import Path

import numpy as np
import pycolmap
from common import DOCS, OUT, machine, scene_is_current, setup_logging, write_json

from colmap_vc import augment, database, mapping
from colmap_vc.baselines import mesh_alignment_poses, run_classic
from colmap_vc.evaluation import (
    THRESHOLDS_DEG,
    Metrics,
    PairError,
    evaluate_poses,
    evaluate_reconstruction,
    pose_auc,
    poses_by_name,
)
from colmap_vc.keypoint_ba import KeypointBaOptions
from colmap_vc.priors import read_priors
from colmap_vc.synthetic import SynthOptions, generate
from colmap_vc.synthetic.gt import (
    FALSE_DETECTION,
    add_true_ids,
    gt_persons_path,
    read_gt_persons,
)

logger = logging.getLogger("bench.accuracy")

LEVELS = {
    "clean": "priors_clean",
    "realistic": "priors",
    "hard": "priors_hard",
    "fitted": "priors_fitted",
}
IDS = " (ids given)"
"""Suffix of a level run on the same priors with the true ids added."""
MULTI = "dome, 3 people"
PAIR_ANGLES = (15.0, 45.0, 75.0, 105.0, 135.0, 165.0)
METHODS = (
    "classic COLMAP",
    "mesh alignment",
    "VC init",
    "VC + BA",
    "VC + keypoint BA",
    "VC + GBA",
    "VC + classic + keypoint BA",
    "VC + classic + GBA",
)


LEGEND = [
    "Methods: *classic COLMAP* (SIFT, exhaustive matching, COLMAP's incremental "
    "mapper at its defaults with the known intrinsics fixed: COLMAP itself, "
    "`baselines.colmap_incremental`; with two images it needs an initial pair of "
    "100 inliers and 16 deg triangulation angle); *mesh "
    "alignment* (Procrustes between the predicted meshes); *VC init* (VCs only, "
    "registration and triangulation without BA); *VC + BA* (pycolmap's mapper with "
    "its BA); *VC + keypoint BA* (then the keypoint bundle adjustment: what "
    "`colmap-vc map` does); *VC + GBA* (`map --gba`: the generalized BA instead, "
    "every surface VC a track by identity, weighted by its spread and its "
    "correlation with its neighbours, docs/gba.md); *+ classic*: VCs verified "
    "together with the SIFT matches.",
    "",
]


def scene(
    preset: str,
    people: int,
    seed: int,
    angle: float | None = None,
    cameras: int | None = None,
) -> Path:
    tag = f"{preset}_p{people}_s{seed}" + ("" if angle is None else f"_a{int(angle)}")
    tag += "" if cameras is None else f"_c{cameras}"
    path = OUT / "scenes" / f"acc_{tag}"
    crowd = people >= 3
    wanted = [path / "database.db", path / "priors_hard", path / "priors_clean"]
    wanted += [gt_persons_path(path, folder) for folder in LEVELS.values()]
    if not (all(p.exists() for p in wanted) and scene_is_current(path)):
        generate(
            preset,
            path,
            SynthOptions(
                seed=seed,
                num_people=people,
                num_cameras=cameras,
                pair_angle_deg=angle,
                extra_noise=("hard", "clean", "fitted"),
                bystander=crowd,
                close_pair=crowd,
                dress_alike=crowd and seed % 2 == 1,
                overwrite=True,
            ),
        )
    if crowd:
        for folder in LEVELS.values():
            add_true_ids(path, folder, folder + "_ids")
    return path


def detection_stats(scene_dir: Path, folder: str) -> dict:
    """What the priors of ``folder`` report against the people actually visible."""
    who = read_gt_persons(gt_persons_path(scene_dir, folder))
    visible = sum(len(v) for v in who.visible.values())
    reported = sum(
        sum(i != FALSE_DETECTION for i in ids) for ids in who.images.values()
    )
    false = sum(ids.count(FALSE_DETECTION) for ids in who.images.values())
    bystanders = [i for i, role in who.people.items() if role == "bystander"]
    return {
        "visible": visible,
        "reported": reported,
        "false": false,
        "bystander_views": sum(
            any(b in ids for b in bystanders) for ids in who.images.values()
        ),
    }


def run_vc(
    scene_dir: Path,
    priors_dir: Path,
    work: Path,
    *,
    with_classic: bool,
    ba: bool,
    kba: bool,
    gba: bool,
    augmented: dict[bool, tuple[Path, float]],
):
    """Augment a copy of the scene's database and map it -> (model or None, augment
    time in seconds).

    ``augmented`` caches the augmented database per ``with_classic`` (the arms differ
    only after augment, which is deterministic): later arms start from a copy of it.
    """
    work.mkdir(parents=True, exist_ok=True)
    db = work / "database.db"
    if with_classic in augmented:
        cached, augment_s = augmented[with_classic]
        shutil.copyfile(cached, db)
    else:
        shutil.copyfile(scene_dir / "database.db", db)
        if not with_classic:
            database.drop_classic_matches(db)
        t0 = time.perf_counter()
        augment.run(
            db,
            priors_dir,
            augment.AugmentOptions(
                show_progress=False, use_classic_matches=with_classic
            ),
        )
        augment_s = time.perf_counter() - t0
        cached = work.parent / f"augmented_classic{int(with_classic)}.db"
        shutil.copyfile(db, cached)
        augmented[with_classic] = (cached, augment_s)
    shutil.rmtree(work / "sparse", ignore_errors=True)  # the bench's own output
    rec, _ = mapping.run_incremental(
        db,
        scene_dir / "images",
        work / "sparse",
        mapping.MappingOptions(
            bundle_adjustment=ba,
            keypoint_ba=kba or gba,
            keypoint_ba_options=KeypointBaOptions(surface_tracks=gba),
            show_progress=False,
        ),
    )
    return rec, augment_s


def evaluate_scene(
    scene_dir: Path, level: str, work: Path, classic: Metrics
) -> tuple[dict[str, Metrics], dict[str, float]]:
    """Every method on one scene and priors folder -> metrics, augment seconds."""
    gt = pycolmap.Reconstruction(scene_dir / "gt" / "sparse")
    gt_poses = poses_by_name(gt)
    folder = LEVELS[level.removesuffix(IDS)] + ("_ids" if level.endswith(IDS) else "")
    priors = read_priors(scene_dir / folder)
    out = {
        "classic COLMAP": classic,
        "mesh alignment": evaluate_poses(mesh_alignment_poses(priors), gt_poses),
    }
    arms = {
        "VC init": (False, False, False, False),
        "VC + BA": (False, True, False, False),
        "VC + keypoint BA": (False, True, True, False),
        "VC + GBA": (False, True, False, True),
        "VC + classic + keypoint BA": (True, True, True, False),
        "VC + classic + GBA": (True, True, False, True),
    }
    augment_s: dict[str, float] = {}
    augmented: dict[bool, tuple[Path, float]] = {}
    for name, (with_classic, ba, kba, gba) in arms.items():
        rec, augment_s[name] = run_vc(
            scene_dir,
            scene_dir / folder,
            work / name.replace(" ", "_").replace("+", "p"),
            with_classic=with_classic,
            ba=ba,
            kba=kba,
            gba=gba,
            augmented=augmented,
        )
        out[name] = evaluate_reconstruction(rec, gt)
    return out, augment_s


def pooled(metrics: list[Metrics], augment_s: list[float] | None = None) -> dict:
    """AUC and registration over the pooled pairs of several scenes, as in the paper;
    the mean augment time per scene when given."""
    errors = np.array([p.error_deg for m in metrics for p in m.pairs])
    aucs = pose_auc(errors, THRESHOLDS_DEG)
    return {
        "augment_s": float(np.mean(augment_s)) if augment_s else None,
        "auc": {f"{t:g}": 100 * a for t, a in zip(THRESHOLDS_DEG, aucs, strict=True)},
        "median_error_deg": float(np.median(errors)) if len(errors) else float("nan"),
        "registered": sum(m.num_registered for m in metrics),
        "images": sum(m.num_images for m in metrics),
        "num_pairs": len(errors),
    }


def table(rows: dict[str, dict], caption: str) -> str:
    lines = [
        f"**{caption}**",
        "",
        "| method | registered | AUC@15 | AUC@30 | AUC@45 | median err (deg) "
        "| augment (s) |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, r in rows.items():
        aug = "" if r.get("augment_s") is None else f"{r['augment_s']:.1f}"
        lines.append(
            f"| {name} | {r['registered']}/{r['images']} | {r['auc']['15']:.1f} | "
            f"{r['auc']['30']:.1f} | {r['auc']['45']:.1f} | "
            f"{r['median_error_deg']:.1f} | {aug} |"
        )
    return "\n".join(lines)


def detection_line(stats: list[dict]) -> str:
    """One sentence: what the priors reported, pooled over the seeds."""
    visible = sum(s["visible"] for s in stats)
    reported = sum(s["reported"] for s in stats)
    return (
        f"Priors: {reported} of {visible} visible people reported "
        f"({100 * reported / max(visible, 1):.0f}%), "
        f"{sum(s['false'] for s in stats)} false detection(s), a bystander reported "
        f"in {sum(s['bystander_views'] for s in stats)} image(s)."
    )


def angle_plot(pairs_by_method: dict[str, list[PairError]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    bins = np.arange(0, 181, 30)
    fig, ax = plt.subplots(1, 2, figsize=(11, 4))
    for name, pairs in pairs_by_method.items():
        angle = np.array([p.gt_angle_deg for p in pairs])
        err = np.array([p.error_deg for p in pairs])
        med, auc30 = [], []
        for lo, hi in itertools.pairwise(bins):
            sel = (angle >= lo) & (angle < hi)
            med.append(np.median(err[sel]) if sel.any() else np.nan)
            auc30.append(100 * pose_auc(err[sel], [30])[0] if sel.any() else np.nan)
        centres = (bins[:-1] + bins[1:]) / 2
        ax[0].plot(centres, med, marker="o", label=name)
        ax[1].plot(centres, auc30, marker="o", label=name)
    ax[0].set(
        xlabel="ground-truth angle between the two cameras (deg)",
        ylabel="median pose error (deg)",
        yscale="log",
        title="Pose error vs camera angle (realistic priors)",
    )
    ax[1].set(
        xlabel="ground-truth angle between the two cameras (deg)",
        ylabel="AUC@30 (%)",
        ylim=(0, 100),
        title="AUC@30 vs camera angle",
    )
    ax[0].legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument(
        "--quick", action="store_true", help="one seed, no pair sweep, realistic only"
    )
    parser.add_argument(
        "--groups",
        nargs="+",
        default=None,
        help='only these groups, e.g. "dome, 3 people"',
    )
    parser.add_argument(
        "--cameras", type=int, default=None, help="cameras per dome/dense scene"
    )
    parser.add_argument(
        "--no-docs", action="store_true", help="do not write docs/results.md"
    )
    args = parser.parse_args()
    setup_logging()
    seeds = args.seeds[:1] if args.quick else args.seeds
    base_levels = ["realistic"] if args.quick else list(LEVELS)
    groups = {
        "dome, 1 person": ("dome", 1, None),
        MULTI: ("dome", 3, None),
        "dense, 1 person": ("dense", 1, None),
    }
    if not args.quick:
        groups |= {
            f"pair, {int(a) - 15}-{int(a) + 15} deg": ("pair", 1, a)
            for a in PAIR_ANGLES
        }
    if args.groups:
        unknown = set(args.groups) - set(groups)
        if unknown:
            parser.error(f"unknown groups {sorted(unknown)}; known: {list(groups)}")
        groups = {g: groups[g] for g in args.groups}
    t0 = time.perf_counter()
    results: dict[str, dict[str, dict[str, list[Metrics]]]] = {}
    augment_times: dict[str, dict[str, dict[str, list[float]]]] = {}
    detections: dict[str, dict[str, list[dict]]] = {}
    for group, (preset, people, angle) in groups.items():
        levels = [
            lv + suffix
            for lv in base_levels
            for suffix in (("", IDS) if group == MULTI else ("",))
        ]
        for seed in seeds:
            scene_dir = scene(preset, people, seed, angle, args.cameras)
            work = OUT / "runs" / "accuracy" / scene_dir.name
            _, classic = run_classic(scene_dir, work / "classic")
            for level in levels:
                logger.info("%s seed %d, %s priors", group, seed, level)
                metrics, seconds = evaluate_scene(
                    scene_dir, level, work / level.replace(IDS, "_ids"), classic
                )
                for method, m in metrics.items():
                    results.setdefault(group, {}).setdefault(level, {}).setdefault(
                        method, []
                    ).append(m)
                for method, sec in seconds.items():
                    augment_times.setdefault(group, {}).setdefault(
                        level, {}
                    ).setdefault(method, []).append(sec)
                if not level.endswith(IDS):
                    detections.setdefault(group, {}).setdefault(level, []).append(
                        detection_stats(scene_dir, LEVELS[level])
                    )
    summary = {
        g: {
            lv: {
                meth: pooled(ms, augment_times[g][lv].get(meth))
                for meth, ms in by_m.items()
            }
            for lv, by_m in by_l.items()
        }
        for g, by_l in results.items()
    }
    elapsed = time.perf_counter() - t0
    write_json(
        "accuracy.json",
        {
            "machine": machine(),
            "seeds": seeds,
            "summary": summary,
            "detections": detections,
            "elapsed_s": elapsed,
        },
    )
    print(f"elapsed {elapsed:.0f} s")

    def tables(group: str, level: str, caption: str) -> list[str]:
        out = []
        if level in summary.get(group, {}):
            out += [table(summary[group][level], caption), ""]
            if level in detections.get(group, {}):
                out += [detection_line(detections[group][level]), ""]
        if level + IDS in summary.get(group, {}):
            out += [table(summary[group][level + IDS], caption + IDS), ""]
        return out

    cmd = f".venv/bin/python bench/accuracy.py --seeds {' '.join(map(str, seeds))}" + (
        " --quick" if args.quick else ""
    )
    doc = [
        "# Results",
        "",
        f"Generated by `{cmd}`"
        + (" (`make bench`)" if seeds == [0, 1] and not args.quick else "")
        + f" at commit {machine()['commit']}; "
        "every method runs on the same images in the same run. A pair with an "
        "unregistered image counts as 180 degrees; AUC as in SuperGlue "
        "(docs/benchmark.md has the set-up checks and speed). The priors are "
        "anonymous with the detection failures of their level (docs/synthetic.md); "
        "the 3-person domes (with a bystander and two people close together) are "
        "also run on the same priors with the true ids given (the *ids given* "
        "tables), the upper bound of the association. *augment (s)*: mean time of "
        "`augment` per scene.",
        "",
    ]
    doc += LEGEND
    doc.append("## Table 1 analog: methods on each dataset (realistic priors)\n")
    for group in groups:
        doc += tables(group, "realistic", group)
    doc.append(
        "## The bundled estimator's priors (fitted): methods on each dataset\n\n"
        "The `fitted` level fits the Anny body to landmarks with the noise measured "
        "on pose2sim and ray-casts the mask on it, as the bundled estimator does on "
        "photos: its dense map repeats the landmarks' errors (docs/synthetic.md, "
        '"The fitted level").\n'
    )
    for group in groups:
        doc += tables(group, "fitted", f"{group}, fitted priors")
    doc.append("## Table 2 analog: ablation on the dome, by prior noise\n")
    for group in ("dome, 1 person", MULTI):
        for level in base_levels:
            doc += tables(group, level, f"{group}, {level} priors")
    pairs_by_method: dict[str, list[PairError]] = {}
    for group in results:
        for method, ms in results[group].get("realistic", {}).items():
            pairs_by_method.setdefault(method, []).extend(
                p for m in ms for p in m.pairs
            )
    if args.no_docs:
        print("\n".join(doc))
        return
    angle_plot(pairs_by_method, DOCS / "img" / "error_vs_angle.png")
    doc += [
        "## Error against the camera angle (Fig. 8/9 analog)",
        "",
        "All image pairs of all scenes above, realistic priors, binned by the "
        "ground-truth angle between the two cameras.",
        "",
        "![error vs angle](img/error_vs_angle.png)",
        "",
    ]
    # Keep everything from the first section other benches own (<!-- name:begin -->
    # ... <!-- name:end -->: pose2sim.py, realdata.py, static_cameras.py, ...) to
    # the end, the prose written between those sections included.
    path = DOCS / "results.md"
    old = path.read_text() if path.exists() else ""
    first = re.search(r"<!-- [\w-]+:begin -->", old)
    if first:
        doc += ["", old[first.start() :]]
    path.write_text("\n".join(doc))
    print("\n".join(doc))


if __name__ == "__main__":
    main()
