"""Real photos through the user's path: pose2sim_single and pose2sim_multi, per instant.

Exactly what a user runs, one instant (4 cameras) at a time, through the CLI entry
point (``colmap_vc.cli.main``):

1. a COLMAP database with the cameras' known intrinsics (SIFT, exhaustive matching);
2. ``colmap-vc priors IMAGES --output P --database DB``;
3. ``colmap-vc augment DB --priors P``;
4. ``colmap-vc map DB --image-path IMAGES --output-path SPARSE``;
5. ``colmap-vc eval`` against the marker-based calibration (pairs pooled over instants).

``--orders K`` repeats every instant with K image orders (the order COLMAP's feature
extraction wrote the images: ids permuted), the spread of AUC@15 is the stability.
``--seeds 0 1 ...`` maps every instant (camera order) again with each seed of
augment's RANSAC and of the mapper (``--seed`` of both commands): the run-to-run
noise of a result, and whether a seed ever leaves a wrong camera.

    .venv/bin/python bench/realdata.py [--datasets single multi] [--orders 3]
        [--seeds 0 1 2 3 4 5]

Writes bench/out/realdata.json and the "realdata" section of docs/results.md.
"""

from __future__ import annotations

import argparse
import json
import logging
import shutil
import time
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import pycolmap
from common import (
    DOCS,
    OUT,
    ROOT,
    WRONG_DEG,
    add_pose2sim_run_args,
    machine,
    replace_section,
    setup_logging,
    write_json,
    wrong_cameras,
)

from colmap_vc import cli, database
from colmap_vc.evaluation import (
    THRESHOLDS_DEG,
    Metrics,
    evaluate_poses,
    pose_auc,
    poses_by_name,
)
from colmap_vc.priors import read_priors
from colmap_vc.structs import PersonPrior
from colmap_vc.vc_records import person_identities

logger = logging.getLogger("bench.realdata")
SHARED = ROOT.parent / "shared" / "data"
LABELS = ROOT / "tests" / "data" / "pose2sim_people.json"
INSTANTS = ("t010", "t030", "t050", "t070", "t090")


def load_calibration(
    data: Path,
) -> tuple[dict[str, pycolmap.Camera], dict[str, np.ndarray]]:
    """pycolmap camera and GT cam_from_world (3, 4) per image name."""
    spec = json.loads((data / "cameras.json").read_text())
    cameras, poses = {}, {}
    for cam in spec["cameras"]:
        K = np.array(cam["K"])
        w, h = cam["image_size_wh"]
        params = [K[0, 0], K[1, 1], K[0, 2], K[1, 2], *cam["dist_k1k2p1p2"]]
        for rel in cam["images"].values():
            name = Path(rel).name
            cameras[name] = pycolmap.Camera(
                model="OPENCV", width=w, height=h, params=params
            )
            poses[name] = np.c_[np.array(cam["R"]), np.array(cam["t"])]
    return cameras, poses


def make_database(
    data: Path,
    images: list[str],
    cameras: Mapping[str, pycolmap.Camera | None],
    db: Path,
    match: bool = True,
) -> None:
    """SIFT + exhaustive matching with the known intrinsics, images in this order
    (an image whose camera is None: COLMAP's guess, as without calibration);
    ``match=False``: SIFT only, no classic matches."""
    db.parent.mkdir(parents=True, exist_ok=True)
    if db.exists():
        db.unlink()
    extraction = pycolmap.FeatureExtractionOptions(num_threads=2)
    extraction.sift.max_num_features = 8192
    for name in images:
        cam = cameras[name]
        reader = (
            pycolmap.ImageReaderOptions()
            if cam is None
            else pycolmap.ImageReaderOptions(
                camera_model="OPENCV",
                camera_params=",".join(f"{p:.17g}" for p in cam.params),
            )
        )
        pycolmap.extract_features(
            db,
            data / "images",
            image_names=[name],
            camera_mode=pycolmap.CameraMode.PER_IMAGE,
            reader_options=reader,
            extraction_options=extraction,
            device=pycolmap.Device.cpu,
        )
    if not match:
        return
    pycolmap.match_exhaustive(
        db,
        matching_options=pycolmap.FeatureMatchingOptions(num_threads=2),
        device=pycolmap.Device.cpu,
    )


