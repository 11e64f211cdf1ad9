"""Metric scale: how far `map`'s models in metres are from the ground truth's size.

Reads the models `bench/accuracy.py` left (the default `map`, "VC + keypoint BA",
under bench/out/runs/accuracy), the default `map`'s models of `bench/gba_seeds.py`
(twelve domes per level, with one person and with three: the accuracy bench has
three) and the static-camera models of `bench/static_cameras.py`, and compares
camera distances with the ground truth: the median over camera pairs of model
distance / true distance (1 = right size), and how often the truth lies within
one and two of the uncertainty `map` reports with its scale (estimated again on
every model with today's code, and the priors' own size beside it on the
synthetic scenes). A scene made with another noise model than today's is left
out.
``--instants`` reads the per-instant models of `bench/evidence.py --seeds` instead
(`map` and `map --gba` on each seed's databases: pose2sim's instants, 4 images
each) and writes bench/out/metric_scale_instants.json and the "scale-instants"
section.

    .venv/bin/python bench/metric_scale.py   # after accuracy.py and gba_seeds.py
    .venv/bin/python bench/metric_scale.py --instants  # after evidence.py --seeds

Writes bench/out/metric_scale.json and the "scale" section of docs/results.md.
"""

from __future__ import annotations

import argparse
import json
import logging
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pycolmap
from accuracy import LEVELS
from common import DOCS, OUT, machine, replace_section, scene_is_current, write_json
from evidence import ARMS
from realdata import SHARED, load_calibration

from colmap_vc.evaluation import camera_distance_ratio, evaluate_poses, poses_by_name
from colmap_vc.mapping import MappingOptions
from colmap_vc.mapping.inputs import read_inputs
from colmap_vc.mapping.pipeline import people_scale
from colmap_vc.metric_scale import read_metric_scale, skeleton_ratio
from colmap_vc.priors import read_priors
from colmap_vc.synthetic.gt import gt_persons_path, read_gt_persons

ARM = "VC_p_keypoint_BA"
logger = logging.getLogger(__name__)


def _largest(sparse: Path) -> tuple[pycolmap.Reconstruction, Path] | None:
    best = None
    for d in sorted(sparse.rglob("images.bin")):
        rec = pycolmap.Reconstruction(d.parent)
        if best is None or rec.num_reg_images() > best[0].num_reg_images():
            best = (rec, d.parent)
    return best


def scale_info(folder: Path, database_path: Path | None, ratio: float) -> dict:
    """What `map` wrote beside a model (metric_scale.json), with the scale and
    uncertainty of today's code: estimated again on the model with
    ``database_path``'s priors (and the static cameras augment recorded there).
    ``ratio`` (the model's camera distances over the truth's, as written) comes
    back as the ratio the model has with today's scale (``map`` applies the
    scale last, so mapping again would give the same model at that scale), and
    as written (``ratio_as_written``). Without a database, or where the file has
    none, from what was written (``read_metric_scale``)."""
    scale = read_metric_scale(folder)
    if scale is None:
        return {"ratio": ratio}
    info = {**asdict(scale), "ratio": ratio, "ratio_as_written": ratio}
    if database_path is not None:
        again = people_scale(
            pycolmap.Reconstruction(folder),
            read_inputs(database_path, MappingOptions(), None),
            MappingOptions(),
        )
        if again is not None:
            info["ratio"] = ratio * again.scale
            info["uncertainty"] = again.uncertainty
            info["relative_pose"] = again.relative_pose
    return info


def priors_size(scene: Path, level: str, folder: str | None = None) -> float | None:
    """How large the priors of ``level`` make the people: over every person view
    of a real person, its skeleton's size predicted / true (``skeleton_ratio``,
    as `map` reads the scale), and the median of those (``realistic_ids`` reads
    ``realistic``'s priors). The ratio a model would have if the priors' size
    were all there is: the person's shared size error (scene.json's
    ``size_error``), one per view, and what another body's proportions and the
    joints' errors add (docs/synthetic.md). ``folder``: the
    scene's folder of those priors, where it is not the accuracy bench's."""
    folder = folder or LEVELS[level.removesuffix("_ids")]
    persons = gt_persons_path(scene, folder)
    if not persons.exists():
        return None
    truth = read_priors(scene / "gt" / "priors")
    predicted = read_priors(scene / folder)
    who = read_gt_persons(persons)
    ratios = []
    for name, image in predicted.images.items():
        true_person = {p.person_id: p for p in truth.images[name].persons}
        for person, true_id in zip(image.persons, who.images[name], strict=True):
            if true_id not in true_person:  # a false detection
                continue
            true = np.asarray(true_person[true_id].keypoints_cam)
            joints = len(true)  # the fitted level adds surface landmarks after them
            valid = np.asarray(person.keypoints_valid)[:joints]
            if valid.sum() < 2:
                continue
            guess = np.asarray(person.keypoints_cam)[:joints][valid]
            ratios.append(skeleton_ratio(guess, true[valid]))
    return float(np.median(ratios)) if ratios else None


