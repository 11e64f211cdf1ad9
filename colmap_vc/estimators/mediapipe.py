"""The bundled prior estimator: MediaPipe Pose + the Anny body fit, offline on a CPU.

MediaPipe 0.10.14 ships one pose-landmark model inside its wheel
(``mediapipe/modules/pose_landmark/pose_landmark_full.tflite``, model complexity 1)
and the person detector; the Tasks API (``PoseLandmarker``) needs a ``.task`` bundle
that the wheel does not ship, and complexities 0 and 2 download their model on first
use. So this module uses the legacy ``mp.solutions.pose.Pose(static_image_mode=True,
model_complexity=1, enable_segmentation=True)``, which runs with no network.

Per image: MediaPipe finds one person per pass; the person's segmentation and
landmark hull are painted grey and MediaPipe runs again, until it finds nobody, finds
a region already taken (the same person again) or ``max_people`` are found. Each
detection gets an image-local index and ``person_id = None`` (``augment`` associates
people across images geometrically). A detection is skipped, with a reason, if it is
low-confidence, too small, cut by the frame, or if the body fit fails or disagrees
with the silhouette. An image is never an error: a missing, unreadable or mis-sized
image is skipped with a reason too.
"""

from __future__ import annotations

import dataclasses
import logging
import time
import warnings
from collections.abc import Mapping, Sequence
from contextlib import AbstractContextManager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pycolmap
from tqdm import tqdm

from colmap_vc.estimators import (
    EstimatorOptions,
    EstimatorReport,
    PersonReport,
    appearance,
    body,
    fit,
    prior,
)
from colmap_vc.structs import BoolArray, ImagePrior, PersonPrior, ScenePriors

logger = logging.getLogger(__name__)

MODEL_COMPLEXITY = 1  # the only pose-landmark model inside the 0.10.14 wheel
GREY = 128  # paint over found people so the next pass looks elsewhere


@dataclass(frozen=True, kw_only=True, slots=True)
class Detection:
    """One MediaPipe detection: landmarks and segmentation."""

    landmarks: body.BodyLandmarks
    segmentation: BoolArray  # (H, W) bool


def _import_mediapipe() -> Any:
    try:
        import mediapipe
    except ImportError as exc:
        raise ImportError(
            "the MediaPipe estimator needs mediapipe 0.10.14: pip install --no-deps "
            "mediapipe==0.10.14 absl-py attrs flatbuffers 'protobuf>=4.25.3,<5' "
            "(see docs/real-data.md)"
        ) from exc
    return mediapipe


def open_pose(options: EstimatorOptions) -> AbstractContextManager[Any]:
    """A MediaPipe Pose solution for still images (a context manager)."""
    mp = _import_mediapipe()
    return mp.solutions.pose.Pose(  # type: ignore[no-any-return]
        static_image_mode=True,
        model_complexity=MODEL_COMPLEXITY,
        enable_segmentation=True,
        min_detection_confidence=options.min_detection_confidence,
    )


def _to_landmarks(result: Any, width: int, height: int) -> body.BodyLandmarks:
    """MediaPipe's result -> BodyLandmarks (pixels in COLMAP's convention)."""
    image_lm = result.pose_landmarks.landmark
    world_lm = result.pose_world_landmarks.landmark
    norm = np.array([(p.x, p.y) for p in image_lm], dtype=np.float64)
    # MediaPipe normalises by the image extent [0, W] x [0, H], which is COLMAP's
    # continuous pixel frame (pixel centres at +0.5): pixel = normalised * size.
    xy = norm * [width, height]
    # World landmarks: metres, centred between the hips, x right, y down, z away from
    # the camera (right-handed, like OpenCV).
    p3 = np.array([(p.x, p.y, p.z) for p in world_lm], dtype=np.float64)
    vis = np.array([p.visibility for p in image_lm], dtype=np.float64).clip(0.0, 1.0)
    return body.BodyLandmarks(xy_img=xy, points_3d=p3, visibility=vis)


def _landmark_region(lm: body.BodyLandmarks, shape: tuple[int, int]) -> BoolArray:
    """The convex hull of the in-image landmarks, as a mask."""
    h, w = shape
    xy = lm.xy_img[np.isfinite(lm.xy_img).all(axis=1)]
    region = np.zeros((h, w), dtype=np.uint8)
    if len(xy) >= 3:
        hull = cv2.convexHull((xy - 0.5).astype(np.float32))  # COLMAP -> OpenCV
        cv2.fillConvexPoly(region, np.round(hull).astype(np.int32), 1)
    return region.astype(bool)


