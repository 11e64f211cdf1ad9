"""VC geometry on `dome` scenes: verified pairs, rotation errors, inlier ratios.

For every image pair that sees a person in both images: does `augment` give it a
verified two-view geometry, and how far is its relative rotation from ground truth,
next to the mesh-alignment baseline (Procrustes between the two predicted meshes)?
With the same VCs: inlier ratio after verification and the epipolar error of the VCs
under the ground-truth poses. Priors: `clean` (gt/priors, with the true ids),
`realistic` (priors/: anonymous, as a user's; the VCs pair people through
`augment`'s association, and the mesh alignment pairs them by the identities it
gave) and `realistic_ids` (the same priors with the true ids: the geometry without
the association's errors).

    .venv/bin/python bench/vc_geometry.py [--seeds 0 1 2] [--people 1 3]

Writes bench/out/vc_geometry.json and a table in docs/benchmark.md.
"""

from __future__ import annotations

import argparse
import itertools
import logging
from pathlib import Path

import numpy as np
import pycolmap
from common import (
    DOCS,
    OUT,
    machine,
    replace_section,
    scene_is_current,
    setup_logging,
    write_json,
)

from colmap_vc import database
from colmap_vc.augment import AugmentOptions, compute_virtual_correspondences
from colmap_vc.baselines import mesh_alignment
from colmap_vc.evaluation import relative_pose, rotation_angle_deg, vector_angle_deg
from colmap_vc.mapping import apply_associations
from colmap_vc.priors import read_priors
from colmap_vc.synthetic import SynthOptions, generate
from colmap_vc.synthetic.gt import add_true_ids
from colmap_vc.verification import epipolar_errors_px

logger = logging.getLogger("bench.vc_geometry")


def scene_dir(people: int, seed: int) -> Path:
    path = OUT / "scenes" / f"dome_p{people}_s{seed}"
    if not ((path / "database.db").exists() and scene_is_current(path)):
        generate(
            "dome", path, SynthOptions(seed=seed, num_people=people, overwrite=True)
        )
    return path


PRIORS = {"clean": "gt/priors", "realistic": "priors", "realistic_ids": "priors_ids"}


def priors_folder(scene: Path, level: str) -> Path:
    """The scene's priors folder of ``level`` (the true ids added to the
    realistic priors on first use)."""
    path = scene / PRIORS[level]
    if level == "realistic_ids" and not path.exists():
        add_true_ids(scene, "priors", "priors_ids")
    return path


def evaluate(scene: Path, priors_dir: Path) -> dict:
    db = scene / "database.db"
    views = database.read_views(db)
    priors = read_priors(priors_dir, known_image_names=views.image_names)
    classic_kp = {int(i): database.read_keypoints(db, int(i)) for i in views.image_ids}
    vcs = compute_virtual_correspondences(
        views,
        priors,
        AugmentOptions(show_progress=False),
        classic_kp,
        database.read_matches(db),
    )
    rec = pycolmap.Reconstruction(scene / "gt" / "sparse")
    gt = {im.name: im.cam_from_world().matrix() for im in rec.images.values()}
    id_of = dict(zip(views.image_names, views.image_ids.tolist(), strict=True))
    # the baseline pairs people by identity: anonymous ones by the association's
    priors = apply_associations(priors, vcs.associations, id_of)
    name_of = {v: k for k, v in id_of.items()}
    cam_of = {
        int(i): views.cameras[int(c)]
        for i, c in zip(views.image_ids, views.camera_ids, strict=True)
    }
    seen = {
        n: set(
            np.unique(
                np.load(scene / "gt" / "surface" / (Path(n).stem + ".npz"))["person_id"]
            ).tolist()
        )
        for n in views.image_names
    }
    rows = []
    for n1, n2 in itertools.combinations(sorted(views.image_names, key=id_of.get), 2):
        if not seen[n1] & seen[n2]:
            continue
        rel = relative_pose(gt[n1], gt[n2])
        geom = vcs.geometries.get((id_of[n1], id_of[n2]))
        mesh = mesh_alignment(priors.images[n1], priors.images[n2])
        rows.append(
            {
                "pair": [n1, n2],
                "gt_angle_deg": rotation_angle_deg(rel[:, :3]),
                "verified": geom is not None,
                "vc_rot_deg": None
                if geom is None
                else rotation_angle_deg(geom.cam2_from_cam1[:, :3] @ rel[:, :3].T),
                "vc_trans_deg": None
                if geom is None
                else vector_angle_deg(geom.cam2_from_cam1[:, 3], rel[:, 3]),
                "mesh_rot_deg": None
                if mesh is None
                else rotation_angle_deg(mesh[:, :3] @ rel[:, :3].T),
                "mesh_trans_deg": None
                if mesh is None
                else vector_angle_deg(mesh[:, 3], rel[:, 3]),
            }
        )
    kp = {k.image_id: k for k in vcs.keypoints}
    epi_in, epi_all, n_vc, n_in = [], [], 0, 0
    for pair in vcs.pairs:
        rel = relative_pose(gt[name_of[pair.image_id1]], gt[name_of[pair.image_id2]])
        err = epipolar_errors_px(
            cam_of[pair.image_id1],
            cam_of[pair.image_id2],
            rel,
            kp[pair.image_id1].xy_img[pair.idx1],
            kp[pair.image_id2].xy_img[pair.idx2],
        )
        epi_all.append(err)
        epi_in.append(err[pair.is_inlier])
        n_vc += len(pair)
        n_in += int(pair.is_inlier.sum())
    return {
        "pairs": rows,
        "num_vcs": n_vc,
        "num_inliers": n_in,
        "epipolar_all_px": np.concatenate(epi_all).tolist() if epi_all else [],
        "epipolar_inlier_px": np.concatenate(epi_in).tolist() if epi_in else [],
    }


