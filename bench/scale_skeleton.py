"""The metric scale from the people's skeleton (today) or their distance (before).

`map` scales a model by how much larger each person's keypoints are in its prior
than in the model (colmap_vc/metric_scale.py, ``skeleton_ratio``). Until this
bench it took how far the prior puts them from the camera instead. A fit from
the image reads a body's size from its proportions and places it by
reprojection, so its distance carries the fit's size and whatever the placement
adds (a limb turned out of the image plane projects shorter, and the refit
brings the body nearer); the skeleton's size does not depend on where the fit
put it. This bench compares, on the same models, the scale read three ways per
(image, person), combined over views as `map` does (Hodges-Lehmann):

- *distance*: the prior's keypoints' distance from the camera over the model's,
  the median over the keypoints (`map`'s scale before);
- *skeleton*: `map`'s today, the weighted median over pairs of keypoints of the
  prior's distance between the two over the model's, each pair weighted by its
  squared length in the prior;
- *radius*: the root-mean-square distance of the keypoints from their centroid
  in the prior over the model's (no median: one stray keypoint moves it).

The models are those `bench/metric_scale.py` reads (the accuracy bench's default
`map`, `bench/gba_seeds.py`'s twelve domes per level, pose2sim per instant from
`bench/evidence.py --seeds`, the static cameras), each compared with the truth
at each way's scale (1 = metres exactly; the scale is `map`'s last step, so the
model is the same at any). On pose2sim the models' poses are also replaced by the
calibration's, which reads each person's fit against the calibrated triangulation
of its own keypoints (the man, the same in both captures, and pose2sim_multi's
avatar: the person more than 0.5 m from where pose2sim_single's man stands at
that instant).

    .venv/bin/python bench/scale_skeleton.py   # after bench/metric_scale.py's runs

Writes bench/out/scale_skeleton.json and the "scale-skeleton" section of
docs/results.md.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pycolmap
from common import DOCS, OUT, machine, replace_section, scene_is_current, write_json
from evidence import ARMS
from metric_scale import SHARED, _largest, load_calibration
from static_ceiling import posed_copy

from colmap_vc.evaluation import camera_distance_ratio, poses_by_name
from colmap_vc.mapping import MappingOptions
from colmap_vc.mapping.inputs import read_inputs
from colmap_vc.metric_scale import hodges_lehmann, person_keypoints, skeleton_ratio

logger = logging.getLogger(__name__)

WAYS = ("distance", "skeleton", "radius")
AVATAR_M = 0.5
MAP_ARM = f"arm{list(ARMS).index('keypoints + surface + up (`map`)')}"
"""`bench/evidence.py --seeds`'s folder of the default `map`'s models."""


def person_scales(
    database_path: Path, rec: pycolmap.Reconstruction
) -> tuple[dict[str, dict[tuple[int, int], float]], dict[int, np.ndarray]]:
    """Per way, the scale each (image id, identity) gives (metres per model unit),
    and each identity's centroid of triangulated keypoints (model frame), on the
    keypoints `map`'s scale uses (``person_keypoints``)."""
    inputs = read_inputs(database_path, MappingOptions(), None)
    assert inputs.priors is not None
    found = person_keypoints(inputs.records, rec, inputs.priors)
    out: dict[str, dict[tuple[int, int], float]] = {w: {} for w in WAYS}
    centre: dict[int, np.ndarray] = {}
    if found is None:
        return out, centre
    for (image_id, ident), (obs, P, _) in found.views.items():  # loop over views
        M = found.points[found.tracks.track[obs]]
        centre[ident] = M.mean(axis=0)
        T = rec.image(image_id).cam_from_world().matrix()
        d_model = np.linalg.norm(M @ T[:, :3].T + T[:, 3], axis=1)
        out["distance"][(image_id, ident)] = float(
            np.median(np.linalg.norm(P, axis=1) / d_model)
        )
        if len(P) >= 2:
            out["skeleton"][(image_id, ident)] = skeleton_ratio(P, M)
            out["radius"][(image_id, ident)] = radius(P) / radius(M)
    return out, centre


