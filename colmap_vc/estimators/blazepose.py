"""Multi-person BlazePose from the models inside MediaPipe 0.10.14's wheel.

MediaPipe's legacy ``Pose`` solution runs the person detector
(``pose_detection.tflite``) but keeps only its best box. This module runs the same two
models by hand, with ``ai-edge-litert``'s TFLite interpreter on the CPU, and keeps every
person, following MediaPipe's graphs:

- ``pose_detection_cpu``: the whole image letterboxed into 224 x 224 (values in
  [-1, 1]), 2254 SSD anchors (strides 8, 16, 32, 32, 32; two anchors per cell and
  layer), sigmoid scores, boxes and four keypoints decoded against the anchors, weighted
  non-max suppression at IoU 0.3.
- ``pose_detection_to_roi``: a square ROI centred on keypoint 0 (hip centre), of side
  2.5 x its distance to keypoint 1 (full-body scale point), rotated so that this vector
  points up.
- ``pose_landmark_by_roi_cpu``: the ROI cropped to 256 x 256 (values in [0, 1]), 39
  landmarks x (x, y, z, visibility, presence) refined on the 64 x 64 heatmap (7 x 7
  window), 39 world landmarks rotated by the ROI's rotation, a 256 x 256 segmentation
  logit map warped back into the image, and the pose-presence flag.

Pixels follow COLMAP's convention (the centre of the top-left pixel is (0.5, 0.5));
OpenCV's warps index pixel centres at integers, hence the 0.5 shifts.
"""

from __future__ import annotations

import functools
import logging
from dataclasses import dataclass
from importlib.resources import files
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from colmap_vc.estimators import body
from colmap_vc.structs import BoolArray, FloatArray

logger = logging.getLogger(__name__)

DETECTOR_SIZE = 224
LANDMARK_SIZE = 256
NUM_MODEL_LANDMARKS = 39  # 33 BlazePose landmarks + 6 auxiliary ones
NMS_IOU = 0.3
ROI_SCALE = 1.25  # pose_detection_to_roi: rect scaled by 1.25, square on its long side
HEATMAP_KERNEL = 7
HEATMAP_MIN_CONFIDENCE = 0.5
# find_people: a crop whose landmarks share this fraction with a person already found
# is that person again; sharing MAYBE_SAME, it counts only with a confident detection
# (a person partly behind another, not a crop mixing the two).
SAME_PERSON = 0.5
MAYBE_SAME = 1.0 / 3.0
SURE_SCORE = 0.8


@dataclass(frozen=True, kw_only=True, slots=True)
class PersonBox:
    """One decoded person detection, in image pixels (COLMAP convention)."""

    score: float
    box: FloatArray  # (4,) x0, y0, x1, y1
    keypoints: (
        FloatArray  # (4, 2): hip centre, body scale, shoulder centre, upper scale
    )


@dataclass(frozen=True, kw_only=True, slots=True)
class Roi:
    """A rotated square crop: centre (pixels), side (pixels), rotation (radians)."""

    center: FloatArray  # (2,)
    side: float
    rotation: float


@dataclass(frozen=True, kw_only=True, slots=True)
class PoseResult:
    """One person's landmarks, world landmarks and segmentation logits."""

    landmarks: body.BodyLandmarks
    presence: float  # sigmoid of the pose-presence flag
    segmentation_logits: npt.NDArray[np.float32]  # (H, W) image pixels; -inf off ROI
    roi: Roi
    detection: PersonBox


def models_dir() -> Path:
    """MediaPipe 0.10.14's two BlazePose models, as shipped inside colmap-vc.

    They are copied byte for byte from the ``mediapipe==0.10.14`` wheel
    (``mediapipe/modules/{pose_detection,pose_landmark}``; Apache-2.0, see
    ``models/LICENSE``): MediaPipe itself is not needed to run them, and its wheel
    would pull a second, non-headless OpenCV, jax and sounddevice into the install.
    """
    return Path(str(files("colmap_vc.estimators") / "models"))


def _interpreter(path: Path) -> Any:
    try:
        from ai_edge_litert.interpreter import Interpreter
    except ImportError as exc:
        raise ImportError(
            "the MediaPipe estimator runs MediaPipe's .tflite models with "
            "ai-edge-litert: pip install ai-edge-litert (extra `mediapipe`)"
        ) from exc
    if not path.is_file():
        raise FileNotFoundError(f"MediaPipe model {path} is missing (need 0.10.14)")
    interp = Interpreter(model_path=str(path), num_threads=1)
    interp.allocate_tensors()
    return interp