def detect_people(
    pose: Any, image_rgb: np.ndarray, options: EstimatorOptions
) -> list[Detection]:
    """Every person MediaPipe finds in an RGB image, one pass per person."""
    h, w = image_rgb.shape[:2]
    work = image_rgb.copy()
    taken = np.zeros((h, w), dtype=bool)
    found: list[Detection] = []
    for _ in range(options.max_people):
        with warnings.catch_warnings():
            # protobuf 4 warns about MediaPipe's use of a deprecated API on every call.
            warnings.simplefilter("ignore", UserWarning)
            result = pose.process(work)
        if result.pose_landmarks is None or result.pose_world_landmarks is None:
            break
        lm = _to_landmarks(result, w, h)
        seg = (
            np.zeros((h, w), dtype=bool)
            if result.segmentation_mask is None
            else np.asarray(result.segmentation_mask) >= 0.5
        )
        px = np.floor(lm.xy_img).astype(np.int64)
        on = (px[:, 0] >= 0) & (px[:, 1] >= 0) & (px[:, 0] < w) & (px[:, 1] < h)
        seen = on & (lm.visibility >= options.min_visibility)
        if found and (not seen.any() or taken[px[seen, 1], px[seen, 0]].mean() > 0.5):
            break  # most of it lies on a person already found: nobody new
        found.append(Detection(landmarks=lm, segmentation=seg))
        region = seg | _landmark_region(lm, (h, w))
        ys, xs = np.nonzero(region)
        size = max(np.ptp(xs), np.ptp(ys)) if len(xs) else 0
        grow = 2 * int(0.05 * size) + 1
        grown = cv2.dilate(region.astype(np.uint8), np.ones((grow, grow), np.uint8))
        taken |= grown.astype(bool)
        work[taken] = GREY
    return found


def _shape_name(shape: tuple[int, int, float]) -> str:
    names = body.load_template().model.phenotype_names
    p, q, w = shape
    if w == 0.0 or p == q:
        return names[p]
    return f"{1 - w:g} {names[p]} + {w:g} {names[q]}"


def person_from_detection(
    det: Detection,
    camera: pycolmap.Camera,
    options: EstimatorOptions,
    image_name: str = "",
    index: int = 0,
) -> tuple[PersonPrior | None, PersonReport]:
    """Quality checks, body fit and prior of one detection (None when skipped)."""
    lm = det.landmarks
    rows = np.array([body.BLAZEPOSE_NAMES.index(n) for n in body.BODY_LANDMARKS])
    xy = lm.xy_img[rows]
    inside = (xy[:, 0] >= 0) & (xy[:, 1] >= 0) & (xy[:, 0] <= camera.width)
    inside &= xy[:, 1] <= camera.height
    seen = inside & (lm.visibility[rows] >= options.min_visibility)
    size = float(max(np.ptp(xy[seen], axis=0))) if seen.sum() >= 2 else 0.0
    mean_vis = float(lm.visibility[rows].mean())

    def skip(reason: str, **kw: Any) -> tuple[None, PersonReport]:
        return None, PersonReport(
            image_name=image_name,
            detection=index,
            kept=False,
            reason=reason,
            size_px=size,
            **kw,
        )

    if mean_vis < options.min_mean_visibility:
        return skip(
            f"low-confidence detection (mean visibility {mean_vis:.2f} < "
            f"{options.min_mean_visibility})"
        )
    if int(inside.sum()) < options.min_body_landmarks_inside:
        return skip(
            f"cut by the frame ({int(inside.sum())} of 12 body landmarks inside, "
            f"need {options.min_body_landmarks_inside})"
        )
    if size < options.min_person_size_px:
        return skip(f"too small ({size:.0f} px < {options.min_person_size_px:g} px)")
    try:
        fitted = fit.fit_body(lm, camera, options=options.fit)
    except (ValueError, np.linalg.LinAlgError) as exc:
        return skip(f"fit failed: {exc}")
    err = float(np.median(fitted.reprojection_error_px[fitted.used_2d]))
    depth = float(np.median(fitted.vertices_cam[:, 2]))
    stats: dict[str, Any] = {
        "depth_m": depth,
        "reprojection_error_px": err,
        "relabelled_left_right": fitted.relabelled,
        "shape": _shape_name(fitted.shape),
    }
    if err > options.max_reprojection_error_frac * size:
        return skip(
            f"fit disagrees with the landmarks (median {err:.1f} px > "
            f"{options.max_reprojection_error_frac:g} x {size:.0f} px)",
            **stats,
        )
    if (fitted.vertices_cam[:, 2] <= 0.05).mean() > 0.05:
        return skip("fit put the body behind the camera", **stats)
    person, iou = prior.prior_from_fit(
        fitted,
        camera,
        det.segmentation if det.segmentation.any() else None,
        min_visibility=options.min_visibility,
        surface_stride_px=options.surface_stride_px,
    )
    if iou < options.min_mask_iou:
        return skip(
            f"fit disagrees with the silhouette (IoU {iou:.2f} < "
            f"{options.min_mask_iou})",
            mask_iou=iou,
            **stats,
        )
    # Confidence: landmark visibility, discounted when the silhouette fits poorly.
    person = dataclasses.replace(person, confidence=mean_vis * min(1.0, iou / 0.7))
    report = PersonReport(
        image_name=image_name,
        detection=index,
        kept=True,
        reason="",
        mask_iou=iou,
        size_px=size,
        **stats,
    )
    return person, report