def stats(values: list[float]) -> tuple[float, float]:
    v = np.asarray([x for x in values if x is not None], dtype=float)
    return (
        (float(np.median(v)), float(np.percentile(v, 80)))
        if len(v)
        else (float("nan"), float("nan"))
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--people", type=int, nargs="+", default=[1, 3])
    args = parser.parse_args()
    setup_logging()
    results = {}
    for people, level in itertools.product(args.people, PRIORS):
        merged = {
            "pairs": [],
            "num_vcs": 0,
            "num_inliers": 0,
            "epipolar_all_px": [],
            "epipolar_inlier_px": [],
        }
        for seed in args.seeds:
            scene = scene_dir(people, seed)
            r = evaluate(scene, priors_folder(scene, level))
            for k in merged:
                merged[k] = merged[k] + r[k]
            logger.info(
                "dome p%d s%d %s: %d/%d pairs verified",
                people,
                seed,
                level,
                sum(p["verified"] for p in r["pairs"]),
                len(r["pairs"]),
            )
        results[f"p{people}_{level}"] = merged
    lines = [
        "| people | priors | pairs verified | VC rot. err. median / p80 (deg) | "
        "mesh alignment rot. err. median / p80 (deg) | "
        "VC transl. dir. err. median (deg) | inlier ratio | "
        "epipolar err. of inliers under GT, median (px) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    summary = {}
    for key, r in results.items():
        people, level = key.split("_", 1)
        pairs = r["pairs"]
        ver = sum(p["verified"] for p in pairs)
        vc = stats([p["vc_rot_deg"] for p in pairs])
        mesh = stats([p["mesh_rot_deg"] for p in pairs])
        vt = stats([p["vc_trans_deg"] for p in pairs])
        ratio = r["num_inliers"] / max(r["num_vcs"], 1)
        epi = (
            float(np.median(r["epipolar_inlier_px"]))
            if r["epipolar_inlier_px"]
            else float("nan")
        )
        summary[key] = {
            "verified": ver,
            "pairs": len(pairs),
            "vc_rot_median": vc[0],
            "vc_rot_p80": vc[1],
            "mesh_rot_median": mesh[0],
            "mesh_rot_p80": mesh[1],
            "inlier_ratio": ratio,
            "epipolar_inlier_median_px": epi,
        }
        lines.append(
            f"| {people[1:]} | {level} | {ver}/{len(pairs)} | "
            f"{vc[0]:.2f} / {vc[1]:.2f} | "
            f"{mesh[0]:.2f} / {mesh[1]:.2f} | {vt[0]:.2f} | {ratio:.2f} | {epi:.3f} |"
        )
    lines.append(
        f"\nDome scenes (8-16 views), seeds {' '.join(map(str, args.seeds))}, "
        "all pairs that see a "
        f"shared person. Measured at commit {machine()['commit']} by "
        "`.venv/bin/python bench/vc_geometry.py "
        f"--seeds {' '.join(map(str, args.seeds))} "
        f"--people {' '.join(map(str, args.people))}`; "
        "raw numbers in `bench/out/vc_geometry.json`."
    )
    write_json(
        "vc_geometry.json",
        {"machine": machine(), "summary": summary, "results": results},
    )
    replace_section(DOCS / "benchmark.md", "vc-geometry", "\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