def radius(Y: np.ndarray) -> float:
    """Root-mean-square distance of points from their centroid."""
    return float(np.sqrt(np.mean(np.sum((Y - Y.mean(axis=0)) ** 2, axis=1))))


def combined(values: dict[tuple[int, int], float]) -> float:
    return hodges_lehmann(np.array(list(values.values()))) if values else np.nan


def models() -> Iterator[tuple[str, str, pycolmap.Reconstruction, Path, float]]:
    """(row, model name, model, database, ratio of camera distances to the
    truth) for every model `bench/metric_scale.py` reads, `realistic` and
    `fitted` priors only."""
    for run in sorted((OUT / "runs" / "accuracy").glob("acc_*")):
        gt = poses_by_name(
            pycolmap.Reconstruction(OUT / "scenes" / run.name / "gt" / "sparse")
        )
        kind = "dome" if "_dome_" in run.name else run.name.split("_")[1]
        people = run.name.split("_")[2][1:]
        for level in sorted(p for p in run.iterdir() if p.is_dir()):
            found = _largest(level / "VC_p_keypoint_BA" / "sparse")
            db = level / "VC_p_keypoint_BA" / "database.db"
            if (
                found is None
                or not db.exists()
                or level.name.split("_")[0]
                not in (
                    "realistic",
                    "fitted",
                )
            ):
                continue
            ratio = camera_distance_ratio(poses_by_name(found[0]), gt)
            row = f"accuracy bench, {kind}, {people} p., `{level.name}`"
            yield row, run.name, found[0], db, ratio
    for run in sorted((OUT / "runs" / "gba_seeds").glob("seeds_dome_p*_s*_*")):
        scene = OUT / "scenes" / run.name
        found = _largest(run / "default" / "sparse")
        _, people, _, level = run.name.split("_")[1:]
        if found is None or level == "hard" or not scene_is_current(scene):
            continue
        gt = poses_by_name(pycolmap.Reconstruction(scene / "gt" / "sparse"))
        ratio = camera_distance_ratio(poses_by_name(found[0]), gt)
        row = f"twelve domes, {people[1:]} p., `{level}`"
        yield row, run.name, found[0], run / "default" / "database.db", ratio
    for ds in ("single", "multi"):
        _, gt = load_calibration(SHARED / f"pose2sim_{ds}")
        for d in sorted((OUT / "evidence_seeds" / ds / MAP_ARM).glob("seed*/t*")):
            found = _largest(d)
            where = "order0" if d.parent.name == "seed0" else d.parent.name
            db = OUT / "realdata" / ds / d.name / where / "database.db"
            if found is None or not db.exists():
                continue
            now = {n: g for n, g in gt.items() if d.name in n}
            ratio = camera_distance_ratio(poses_by_name(found[0]), now)
            name = f"{d.parent.name}/{d.name}"
            yield f"pose2sim_{ds}, per instant", name, found[0], db, ratio
        where = OUT / "static_cameras" / ds
        for sparse in sorted(where.glob("sparse*/0")):
            rec = pycolmap.Reconstruction(sparse)
            ratio = camera_distance_ratio(poses_by_name(rec), gt)
            row = f"pose2sim_{ds}, static cameras, {sparse.parent.name}"
            yield row, sparse.parent.name, rec, where / "database.db", ratio


