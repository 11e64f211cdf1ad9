"""Person detection on pose2sim_single and pose2sim_multi against hand labels.

Compares the multi-person BlazePose detector (colmap_vc.estimators.blazepose, the
estimator's path) with the former path: MediaPipe's legacy single-person ``Pose``
solution, the found person painted grey and the solution run again. A detection
matches a labelled person (tests/data/pose2sim_people.json) when its landmark box has
IoU >= 0.5 with the label's box or its hip centre lies in that box (one-to-one,
greedy by IoU). Recall is over labelled people, precision over detections.

    PYTHONPATH=$PWD python bench/detection.py
"""

from __future__ import annotations

import json
import time
import warnings
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from bench.common import DOCS, OUT, machine, replace_section
from colmap_vc.estimators import EstimatorOptions, body
from colmap_vc.estimators import mediapipe as mp_estimator
from colmap_vc.estimators.blazepose import box_iou, landmark_box

ROOT = Path(__file__).resolve().parents[1]
LABELS = ROOT / "tests" / "data" / "pose2sim_people.json"
DATA = ROOT.parent / "shared" / "data"
if not DATA.is_dir():
    DATA = Path("/work/shared/data")
MAIN = ("man", "woman")
HIPS = [body.BLAZEPOSE_NAMES.index(n) for n in ("left_hip", "right_hip")]


def legacy_detect(pose: Any, image_rgb: np.ndarray, max_people: int = 4) -> list:
    """The former path: legacy single-person Pose, found people painted grey."""
    h, w = image_rgb.shape[:2]
    work = image_rgb.copy()
    taken = np.zeros((h, w), dtype=bool)
    found: list[body.BodyLandmarks] = []
    for _ in range(max_people):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            result = pose.process(work)
        if result.pose_landmarks is None:
            break
        lm_img = result.pose_landmarks.landmark
        xy = np.array([(p.x, p.y) for p in lm_img]) * [w, h]
        vis = np.array([p.visibility for p in lm_img]).clip(0.0, 1.0)
        lm = body.BodyLandmarks(xy_img=xy, points_3d=np.zeros((33, 3)), visibility=vis)
        seg = (
            np.zeros((h, w), dtype=bool)
            if result.segmentation_mask is None
            else np.asarray(result.segmentation_mask) >= 0.5
        )
        px = np.floor(xy).astype(np.int64)
        on = (px[:, 0] >= 0) & (px[:, 1] >= 0) & (px[:, 0] < w) & (px[:, 1] < h)
        seen = on & (vis >= 0.5)
        if found and (not seen.any() or taken[px[seen, 1], px[seen, 0]].mean() > 0.5):
            break
        found.append(lm)
        region = seg.astype(np.uint8)
        pts = xy[np.isfinite(xy).all(axis=1)]
        if len(pts) >= 3:
            hull = cv2.convexHull((pts - 0.5).astype(np.float32))
            cv2.fillConvexPoly(region, np.round(hull).astype(np.int32), 1)
        ys, xs = np.nonzero(region)
        size = max(np.ptp(xs), np.ptp(ys)) if len(xs) else 0
        grow = 2 * int(0.05 * size) + 1
        taken |= cv2.dilate(region, np.ones((grow, grow), np.uint8)).astype(bool)
        work[taken] = 128
    return found


def match(dets: list[body.BodyLandmarks], labels: list[dict]) -> list[int | None]:
    """Label index -> matched detection index (or None), one-to-one, greedy by IoU."""
    if not dets or not labels:
        return [None] * len(labels)
    boxes = np.array([landmark_box(d, 0.5) for d in dets])
    lab = np.array([lb["box"] for lb in labels], dtype=np.float64)
    iou = box_iou(boxes, lab)
    hips = np.array([d.xy_img[HIPS].mean(axis=0) for d in dets])
    inside = (hips[:, None, :] >= lab[None, :, :2]) & (
        hips[:, None, :] <= lab[None, :, 2:]
    )
    ok = (iou >= 0.5) | inside.all(axis=2)
    score = np.where(ok, iou + 1e-3, -1.0)
    out: list[int | None] = [None] * len(labels)
    while score.max() >= 0:
        d, k = np.unravel_index(np.argmax(score), score.shape)
        out[k] = int(d)
        score[d, :] = -1.0
        score[:, k] = -1.0
    return out