def run_instant(
    data: Path,
    images: list[str],
    cameras: Mapping[str, pycolmap.Camera | None],
    gt: dict[str, np.ndarray],
    work: Path,
    priors_dir: Path,
    augment_args: tuple[str, ...] = (),
    priors_args: tuple[str, ...] = (),
    map_args: tuple[str, ...] = (),
) -> tuple[Metrics, dict]:
    """Database (images in the given order), priors (cached), augment, map, eval."""
    db = work / "database.db"
    make_database(data, images, cameras, db)
    if not (priors_dir / "priors.json").exists():
        code = cli.main(
            [
                "priors",
                str(data / "images"),
                "--output",
                str(priors_dir),
                "--database",
                str(db),
                "--no-progress",
                *priors_args,
            ]
        )
        if code != 0:
            raise RuntimeError(f"priors failed ({code}) for {images}")
    t0 = time.perf_counter()
    code = cli.main(
        [
            "augment",
            str(db),
            "--priors",
            str(priors_dir),
            "--no-show-progress",
            *list(augment_args),
        ]
    )
    if code != 0:
        raise RuntimeError(f"augment failed ({code}) for {images}")
    t_augment = time.perf_counter() - t0
    sparse = work / "sparse"
    shutil.rmtree(sparse, ignore_errors=True)  # the bench's own output
    t0 = time.perf_counter()
    code = cli.main(
        [
            "map",
            str(db),
            "--image-path",
            str(data / "images"),
            "--output-path",
            str(sparse),
            "--no-show-progress",
            *list(map_args),
        ]
    )
    t_map = time.perf_counter() - t0
    rec = _largest_model(sparse) if code == 0 else None
    pred = {} if rec is None else poses_by_name(rec)
    metrics = evaluate_poses(pred, {n: gt[n] for n in images})
    labels = json.loads(LABELS.read_text()).get(
        f"pose2sim_{data.name.split('_')[-1]}", {}
    )
    assoc = association_accuracy(priors_dir, db, labels)
    return metrics, {
        "augment_s": t_augment,
        "map_s": t_map,
        "map_exit": code,
        "association": assoc,
    }


def _box_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """IoU (N, M) of boxes (N, 4) and (M, 4), x0 y0 x1 y1."""
    lo = np.maximum(a[:, None, :2], b[None, :, :2])
    hi = np.minimum(a[:, None, 2:], b[None, :, 2:])
    inter = np.prod(np.clip(hi - lo, 0, None), axis=2)
    area = lambda x: np.prod(x[:, 2:] - x[:, :2], axis=1)  # noqa: E731
    return inter / (area(a)[:, None] + area(b)[None, :] - inter)


def person_labels(persons: Sequence[PersonPrior], labels: list[dict]) -> dict[int, str]:
    """The hand label of each of an image's prior persons that has one (by index):
    the label whose box overlaps the box of the person's valid 2D keypoints most
    (IoU >= 0.3, one person per label, greedy)."""
    boxes = []
    for p in persons:
        ok = p.keypoints_valid if p.keypoints_valid is not None else slice(None)
        xy = p.keypoints_xy[ok]
        boxes.append([*xy.min(axis=0), *xy.max(axis=0)])
    label_of: dict[int, str] = {}
    if boxes and labels:
        iou = _box_iou(np.array(boxes), np.array([lb["box"] for lb in labels], float))
        while iou.max() >= 0.3:
            k, j = np.unravel_index(np.argmax(iou), iou.shape)
            label_of[int(k)] = labels[j]["label"]
            iou[k, :] = -1.0
            iou[:, j] = -1.0
    return label_of


def association_accuracy(priors_dir: Path, db: Path, labels: dict) -> dict:
    """Links between people of different images against the hand labels.

    A prior person takes the label whose box overlaps the box of its valid 2D
    keypoints most (IoU >= 0.3, one person per label, greedy); its identity is the
    one `augment`'s association gave it. A true link: two people of different images
    with the same label; a predicted link: the same identity.
    """
    priors = read_priors(priors_dir)
    views = database.read_views(db)
    ids = dict(zip(views.image_names, views.image_ids.tolist(), strict=True))
    identity = person_identities(database.read_person_associations(db))
    people = []  # (image, label or None, identity or -1)
    for name, ip in sorted(priors.images.items()):
        label_of = person_labels(ip.persons, labels.get(name, []))
        for k in range(len(ip.persons)):
            people.append((name, label_of.get(k), identity.get((ids[name], k), -1)))
    true = pred = correct = 0
    for a in range(len(people)):
        for b in range(a + 1, len(people)):
            (n1, l1, i1), (n2, l2, i2) = people[a], people[b]
            if n1 == n2:
                continue
            t = l1 is not None and l1 == l2
            p = i1 >= 0 and i1 == i2
            true += t
            pred += p
            correct += t and p
    return {"true_links": true, "predicted_links": pred, "correct_links": correct}