def _with_appearance(
    person: PersonPrior,
    det: Detection,
    image_rgb: np.ndarray,
    options: EstimatorOptions,
) -> PersonPrior:
    """The person's clothing colours (estimators.appearance), for the association."""
    lm = det.landmarks
    h, w = image_rgb.shape[:2]
    inside = (lm.xy_img[:, 0] >= 0) & (lm.xy_img[:, 0] < w)
    inside &= (lm.xy_img[:, 1] >= 0) & (lm.xy_img[:, 1] < h)
    visible = inside & (lm.visibility >= options.min_visibility)
    mask = person.mask if person.mask is not None else det.segmentation
    colours = appearance.describe_person(image_rgb, lm.xy_img, visible, mask)
    return dataclasses.replace(person, appearance=colours)


def read_image(path: Path) -> np.ndarray | None:
    """RGB uint8 pixels as stored, ignoring EXIF orientation (as COLMAP reads them)."""
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
    return None if bgr is None else np.ascontiguousarray(bgr[:, :, ::-1])


def estimate_image(
    pose: Any,
    image_rgb: np.ndarray,
    camera: pycolmap.Camera,
    options: EstimatorOptions,
    image_name: str = "",
) -> tuple[ImagePrior, list[PersonReport], str | None]:
    """Priors of one image; the reason when nobody was kept (else None)."""
    h, w = image_rgb.shape[:2]
    if (w, h) != (camera.width, camera.height):
        mismatch = f"image is {w}x{h} but its camera is {camera.width}x{camera.height}"
        return ImagePrior(image_name=image_name, persons=()), [], mismatch
    persons: list[PersonPrior] = []
    reports: list[PersonReport] = []
    for k, det in enumerate(detect_people(pose, image_rgb, options)):
        person, report = person_from_detection(det, camera, options, image_name, k)
        reports.append(report)
        if person is not None:
            persons.append(_with_appearance(person, det, image_rgb, options))
    reason: str | None = None
    if not reports:
        reason = "no person detected"
    elif not persons:
        reason = "; ".join(f"detection {r.detection}: {r.reason}" for r in reports)
    return ImagePrior(image_name=image_name, persons=tuple(persons)), reports, reason


def estimate_priors(
    image_dir: Path,
    image_names: Sequence[str],
    cameras: Mapping[str, pycolmap.Camera],
    options: EstimatorOptions | None = None,
) -> tuple[ScenePriors, EstimatorReport]:
    """MediaPipe priors of the named images (image name -> camera in ``cameras``).

    Every image gets an entry (an empty one when nobody was kept); the report says why
    images were skipped, and what became of every detection.

    Raises:
        ImportError: MediaPipe is not installed.
        ValueError: an image name has no camera.
    """
    options = options or EstimatorOptions()
    missing = [n for n in image_names if n not in cameras]
    if missing:
        raise ValueError(f"{len(missing)} image(s) have no camera, e.g. {missing[0]!r}")
    images: dict[str, ImagePrior] = {}
    skipped: dict[str, str] = {}
    reports: list[PersonReport] = []
    seconds: dict[str, float] = {}
    with open_pose(options) as pose:
        for name in tqdm(image_names, desc="priors", disable=not options.show_progress):
            start = time.perf_counter()
            rgb = read_image(Path(image_dir) / name)
            if rgb is None:
                reason: str | None = f"cannot read {Path(image_dir) / name}"
                images[name] = ImagePrior(image_name=name, persons=())
            else:
                images[name], rep, reason = estimate_image(
                    pose, rgb, cameras[name], options, name
                )
                reports.extend(rep)
            if reason is not None:
                skipped[name] = reason
                logger.info("%s: skipped: %s", name, reason)
            seconds[name] = time.perf_counter() - start
            logger.debug(
                "%s: %d person(s) in %.2f s",
                name,
                len(images[name].persons),
                seconds[name],
            )
    report = EstimatorReport(skipped=skipped, persons=tuple(reports), seconds=seconds)
    return ScenePriors(images=images), report