@functools.cache
def ssd_anchors() -> FloatArray:
    """The detector's 2254 anchor centres (x, y), normalised to the 224 x 224 input.

    MediaPipe's SsdAnchorsCalculator with fixed anchor size: layers of equal stride
    share a grid, each layer adds two anchors per cell (aspect 1 and the interpolated
    scale); cells in row-major order, anchors innermost.
    """
    strides = [8, 16, 32, 32, 32]
    out = []
    i = 0
    while i < len(strides):
        j = i
        while j < len(strides) and strides[j] == strides[i]:
            j += 1
        per_cell = 2 * (j - i)
        n = int(np.ceil(DETECTOR_SIZE / strides[i]))
        yy, xx = np.meshgrid((np.arange(n) + 0.5) / n, (np.arange(n) + 0.5) / n)
        cells = np.stack([xx.T.ravel(), yy.T.ravel()], axis=1)  # row-major (y, x)
        out.append(np.repeat(cells, per_cell, axis=0))
        i = j
    return np.concatenate(out)


def _crop_matrix(roi: Roi, size: int) -> FloatArray:
    """2x3 affine map from a (size x size) tensor's pixel indices to OpenCV pixels."""
    c, s = np.cos(roi.rotation), np.sin(roi.rotation)
    rot = np.array([[c, -s], [s, c]]) * (roi.side / size)
    offset = rot @ np.full(2, 0.5 - size / 2.0) + roi.center - 0.5
    return np.hstack([rot, offset[:, None]])


def _crop(image_rgb: np.ndarray, roi: Roi, size: int) -> np.ndarray:
    """The ROI resampled to size x size (bilinear, zero outside the image), float32."""
    return cv2.warpAffine(
        image_rgb,
        _crop_matrix(roi, size),
        (size, size),
        flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=(0, 0, 0),
    ).astype(np.float32)


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-np.clip(x, -80.0, 80.0)))