def _largest_model(sparse: Path) -> pycolmap.Reconstruction | None:
    best = None
    for d in sorted(p for p in sparse.rglob("images.bin")):
        rec = pycolmap.Reconstruction(d.parent)
        if best is None or rec.num_reg_images() > best.num_reg_images():
            best = rec
    return best


def _per_instant(per_instant: dict[str, dict]) -> str:
    """AUC@15 of each instant, rounded, in instant order."""
    return " ".join(f"{v['auc']['15']:.0f}" for v in per_instant.values())


def _wrong(m: Metrics) -> list[str]:
    """The wrong cameras of one instant's model (:func:`common.wrong_cameras`)."""
    posed = {n for p in m.pairs if p.registered for n in (p.image_name1, p.image_name2)}
    return wrong_cameras(list(m.pairs), posed)


def pooled(ms: list[Metrics]) -> dict:
    errors = np.array([p.error_deg for m in ms for p in m.pairs])
    aucs = pose_auc(errors, THRESHOLDS_DEG)
    return {
        "auc": {f"{t:g}": 100 * a for t, a in zip(THRESHOLDS_DEG, aucs, strict=True)},
        "median_error_deg": float(np.median(errors)),
        "registered": sum(m.num_registered for m in ms),
        "images": sum(m.num_images for m in ms),
        "pairs": [round(p.error_deg, 2) for m in ms for p in m.pairs],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--datasets", nargs="+", default=["single", "multi"])
    parser.add_argument("--instants", nargs="+", default=list(INSTANTS))
    parser.add_argument(
        "--orders", type=int, default=1, help="image orders per instant (stability)"
    )
    parser.add_argument(
        "--seeds",
        nargs="+",
        type=int,
        default=[0],
        help="seeds of augment's RANSAC and the mapper; seed 0 makes the orders' "
        "table, each other seed maps every instant again in camera order",
    )
    parser.add_argument(
        "--fresh-priors", action="store_true", help="re-estimate cached priors"
    )
    parser.add_argument(
        "--augment-args", default="", help="extra `colmap-vc augment` arguments"
    )
    parser.add_argument(
        "--priors-args", default="", help="extra `colmap-vc priors` arguments"
    )
    add_pose2sim_run_args(
        parser, "realdata", "folder under bench/out (priors cache) and name of the JSON"
    )
    args = parser.parse_args()
    setup_logging()
    t_start = time.perf_counter()
    out = OUT / args.out
    results: dict[str, dict] = {}
    for ds in args.datasets:
        data = SHARED / f"pose2sim_{ds}"
        cameras, gt = load_calibration(data)
        cams = sorted({n.split("_")[0] for n in gt})
        per_order: dict[int, dict[str, Metrics]] = {}
        per_seed: dict[int, dict[str, Metrics]] = {}
        info: dict[str, dict] = {}
        for instant in args.instants:
            images = [f"{c}_{instant}.jpg" for c in cams]
            priors_dir = out / ds / instant / "priors"
            if args.fresh_priors and priors_dir.exists():
                shutil.rmtree(priors_dir)
            for k in range(args.orders):
                # Order 0: camera order; others: a fixed permutation per k.
                order = (
                    images
                    if k == 0
                    else [images[i] for i in np.random.default_rng(k).permutation(4)]
                )
                work = out / ds / instant / f"order{k}"
                m, t = run_instant(
                    data,
                    order,
                    cameras,
                    gt,
                    work,
                    priors_dir,
                    tuple(args.augment_args.split()),
                    tuple(args.priors_args.split()),
                    tuple(args.map_args.split()),
                )
                per_order.setdefault(k, {})[instant] = m
                info[f"{instant}/order{k}"] = {**t, "order": order}
                if k == 0:
                    per_seed.setdefault(0, {})[instant] = m
                logger.info(
                    "%s %s order %d: %d/4 registered, AUC@15 %.1f, median %.1f deg",
                    ds,
                    instant,
                    k,
                    m.num_registered,
                    m.auc["15"],
                    float(np.median([p.error_deg for p in m.pairs])),
                )
            for seed in (x for x in args.seeds if x != 0):  # 0: order 0 above
                seed_args = ("--seed", str(seed))
                m, t = run_instant(
                    data,
                    images,
                    cameras,
                    gt,
                    out / ds / instant / f"seed{seed}",
                    priors_dir,
                    (*args.augment_args.split(), *seed_args),
                    tuple(args.priors_args.split()),
                    (*args.map_args.split(), *seed_args),
                )
                per_seed.setdefault(seed, {})[instant] = m
                logger.info(
                    "%s %s seed %d: %d/4 registered, AUC@15 %.1f",
                    ds,
                    instant,
                    seed,
                    m.num_registered,
                    m.auc["15"],
                )
        assoc = {
            key: sum(r["association"][key] for r in info.values())
            for key in ("true_links", "predicted_links", "correct_links")
        }
        results[ds] = {
            "association": assoc,
            "pooled": {k: pooled(list(v.values())) for k, v in per_order.items()},
            "per_instant": {
                k: {i: pooled([m]) for i, m in v.items()} for k, v in per_order.items()
            },
            "runs": info,
            "seeds": {
                seed: {
                    "pooled": pooled(list(v.values())),
                    "per_instant": {i: pooled([m]) for i, m in v.items()},
                    "wrong_cameras": {i: _wrong(m) for i, m in v.items()},
                }
                for seed, v in per_seed.items()
            },
        }
    elapsed = time.perf_counter() - t_start
    write_json(
        f"{args.out}.json",
        {"machine": machine(), "results": results, "elapsed_s": elapsed},
    )
    lines = [
        "| data | image order | registered | AUC@15 | AUC@30 | AUC@45 "
        "| median pair error (deg) | per instant AUC@15 | association "
        "(correct / predicted / true links) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for ds, r in results.items():
        for k, p in r["pooled"].items():
            a = p["auc"]
            each = _per_instant(r["per_instant"][k])
            lines.append(
                f"| pose2sim_{ds} | {k} | {p['registered']}/{p['images']} "
                f"| {a['15']:.1f} | {a['30']:.1f} | {a['45']:.1f} "
                f"| {p['median_error_deg']:.1f} | {each} "
                f"| {r['association']['correct_links']} / "
                f"{r['association']['predicted_links']} / "
                f"{r['association']['true_links']} |"
            )
    extra = [x for x in args.seeds if x != 0]
    if extra:
        lines += [
            "",
            "| data | seed | registered | AUC@15 | per instant AUC@15 "
            "| wrong cameras |",
            "|---|---|---|---|---|---|",
        ]
        for ds, r in results.items():
            for seed, v in r["seeds"].items():
                p = v["pooled"]
                each = _per_instant(v["per_instant"])
                wrong = [n for names in v["wrong_cameras"].values() for n in names]
                lines.append(
                    f"| pose2sim_{ds} | {seed} | {p['registered']}/{p['images']} "
                    f"| {p['auc']['15']:.1f} | {each} | {', '.join(wrong) or 'none'} |"
                )
    seeds = f" --seeds {' '.join(map(str, args.seeds))}" if extra else ""
    lines += [
        "",
        f"Measured at commit {machine()['commit']} by `.venv/bin/python "
        f"bench/realdata.py --datasets {' '.join(args.datasets)} --orders "
        f"{args.orders}{seeds}"
        f"{f' --map-args={args.map_args}' if args.map_args else ''}` "
        f"({elapsed / 60:.0f} min; raw numbers and per-pair errors in "
        f"`bench/out/{args.out}.json`). Each instant is mapped on its own (4 images); "
        "pairs are pooled over the instants; an unregistered image's pairs count "
        "as 180 deg. Image order k > 0: the same images extracted in another order. "
        "Association: links between people of different images (same instant) "
        "against the hand labels of tests/data/pose2sim_people.json, summed over "
        "instants and orders."
        + (
            " Seeds: augment's RANSAC and the mapper (`--seed` of both), camera "
            "order; a wrong camera is registered with a median pair error above "
            f"{WRONG_DEG:.0f} deg."
            if seeds
            else ""
        ),
    ]
    print("\n".join(lines))
    if args.no_docs:
        return
    replace_section(
        DOCS / "results.md",
        "realdata",
        "## Real photos, the user's path (one instant at a time)\n\n"
        + "\n".join(lines),
    )


if __name__ == "__main__":
    main()