def per_person_calibrated() -> dict[str, dict[str, list[float]]]:
    """pose2sim's seed-0 per-instant models with the calibration's poses: per
    person (the man, the avatar) and way, the scale of each (image, person)."""
    out: dict[str, dict[str, list[float]]] = {}
    man_at: dict[str, np.ndarray] = {}
    for ds in ("single", "multi"):
        _, gt = load_calibration(SHARED / f"pose2sim_{ds}")
        for d in sorted((OUT / "evidence_seeds" / ds / MAP_ARM / "seed0").glob("t*")):
            found = _largest(d)
            db = OUT / "realdata" / ds / d.name / "order0" / "database.db"
            if found is None or not db.exists():
                continue
            scales, centre = person_scales(
                db, posed_copy(found[0], set(found[0].reg_image_ids()), gt)
            )
            for ident, c in centre.items():  # loop over a few people
                if ds == "single":
                    man_at[d.name] = c
                    who = "pose2sim_single, the man"
                elif d.name not in man_at:
                    continue
                else:
                    far = np.linalg.norm(c - man_at[d.name]) > AVATAR_M
                    who = f"pose2sim_multi, {'the avatar' if far else 'the man'}"
                for way in WAYS:
                    values = [v for (_, i), v in scales[way].items() if i == ident]
                    out.setdefault(who, {}).setdefault(way, []).extend(values)
    return out


def main() -> None:
    rows: dict[str, list[dict]] = {}
    for row, name, rec, db, ratio in models():  # loop over models
        scales, _ = person_scales(db, rec)
        item = {"model": name, "ratio": ratio}
        for way in WAYS:  # the ratio the model would have at that way's scale
            item[way] = ratio * combined(scales[way])
        rows.setdefault(row, []).append(item)
        logger.info("%s %s: %s", row, name, item)
    people = per_person_calibrated()
    write_json(
        "scale_skeleton.json",
        {"machine": machine(), "models": rows, "calibrated_per_person": people},
    )
    lines = [
        "| models | n | median ratio: distance (before) / skeleton (today) / radius "
        "| within 5% | rms of log ratio |",
        "|---|---|---|---|---|",
    ]
    for row, items in rows.items():
        r = np.log(np.array([[it[w] for w in WAYS] for it in items]))
        ok = np.isfinite(r).all(axis=1)
        r = r[ok]
        median = " / ".join(f"{x:.3f}" for x in np.exp(np.median(r, axis=0)))
        within = " / ".join(str(int(x)) for x in (np.abs(r) <= np.log(1.05)).sum(0))
        rms = " / ".join(f"{x:.3f}" for x in np.sqrt(np.mean(r**2, axis=0)))
        lines.append(f"| {row} | {len(r)} | {median} | {within} | {rms} |")
    lines += [
        "",
        "| pose2sim, calibrated poses | views | median: distance / skeleton / radius "
        "| range of distance | range of skeleton |",
        "|---|---|---|---|---|",
    ]
    for who, by_way in people.items():
        v = {w: np.array(by_way[w]) for w in WAYS}
        lines.append(
            f"| {who} | {len(v['distance'])} | "
            + " / ".join(f"{np.median(v[w]):.3f}" for w in WAYS)
            + f" | {v['distance'].min():.2f}-{v['distance'].max():.2f} "
            f"| {v['skeleton'].min():.2f}-{v['skeleton'].max():.2f} |"
        )
    lines += [
        "",
        f"Measured at commit {machine()['commit']} by `.venv/bin/python "
        "bench/scale_skeleton.py` on the models `bench/metric_scale.py` reads "
        "(`realistic` and `fitted` priors): per model the ratio of camera "
        "distances to the truth after scaling it by each way, combined over "
        "(image, person) views as `map` does; *within 5%*: models whose ratio is "
        "within 5% of 1. *distance*: the prior's distance from the camera over "
        "the model's (`map`'s scale before); *skeleton*: `map`'s scale, the "
        "weighted median over pairs of keypoints of their distance in the prior "
        "over the model's; *radius*: their root-mean-square distance from their "
        "centroid, prior over model. "
        "*Calibrated poses*: seed 0's per-instant models with the calibration's "
        "poses, each (image, person) against its own calibrated triangulation "
        "(1: the fit has the person's size).",
    ]
    replace_section(
        DOCS / "results.md",
        "scale-skeleton",
        "### The scale from the skeleton's size instead of its distance\n\n"
        + "\n".join(lines),
    )
    print("\n".join(lines))


if __name__ == "__main__":
    logging.basicConfig(level=logging.WARNING)
    main()
