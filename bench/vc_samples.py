"""How many template samples per person: pair pose error and time against N.

Every person's VCs are the template's surface samples (MatchingOptions.num_samples,
one track each). Their errors have two parts: the predicted mesh's own error (its
orientation, shape and depth), shared by all samples of that person and view, and
each sample's independent error (dense-map and ray-casting noise). Only the second
averages out with more samples, so the pair pose error stops falling once the
shared part dominates; the cost (ray casting, verification, the mapper's points)
grows linearly with N.

This script measures both on the accuracy benchmark's domes (1 and 3 people, the
scenes of bench/accuracy.py) with clean priors (exact meshes and maps: the
geometry's own floor) and realistic ones: for each N, the median rotation error
of the verified pairs against ground truth, the share of pairs verified, and the
seconds of `compute_virtual_correspondences`.

    .venv/bin/python bench/vc_samples.py [--samples 250 500 1000 2000] [--seeds 0 1]

Writes bench/out/vc_samples.json and the section `vc_samples` of docs/benchmark.md.
"""

from __future__ import annotations

import argparse
import itertools
import logging
import time

import numpy as np
import pycolmap
from accuracy import scene
from common import DOCS, machine, replace_section, setup_logging, write_json

from colmap_vc import database
from colmap_vc.augment import AugmentOptions, compute_virtual_correspondences
from colmap_vc.evaluation import relative_pose, rotation_angle_deg
from colmap_vc.executor import ExecutorKind
from colmap_vc.matching import MatchingOptions
from colmap_vc.priors import read_priors

logger = logging.getLogger("bench.vc_samples")

LEVELS = {"clean": "priors_clean", "realistic": "priors"}


def one(path, folder: str, num_samples: int) -> dict:
    """Rotation errors of the verified pairs of one scene, and the seconds."""
    db = path / "database.db"
    views = database.read_views(db)
    priors = read_priors(path / folder, known_image_names=views.image_names)
    t0 = time.perf_counter()
    vcs = compute_virtual_correspondences(
        views,
        priors,
        AugmentOptions(
            show_progress=False,
            executor=ExecutorKind.SERIAL,
            matching=MatchingOptions(num_samples=num_samples),
        ),
    )
    seconds = time.perf_counter() - t0
    rec = pycolmap.Reconstruction(path / "gt" / "sparse")
    gt = {im.name: im.cam_from_world().matrix() for im in rec.images.values()}
    id_of = dict(zip(views.image_names, views.image_ids.tolist(), strict=True))
    errors, pairs = [], 0
    for n1, n2 in itertools.combinations(sorted(views.image_names, key=id_of.get), 2):
        pairs += 1
        geom = vcs.geometries.get((id_of[n1], id_of[n2]))
        if geom is None:
            continue
        rel = relative_pose(gt[n1], gt[n2])
        errors.append(rotation_angle_deg(geom.cam2_from_cam1[:, :3] @ rel[:, :3].T))
    return {"errors_deg": errors, "pairs": pairs, "seconds": seconds}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument(
        "--samples", type=int, nargs="+", default=[250, 500, 1000, 2000]
    )
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--people", type=int, nargs="+", default=[1, 3])
    args = parser.parse_args()
    setup_logging()
    rows = []
    for people, level, n in itertools.product(args.people, LEVELS, args.samples):
        errors: list[float] = []
        pairs, seconds = 0, 0.0
        for seed in args.seeds:
            r = one(scene("dome", people, seed), LEVELS[level], n)
            errors += r["errors_deg"]
            pairs += r["pairs"]
            seconds += r["seconds"]
        e = np.asarray(errors)
        rows.append(
            {
                "people": people,
                "priors": level,
                "num_samples": n,
                "verified": len(e),
                "pairs": pairs,
                "median_deg": float(np.median(e)) if len(e) else None,
                "p80_deg": float(np.percentile(e, 80)) if len(e) else None,
                "seconds": seconds,
            }
        )
        logger.info("%s", rows[-1])
    write_json("vc_samples", {"machine": machine(), "seeds": args.seeds, "rows": rows})
    lines = [
        "| people | priors | samples | verified pairs | median rotation error "
        "(deg) | 80% (deg) | VC seconds |",
        "|---|---|---|---|---|---|---|",
    ]
    lines += [
        f"| {r['people']} | {r['priors']} | {r['num_samples']} "
        f"| {r['verified']}/{r['pairs']} | {r['median_deg']:.2f} "
        f"| {r['p80_deg']:.2f} | {r['seconds']:.1f} |"
        for r in rows
        if r["median_deg"] is not None
    ]
    lines += [
        "",
        f"Measured at commit {machine()['commit']} by `.venv/bin/python "
        f"bench/vc_samples.py --samples {' '.join(map(str, args.samples))} --seeds "
        f"{' '.join(map(str, args.seeds))}` (the accuracy benchmark's domes; VC "
        "seconds: `compute_virtual_correspondences` in one process, both seeds).",
    ]
    replace_section(
        DOCS / "benchmark.md",
        "vc_samples",
        "## Template samples per person (pose error against N)\n\n" + "\n".join(lines),
    )
    print("\n".join(lines))


if __name__ == "__main__":
    main()