WRONG_DEG = 30.0
"""A two-camera model further than this from the calibration is a wrong one."""


def two_camera_models() -> dict[str, list[dict]]:
    """pose2sim's two-camera models of one instant (`bench/subsets.py`): the
    ratio of camera distances to the calibration's, the relative pose's error
    and the scale `map` reports, estimated again on the model."""
    out: dict[str, list[dict]] = {}
    for ds in ("single", "multi"):
        runs = sorted((OUT / "subsets" / ds / "one_instant").glob("t*_cam*-cam*"))
        if not runs:
            continue
        _, gt = load_calibration(SHARED / f"pose2sim_{ds}")
        for run in runs:  # loop over models
            found = _largest(run / "sparse")
            if found is None or run.name.count("cam") != 2:
                continue
            rec, folder = found
            pred = poses_by_name(rec)
            if len(pred) != 2:
                continue
            truth = {name: gt[name] for name in pred}
            out.setdefault(ds, []).append(
                {
                    "model": run.name,
                    "pair_error_deg": evaluate_poses(pred, truth).median_error_deg,
                    **scale_info(
                        folder, run / "database.db", camera_distance_ratio(pred, truth)
                    ),
                }
            )
    return out


def run_commit(name: str) -> str:
    """The commit a bench ran at (bench/out/``name``'s JSON), or "-"."""
    path = OUT / name
    if not path.exists():
        return "-"
    return str(json.loads(path.read_text()).get("machine", {}).get("commit", "-"))


def seeds_domes() -> dict[str, dict[str, list[dict]]]:
    """The default `map`'s models of `bench/gba_seeds.py`'s domes (twelve scene
    draws per level and number of people, where the accuracy bench has three):
    the ratio of camera distances to the truth, the priors' size and the scale's
    uncertainty, estimated again on the model."""
    rows: dict[str, dict[str, list[dict]]] = {}
    for run in sorted((OUT / "runs" / "gba_seeds").glob("seeds_dome_p*_s*_*")):
        scene = OUT / "scenes" / run.name
        found = _largest(run / "default" / "sparse")
        if found is None or not (scene / "gt" / "sparse").is_dir():
            continue
        if not scene_is_current(scene):  # made with another noise model
            logger.warning("%s: left out, made with another noise model", run.name)
            continue
        _, people, seed, level = run.name.split("_")[1:]
        gt = poses_by_name(pycolmap.Reconstruction(scene / "gt" / "sparse"))
        key = f"dome, {people[1:]} {'person' if people == 'p1' else 'people'}"
        rows.setdefault(key, {}).setdefault(level, []).append(
            {
                "scene": run.name,
                "seed": int(seed[1:]),
                "priors_size": priors_size(scene, level, "priors"),
                **scale_info(
                    found[1],
                    run / "default" / "database.db",
                    camera_distance_ratio(poses_by_name(found[0]), gt),
                ),
            }
        )
    for levels in rows.values():
        for items in levels.values():
            items.sort(key=lambda it: it["seed"])
    return rows


def coverage(items: list[dict]) -> str:
    """The median uncertainty, and in how many models the truth lies within one
    and two uncertainties of the scale (|log ratio| <= k u)."""
    pairs = [
        (abs(np.log(it["ratio"])), it["uncertainty"])
        for it in items
        if np.isfinite(it["ratio"]) and it["ratio"] > 0 and "uncertainty" in it
    ]
    if not pairs:
        return "- | -"
    z = np.array([e / u for e, u in pairs])
    median_u = np.median([u for _, u in pairs])
    return (
        f"{100 * median_u:.1f}% | {int((z <= 1).sum())} / {int((z <= 2).sum())} "
        f"of {len(z)}"
    )