def decode_detections(
    raw_boxes: FloatArray, raw_scores: FloatArray, min_score: float
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Raw detector outputs -> scores (N,), boxes (N, 4) x0y0x1y1, keypoints (N, 4, 2).

    Coordinates are normalised to the detector input ([0, 1] across it); only anchors
    scoring at least ``min_score`` are returned.
    """
    anchors = ssd_anchors()
    scores = _sigmoid(raw_scores.reshape(-1))
    keep = scores >= min_score
    raw = raw_boxes.reshape(-1, 12)[keep] / DETECTOR_SIZE
    a = anchors[keep]
    centre = raw[:, :2] + a
    half = raw[:, 2:4] / 2.0
    boxes = np.hstack([centre - half, centre + half])
    keypoints = raw[:, 4:].reshape(-1, 4, 2) + a[:, None, :]
    return scores[keep], boxes, keypoints


def box_iou(a: FloatArray, b: FloatArray) -> FloatArray:
    """IoU of every box in a (N, 4) with every box in b (M, 4) -> (N, M)."""
    lo = np.maximum(a[:, None, :2], b[None, :, :2])
    hi = np.minimum(a[:, None, 2:], b[None, :, 2:])
    inter = np.prod(np.clip(hi - lo, 0.0, None), axis=2)
    area_a = np.prod(np.clip(a[:, 2:] - a[:, :2], 0.0, None), axis=1)
    area_b = np.prod(np.clip(b[:, 2:] - b[:, :2], 0.0, None), axis=1)
    union = area_a[:, None] + area_b[None, :] - inter
    return np.where(union > 0, inter / np.maximum(union, 1e-12), 0.0)


def weighted_nms(
    scores: FloatArray, boxes: FloatArray, keypoints: FloatArray, iou: float = NMS_IOU
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """MediaPipe's weighted non-max suppression: each kept detection is the
    score-weighted mean of the remaining ones overlapping it by more than ``iou``."""
    order = np.argsort(-scores, kind="stable")
    remaining = order
    out_s, out_b, out_k = [], [], []
    while len(remaining):
        ious = box_iou(boxes[remaining[:1]], boxes[remaining])[0]
        group = remaining[ious > iou]
        group = group if len(group) else remaining[:1]
        w = scores[group] / scores[group].sum()
        out_s.append(scores[remaining[0]])
        out_b.append(w @ boxes[group])
        out_k.append(np.einsum("n,nkd->kd", w, keypoints[group]))
        remaining = remaining[~np.isin(remaining, group)]
    if not out_s:
        return np.zeros(0), np.zeros((0, 4)), np.zeros((0, 4, 2))
    return np.array(out_s), np.array(out_b), np.array(out_k)


def roi_from_detection(det: PersonBox) -> Roi:
    """pose_detection_to_roi: hip centre, 2.5 x the hip-to-scale-point distance."""
    hip, scale = det.keypoints[0], det.keypoints[1]
    d = scale - hip
    rotation = np.pi / 2.0 - np.arctan2(-d[1], d[0])
    rotation = float((rotation + np.pi) % (2.0 * np.pi) - np.pi)
    side = 2.0 * float(np.hypot(*d)) * ROI_SCALE
    return Roi(center=hip.astype(np.float64), side=side, rotation=rotation)


def _refine_from_heatmap(xy_norm: FloatArray, heatmap: FloatArray) -> FloatArray:
    """RefineLandmarksFromHeatmapCalculator (kernel 7, min confidence 0.5)."""
    hm_h, hm_w, n = heatmap.shape
    conf = _sigmoid(heatmap.astype(np.float64))
    col = (xy_norm[:, 0] * hm_w).astype(np.int64)
    row = (xy_norm[:, 1] * hm_h).astype(np.int64)
    ok = (col >= 0) & (col < hm_w) & (row >= 0) & (row < hm_h)
    off = np.arange(HEATMAP_KERNEL) - HEATMAP_KERNEL // 2
    rows = row[:, None] + off[None, :]  # (n, k)
    cols = col[:, None] + off[None, :]
    valid = ((rows[:, :, None] >= 0) & (rows[:, :, None] < hm_h)) & (
        (cols[:, None, :] >= 0) & (cols[:, None, :] < hm_w)
    )
    rr = np.clip(rows, 0, hm_h - 1)[:, :, None]
    cc = np.clip(cols, 0, hm_w - 1)[:, None, :]
    c = np.where(valid, conf[rr, cc, np.arange(n)[:, None, None]], 0.0)  # (n, k, k)
    total = c.sum(axis=(1, 2))
    refine = ok & (c.max(axis=(1, 2)) >= HEATMAP_MIN_CONFIDENCE) & (total > 0)
    safe = np.maximum(total, 1e-12)
    wx = (c * cols[:, None, :]).sum(axis=(1, 2)) / safe / hm_w
    wy = (c * rows[:, :, None]).sum(axis=(1, 2)) / safe / hm_h
    out = xy_norm.copy()
    out[refine] = np.stack([wx, wy], axis=1)[refine]
    return out


class BlazePose:
    """MediaPipe's person detector and landmark model, every person kept."""

    def __init__(self, modules: Path | None = None) -> None:
        modules = modules or models_dir()
        self._detector = _interpreter(
            modules / "pose_detection" / "pose_detection.tflite"
        )
        self._landmark = _interpreter(
            modules / "pose_landmark" / "pose_landmark_full.tflite"
        )
        self._det_io = self._io(self._detector)
        self._lm_io = self._io(self._landmark)

    @staticmethod
    def _io(interp: Any) -> tuple[int, dict[tuple[int, ...], int]]:
        inp = interp.get_input_details()[0]["index"]
        outs = {tuple(d["shape"][1:]): d["index"] for d in interp.get_output_details()}
        return inp, outs

    def _detect_roi(
        self, image_rgb: np.ndarray, roi: Roi, min_score: float
    ) -> list[PersonBox]:
        """The detector on one square region (letterboxed when it leaves the image)."""
        tensor = _crop(image_rgb, roi, DETECTOR_SIZE) / 127.5 - 1.0
        inp, outs = self._det_io
        self._detector.set_tensor(inp, tensor[None])
        self._detector.invoke()
        raw_boxes = self._detector.get_tensor(outs[(2254, 12)])[0]
        raw_scores = self._detector.get_tensor(outs[(2254, 1)])[0]
        scores, boxes, kps = weighted_nms(
            *decode_detections(raw_boxes, raw_scores, min_score)
        )
        # Letterbox removal: normalised input -> image pixels.
        origin = roi.center - roi.side / 2.0
        return [
            PersonBox(
                score=float(s),
                box=np.concatenate([origin, origin]) + b * roi.side,
                keypoints=origin + k * roi.side,
            )
            for s, b, k in zip(scores, boxes, kps, strict=True)
        ]

    def detect(
        self,
        image_rgb: np.ndarray,
        min_score: float = 0.5,
        levels: int = 3,
        fine_min_score: float = 0.7,
    ) -> list[PersonBox]:
        """Every person box (image pixels), best first.

        Pass 0 is MediaPipe's: the whole image letterboxed. People far away are a few
        detector pixels tall there, so pass 1 runs the detector on squares of the
        image's shorter side along its longer one and pass 2 on squares of half that
        side (a grid, half overlapping), keeping only boxes scoring ``fine_min_score``
        (small squares see parts of people as people). ``levels`` is the number of
        passes. Boxes of different passes are not merged here: the landmarks say who
        is the same person (:func:`find_people`).
        """
        h, w = image_rgb.shape[:2]
        size = np.array([w, h], dtype=np.float64)
        passes: list[tuple[list[Roi], float]] = [
            ([Roi(center=size / 2.0, side=float(max(h, w)), rotation=0.0)], min_score)
        ]
        short = float(min(h, w))
        for level, threshold in ((1, min_score), (2, max(min_score, fine_min_score))):
            side = short / level
            if level >= levels or (level == 1 and max(h, w) < 1.2 * short):
                continue
            axes = [
                np.linspace(
                    side / 2.0,
                    n - side / 2.0,
                    int(np.ceil((n - side) / (side / 2.0))) + 1,
                )
                for n in size
            ]
            centres = np.stack(np.meshgrid(*axes), axis=-1).reshape(-1, 2)
            passes.append(
                ([Roi(center=c, side=side, rotation=0.0) for c in centres], threshold)
            )
        found = [
            d
            for rois, threshold in passes
            for roi in rois
            for d in self._detect_roi(image_rgb, roi, threshold)
        ]
        return sorted(found, key=lambda d: -d.score)

    def landmarks(self, image_rgb: np.ndarray, det: PersonBox) -> PoseResult:
        """The landmark model on the detection's ROI, mapped back into the image."""
        h, w = image_rgb.shape[:2]
        roi = roi_from_detection(det)
        tensor = _crop(image_rgb, roi, LANDMARK_SIZE) / 255.0
        inp, outs = self._lm_io
        self._landmark.set_tensor(inp, tensor[None])
        self._landmark.invoke()
        raw = self._landmark.get_tensor(outs[(195,)])[0].reshape(NUM_MODEL_LANDMARKS, 5)
        flag = float(self._landmark.get_tensor(outs[(1,)])[0, 0])
        seg = self._landmark.get_tensor(outs[(LANDMARK_SIZE, LANDMARK_SIZE, 1)])[
            0, :, :, 0
        ]
        heatmap = self._landmark.get_tensor(outs[(64, 64, NUM_MODEL_LANDMARKS)])[0]
        world = self._landmark.get_tensor(outs[(117,)])[0].reshape(-1, 3)
        xy_norm = _refine_from_heatmap(
            raw[:, :2].astype(np.float64) / LANDMARK_SIZE, heatmap
        )
        n = body.NUM_LANDMARKS
        # Crop-normalised -> image pixels (the inverse of the crop, in COLMAP pixels).
        c, s = np.cos(roi.rotation), np.sin(roi.rotation)
        rot = np.array([[c, -s], [s, c]])
        xy = (xy_norm[:n] - 0.5) * roi.side @ rot.T + roi.center
        p3 = world[:n].astype(np.float64)
        p3[:, :2] = p3[:, :2] @ rot.T
        vis = _sigmoid(raw[:n, 3].astype(np.float64))
        logits = cv2.warpAffine(
            seg.astype(np.float32),
            _crop_matrix(roi, LANDMARK_SIZE),
            (w, h),
            flags=cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=-np.inf,
        )
        return PoseResult(
            landmarks=body.BodyLandmarks(xy_img=xy, points_3d=p3, visibility=vis),
            presence=flag,
            # float32 already (warpAffine keeps its input's depth); cv2's stub types
            # the result as any int or float array.
            segmentation_logits=np.asarray(logits, dtype=np.float32),
            roi=roi,
            detection=det,
        )

    def close(self) -> None:
        """Nothing to release (the interpreters are garbage-collected)."""

    def __enter__(self) -> BlazePose:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def landmark_box(lm: body.BodyLandmarks, min_visibility: float = 0.0) -> FloatArray:
    """(4,) box around the landmarks seen with at least ``min_visibility``."""
    xy = lm.xy_img[lm.visibility >= min_visibility]
    if len(xy) < 2:
        xy = lm.xy_img
    return np.concatenate([xy.min(axis=0), xy.max(axis=0)])


def segmentation_mask(result: PoseResult) -> BoolArray:
    """The person's segmentation (sigmoid >= 0.5) in image pixels."""
    return result.segmentation_logits >= 0.0


def shared_landmarks(
    a: body.BodyLandmarks, b: body.BodyLandmarks, tol: float = 0.1
) -> float:
    """Fraction of the 33 landmarks two landmark sets put at the same place (within
    ``tol`` x the longer side of the larger landmark box). The same person found
    twice shares most; two people side by side share none; a crop between two
    overlapping people mixes them and shares some with each."""
    size = max(
        float(np.ptp(a.xy_img, axis=0).max()), float(np.ptp(b.xy_img, axis=0).max())
    )
    dist = np.linalg.norm(a.xy_img - b.xy_img, axis=1)
    return float((dist < tol * max(size, 1.0)).mean())


FEET_NAMES = (
    "left_ankle",
    "right_ankle",
    "left_heel",
    "right_heel",
    "left_foot_index",
    "right_foot_index",
)
FEET = tuple(body.BLAZEPOSE_NAMES.index(n) for n in FEET_NAMES)


def _feet_row(lm: body.BodyLandmarks, min_visibility: float = 0.5) -> float | None:
    """The image row of the person's lowest seen foot landmark; None when no
    foot landmark is seen."""
    feet = np.asarray(FEET)
    seen = feet[lm.visibility[feet] >= min_visibility]
    return float(lm.xy_img[seen, 1].max()) if len(seen) else None


def _part_of(a: body.BodyLandmarks, b: body.BodyLandmarks) -> bool:
    """Whether a is a part of b or a copy of b: a's landmark box 80 % inside
    b's, and either at most half its area (a crop on one limb of b, e.g. its
    legs), or with its feet not below b's. People stand on one floor, and the
    camera looks down on it: one standing in front of b (a child before an
    adult), whose box can lie inside b's, has its feet lower in the image. A
    re-saved pose2sim JPEG gave a skeleton on the man's legs, its box 52 % of
    his and 99 % inside it, its feet 330 px above his (tests/test_detector.py).
    Feet not seen, in either: a is kept."""
    box_a, box_b = landmark_box(a, 0.5), landmark_box(b, 0.5)
    area_a = float(np.prod(box_a[2:] - box_a[:2]))
    area_b = float(np.prod(box_b[2:] - box_b[:2]))
    inter = np.prod(
        np.clip(
            np.minimum(box_a[2:], box_b[2:]) - np.maximum(box_a[:2], box_b[:2]), 0, None
        )
    )
    if float(inter) < 0.8 * max(area_a, 1.0):
        return False
    if area_a <= 0.5 * area_b:
        return True
    feet_a, feet_b = _feet_row(a), _feet_row(b)
    return feet_a is not None and feet_b is not None and feet_a <= feet_b


def find_people(
    model: BlazePose,
    image_rgb: np.ndarray,
    *,
    min_score: float = 0.5,
    min_presence: float = 0.5,
    max_people: int = 8,
    levels: int = 3,
    min_fill: float = 0.5,
) -> list[PoseResult]:
    """Every person in an RGB image: detections -> landmarks, duplicates merged.

    Detections are taken best first. A detection adds nobody when its pose-presence
    flag is below ``min_presence``, when its landmarks' box spans less than
    ``min_fill`` of its crop (the landmarks collapsed onto something that is not a
    whole person: a real one fills 0.55-0.8 on pose2sim, false ones 0.3-0.45), when
    they repeat a person already found (:func:`shared_landmarks` >= ``SAME_PERSON``,
    or >= ``MAYBE_SAME`` from a detection scoring below ``SURE_SCORE``) or land on a
    small part of one (e.g. a crop on the legs).
    """
    people: list[PoseResult] = []
    seen: list[FloatArray] = []  # (2, 2) hip and scale keypoints of tried detections
    for det in model.detect(image_rgb, min_score, levels=levels):
        if len(people) >= max_people:
            break
        # The same person seen by several passes: its ROI is already tried.
        kps = det.keypoints[:2]
        tol = 0.15 * float(np.linalg.norm(kps[1] - kps[0]))
        if any(np.linalg.norm(kps - k, axis=1).max() < tol for k in seen):
            continue
        seen.append(kps)
        res = model.landmarks(image_rgb, det)
        if res.presence < min_presence:
            logger.debug("detection %.2f: pose presence %.2f", det.score, res.presence)
            continue
        box = landmark_box(res.landmarks, 0.5)
        if float((box[2:] - box[:2]).max()) < min_fill * res.roi.side:
            continue
        shared = max(
            (shared_landmarks(res.landmarks, p.landmarks) for p in people), default=0.0
        )
        if shared >= SAME_PERSON or (shared >= MAYBE_SAME and det.score < SURE_SCORE):
            continue
        if any(_part_of(res.landmarks, p.landmarks) for p in people):
            continue
        people.append(res)
    return people
