"""How often a classic (SIFT) two-view geometry is right, by its number of inliers.

Every classic two-view geometry of the synthetic scenes the accuracy benchmark made
(bench/out/scenes/*): the relative pose from its inliers (COLMAP's calibrated
two-view estimation) against the ground truth, right within 15 degrees. This is the
evidence behind `augment`'s rule that classic matches join a pair's verification
only when they agree with the VCs (docs/results.md, "Several people").

    .venv/bin/python bench/classic_inliers.py   (after bench/accuracy.py)

Writes bench/out/classic_inliers.json and prints the table.
"""

from __future__ import annotations

import logging

import numpy as np
import pycolmap
from common import OUT, machine, setup_logging, write_json

from colmap_vc import database
from colmap_vc.evaluation import pose_disagreement_deg, poses_by_name, relative_pose

logger = logging.getLogger("bench.classic_inliers")
BINS = [(15, 25), (25, 50), (50, 100), (100, 10**9)]
RIGHT_DEG = 15.0


def main() -> None:
    setup_logging()
    options = pycolmap.TwoViewGeometryOptions(compute_relative_pose=True)
    rows = []
    for scene in sorted((OUT / "scenes").glob("acc_*")):
        db = scene / "database.db"
        if not db.exists() or not (scene / "gt" / "sparse").exists():
            continue
        gt = poses_by_name(pycolmap.Reconstruction(scene / "gt" / "sparse"))
        views = database.read_views(db)
        name = dict(zip(views.image_ids.tolist(), views.image_names, strict=True))
        camera = {
            int(i): views.cameras[int(c)]
            for i, c in zip(views.image_ids, views.camera_ids, strict=True)
        }
        keypoints = {int(i): database.read_keypoints(db, int(i)) for i in name}
        for (a, b), g in sorted(database.read_two_view_geometries(db).items()):
            inl = g.inlier_matches
            if len(inl) < 15:
                continue
            tvg = pycolmap.estimate_calibrated_two_view_geometry(
                camera[a],
                keypoints[a][inl[:, 0]].astype(np.float64),
                camera[b],
                keypoints[b][inl[:, 1]].astype(np.float64),
                np.repeat(np.arange(len(inl), dtype=np.uint32)[:, None], 2, axis=1),
                options,
            )
            err = (
                180.0
                if tvg.cam2_from_cam1 is None
                else pose_disagreement_deg(
                    tvg.cam2_from_cam1.matrix(),
                    relative_pose(gt[name[a]], gt[name[b]]),
                )
            )
            rows.append({"scene": scene.name, "inliers": len(inl), "error_deg": err})
    table = ["| classic inliers | right | wrong |", "|---|---|---|"]
    for lo, hi in BINS:
        sel = [r for r in rows if lo <= r["inliers"] < hi]
        right = sum(r["error_deg"] <= RIGHT_DEG for r in sel)
        label = f"{lo}-{hi}" if hi < 10**9 else f"{lo} and more"
        table.append(f"| {label} | {right} | {len(sel) - right} |")
    write_json("classic_inliers.json", {"machine": machine(), "pairs": rows})
    logger.info(
        "%d classic geometries in %d scenes",
        len(rows),
        len({r["scene"] for r in rows}),
    )
    print("\n".join(table))


if __name__ == "__main__":
    main()