def per_instant(ds: str, arm: str) -> list[dict]:
    """The scale of each per-instant model of `bench/evidence.py --seeds`'s ``arm``
    on pose2sim_``ds`` (4 images; every seed and instant it mapped)."""
    _, gt = load_calibration(SHARED / f"pose2sim_{ds}")
    key = f"arm{list(ARMS).index(arm)}"
    out = []
    for instant_dir in sorted((OUT / "evidence_seeds" / ds / key).glob("seed*/t*")):
        found = _largest(instant_dir)
        if found is None:
            continue
        now = {n: g for n, g in gt.items() if instant_dir.name in n}
        ratio = camera_distance_ratio(poses_by_name(found[0]), now)
        seed = instant_dir.parent.name
        where = "order0" if seed == "seed0" else seed
        db = OUT / "realdata" / ds / instant_dir.name / where / "database.db"
        out.append(
            {
                "model": f"{seed}/{instant_dir.name}",
                **scale_info(found[1], db if db.exists() else None, ratio),
            }
        )
    return out


def synthetic_rows(
    rows: dict[str, dict[str, list[dict]]],
    label: str = "",
    levels: set[str] | None = None,
) -> list[str]:
    """One table row per scene kind and prior level (``levels``: those only)."""
    lines = []
    for key, by_level in rows.items():
        for level, items in by_level.items():
            if levels is not None and level not in levels:
                continue
            ratios = [it["ratio"] for it in items if np.isfinite(it["ratio"])]
            scaled = f"{sum('scale' in it for it in items)}/{len(items)}"
            median = f"{np.median(ratios):.3f}" if ratios else "-"
            listed = " ".join(f"{r:.3f}" for r in ratios) or "-"
            sizes = [it.get("priors_size") for it in items]
            priors = (
                " ".join(f"{x:.3f}" for x in sizes)
                if all(x is not None for x in sizes)
                else "-"
            )
            lines.append(
                f"| {key}{label} | {level} | {len(items)} | {median} | {listed} "
                f"| {priors} | {scaled} | {coverage(items)} |"
            )
    return lines