def _has_mediapipe() -> bool:
    import importlib.util

    return importlib.util.find_spec("mediapipe") is not None


# The legacy row (MediaPipe's own repaint-and-rerun solution) needs
# `pip install --no-deps mediapipe==0.10.14`; colmap-vc itself no longer does.
METHODS = (("legacy",) if _has_mediapipe() else ()) + ("blazepose2", "blazepose3")


def run(method: str, dataset: str, labels: dict[str, list[dict]]) -> dict:
    levels = int(method[-1]) if method.startswith("blazepose") else 1
    options = EstimatorOptions(detector_levels=levels)
    if method == "legacy":
        import mediapipe as mp

        model = mp.solutions.pose.Pose(
            static_image_mode=True, model_complexity=1, enable_segmentation=True
        )

        def detect(img: np.ndarray) -> list[body.BodyLandmarks]:
            return legacy_detect(model, img)
    else:
        model = mp_estimator.open_pose(options)

        def detect(img: np.ndarray) -> list[body.BodyLandmarks]:
            found = mp_estimator.detect_people(model, img, options)
            return [d.landmarks for d in found]

    per_image = {}
    for name, people in labels.items():
        img = mp_estimator.read_image(DATA / dataset / "images" / name)
        assert img is not None, name
        start = time.perf_counter()
        dets = detect(img)
        seconds = time.perf_counter() - start
        m = match(dets, people)
        per_image[name] = {
            "detections": len(dets),
            "found": {lb["label"]: m[k] is not None for k, lb in enumerate(people)},
            "seconds": seconds,
        }
    model.close()
    found = [f for v in per_image.values() for f in v["found"].items()]
    matched = sum(ok for _, ok in found)
    ndet = sum(v["detections"] for v in per_image.values())
    main = [ok for lab, ok in found if lab in MAIN]
    return {
        "recall": matched / len(found),
        "recall_main": sum(main) / len(main),
        "precision": matched / ndet if ndet else float("nan"),
        "labelled": len(found),
        "detections": ndet,
        "seconds_per_image": float(np.mean([v["seconds"] for v in per_image.values()])),
        "per_image": per_image,
    }


def main() -> None:
    doc = json.loads(LABELS.read_text())
    results: dict[str, dict] = {}
    for dataset in ("pose2sim_single", "pose2sim_multi"):
        for method in METHODS:
            r = run(method, dataset, doc[dataset])
            results[f"{dataset}/{method}"] = r
            print(
                f"{dataset:16s} {method:10s} recall {r['recall']:.2f} (main "
                f"{r['recall_main']:.2f}) precision {r['precision']:.2f} "
                f"{r['seconds_per_image']:.2f} s/image"
            )
            for name, v in r["per_image"].items():
                miss = [lab for lab, ok in v["found"].items() if not ok]
                print(f"  {name}: {v['detections']} found, missed {miss or '-'}")
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "detection.json").write_text(
        json.dumps({"machine": machine(), "results": results}, indent=1)
    )
    names = {
        "legacy": "legacy Pose, repainted (former)",
        "blazepose2": "BlazePose multi-person, 2 passes (default)",
        "blazepose3": "BlazePose multi-person, 3 passes",
    }
    lines = [
        "Person detection against hand labels (tests/data/pose2sim_people.json; "
        "`PYTHONPATH=$PWD python bench/detection.py`). Main = the man and the woman; "
        "all = also the bystander (cam01, cam02). A detection matches when its "
        "landmark box has IoU >= 0.5 with the label or its hip centre is inside. "
        "Passes (`EstimatorOptions.detector_levels`): the whole image, squares of "
        "the shorter side, half-size squares. s/image: detection only (one CPU "
        "thread, a shared machine).",
        "",
        "| data | detector | recall main | recall all | precision | s/image |",
        "|---|---|---|---|---|---|",
    ]
    for key, r in results.items():
        dataset, method = key.split("/")
        lines.append(
            f"| {dataset} | {names[method]} | {r['recall_main']:.2f} | "
            f"{r['recall']:.2f} | {r['precision']:.2f} | {r['seconds_per_image']:.2f} |"
        )
    replace_section(DOCS / "results.md", "detection", "\n".join(lines))


if __name__ == "__main__":
    main()