def main() -> None:
    rows: dict[str, dict[str, list[dict]]] = {}
    for run in sorted((OUT / "runs" / "accuracy").glob("acc_*")):
        scene = OUT / "scenes" / run.name
        if not (scene / "gt" / "sparse").is_dir():
            continue
        gt = poses_by_name(pycolmap.Reconstruction(scene / "gt" / "sparse"))
        group = "dome" if "_dome_" in run.name else run.name.split("_")[1]
        people = run.name.split("_")[2][1:]
        for level_dir in sorted(p for p in run.iterdir() if p.is_dir()):
            found = _largest(level_dir / ARM / "sparse")
            if found is None:
                continue
            rec, folder = found
            db = level_dir / ARM / "database.db"
            ratio = camera_distance_ratio(poses_by_name(rec), gt)
            info = scale_info(folder, db if db.exists() else None, ratio)
            key = f"{group}, {people} {'person' if people == '1' else 'people'}"
            size = priors_size(scene, level_dir.name)
            rows.setdefault(key, {}).setdefault(level_dir.name, []).append(
                {"scene": run.name, "priors_size": size, **info}
            )
    static = OUT / "static_cameras.json"
    real: dict[str, dict] = {}
    if static.exists():
        for ds, by_variant in json.loads(static.read_text())["results"].items():
            for variant, r in by_variant.items():  # `map --no-gravity`, `map`
                if "distance_ratio" in r:
                    key = f"pose2sim_{ds}, static cameras (20 images), `{variant}`"
                    sparse = "sparse" + variant.removeprefix("map").replace(" --", "_")
                    where = OUT / "static_cameras" / ds
                    db = where / "database.db"
                    real[key] = {
                        **scale_info(
                            where / sparse / "0",
                            db if db.exists() else None,
                            r["distance_ratio"],
                        ),
                    }
    pairs = two_camera_models()
    seeds = seeds_domes()
    write_json(
        "metric_scale.json",
        {
            "machine": machine(),
            "synthetic": rows,
            "synthetic_seeds": seeds,
            "real": real,
            "pairs": pairs,
        },
    )
    lines = [
        "| scenes | priors | models | median ratio | ratios (one per scene) "
        "| the priors' size (one per scene) "
        "| scaled models | median uncertainty | truth within 1 / 2 uncertainties |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    lines += synthetic_rows(rows)
    lines += synthetic_rows(
        seeds, " (twelve draws, `bench/gba_seeds.py`)", {"realistic", "fitted"}
    )
    for name, it in real.items():
        ratio = it["ratio"]
        lines.append(
            f"| {name} | real photos | 1 | {ratio:.3f} | {ratio:.3f} | - | 1/1 "
            f"| {coverage([it])} |"
        )
    for ds, items in pairs.items():
        near = [it for it in items if it["pair_error_deg"] <= WRONG_DEG]
        for label, chosen in (("", items), (f", within {WRONG_DEG:.0f} deg", near)):
            ratios = [it["ratio"] for it in chosen]
            lines.append(
                f"| pose2sim_{ds}, one instant, two cameras{label} | real photos "
                f"| {len(chosen)} | {np.median(ratios):.3f} | - | - "
                f"| {len(chosen)}/{len(chosen)} | {coverage(chosen)} |"
            )
    lines += [
        "",
        f"Measured at commit {machine()['commit']} by `.venv/bin/python "
        "bench/metric_scale.py` on the models of `bench/accuracy.py` (the default "
        "`map`), `bench/gba_seeds.py` (the default `map`; mapped at "
        f"{run_commit('gba_seeds.json')} with one person, "
        f"{run_commit('gba_seeds_p3.json')} with three) and "
        "`bench/static_cameras.py`: per model the median over camera pairs "
        "of the model's distance between two cameras over the true one (1: metres "
        "exactly), at the scale today's code gives the model (estimated again on "
        "it; `map` applies the scale last, so mapping again gives the same model "
        "at that scale). *scaled models*: those `map` could scale (it needs "
        "triangulated keypoints of people with priors). *the priors' size*: the "
        "median over the real people's views of their skeleton's size predicted "
        "/ true (`colmap_vc.metric_scale.skeleton_ratio`, as `map` reads it: a "
        "size error per person shared by its views, one per view, and what "
        "another body's proportions and the joints' errors add: "
        "docs/synthetic.md), the ratio if that were all. "
        "*uncertainty*: the relative standard "
        "error `map` reports with the scale (metric_scale.json: the people's shared "
        "size error, 7% per person, and the views' spread, widened where the "
        "people of one instant disagree beyond it (the Birge ratio), and for two "
        "images "
        "that only their people place, the relative pose's part; estimated again "
        "on every model with today's code); *truth within*: models "
        "whose |log ratio| is at most one and two of it. *pose2sim, one instant, "
        "two cameras*: the two-camera models of `bench/subsets.py` that `map` "
        f"wrote (at {run_commit('subsets.json')}); *within {WRONG_DEG:.0f} deg*: "
        "those whose relative pose is "
        "within it of the calibration (a wrong pose's scale is as wrong as the "
        "pose, and `map` warns of such pairs).",
    ]
    replace_section(
        DOCS / "results.md",
        "scale",
        "## Metric scale from the people\n\n" + "\n".join(lines),
    )
    print("\n".join(lines))


def instants_section() -> None:
    """The "scale-instants" section: pose2sim per instant, every seed, both
    refinements (the models of `bench/evidence.py --seeds`)."""
    results = {
        f"pose2sim_{ds} | `{name}`": per_instant(ds, arm)
        for ds in ("single", "multi")
        for name, arm in (
            ("map", "keypoints + surface + up (`map`)"),
            ("map --gba", "GBA (`map --gba`): surface tracks by identity + up"),
        )
    }
    write_json("metric_scale_instants.json", {"machine": machine(), **results})
    lines = [
        "| data | refinement | models | median ratio | per instant: median "
        "(range over seeds) | within 5% | median uncertainty "
        "| truth within 1 / 2 uncertainties |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, items in results.items():
        r = np.array([it["ratio"] for it in items])
        when = np.array([it["model"].split("/")[1] for it in items])
        ok = np.isfinite(r)
        each = ", ".join(
            f"{t} {np.median(r[ok & (when == t)]):.3f} "
            f"({r[ok & (when == t)].min():.3f}-{r[ok & (when == t)].max():.3f})"
            for t in sorted(set(when[ok].tolist()))
        )
        within = int((np.abs(r[ok] - 1.0) <= 0.05).sum())
        lines.append(
            f"| {name} | {len(items)} | {np.median(r[ok]):.3f} | {each} "
            f"| {within}/{len(items)} | {coverage(items)} |"
        )
    lines += [
        "",
        f"Measured at commit {machine()['commit']} by `.venv/bin/python "
        "bench/metric_scale.py --instants` on the models of `bench/evidence.py "
        "--seeds` (each instant's 4 images mapped on their own, with each seed of "
        "augment and the mapper): the ratio of camera distances at today's scale "
        "as above, one per model; *within 5%*: models whose ratio is within "
        "0.95-1.05; uncertainty and *truth within* as above.",
    ]
    replace_section(
        DOCS / "results.md",
        "scale-instants",
        "### Metric scale per instant, over seeds\n\n" + "\n".join(lines),
    )
    print("\n".join(lines))


def cli() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument(
        "--instants",
        action="store_true",
        help="only pose2sim per instant (after bench/evidence.py --seeds)",
    )
    if parser.parse_args().instants:
        instants_section()
    else:
        main()


if __name__ == "__main__":
    cli()
