"""The bundled prior estimator: MediaPipe's BlazePose models + the Anny body fit,
offline on a CPU.

MediaPipe 0.10.14 ships its person detector (``pose_detection.tflite``) and one
pose-landmark model (``pose_landmark_full.tflite``) inside its wheel. Its legacy
``Pose`` solution keeps only the detector's best box, so
:mod:`colmap_vc.estimators.blazepose` runs both models by hand (``ai-edge-litert``)
and keeps every person: all detections of the whole image and of overlapping square
tiles, landmarks and segmentation per detection crop, duplicates merged.

Each detection gets an image-local index and ``person_id = None`` (``augment``
associates people across images). A detection is skipped, with a reason, if it is
low-confidence, too small, cut by the frame, or if the body fit fails or disagrees
with the silhouette. An image is never an error: a missing, unreadable or mis-sized
image is skipped with a reason too.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pycolmap
from tqdm import tqdm

from colmap_vc.estimators import (
    EstimatorOptions,
    EstimatorReport,
    PersonReport,
    appearance,
    blazepose,
    body,
    fit,
    prior,
)
from colmap_vc.image_io import read_image as read_stored
from colmap_vc.structs import BoolArray, ImagePrior, PersonPrior, ScenePriors

logger = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True, slots=True)
class Detection:
    """One person found by BlazePose: landmarks and segmentation."""

    landmarks: body.BodyLandmarks
    segmentation: BoolArray  # (H, W) bool


def open_pose(options: EstimatorOptions) -> blazepose.BlazePose:
    """MediaPipe's detector and landmark models (a context manager)."""
    del options  # thresholds are applied per image
    return blazepose.BlazePose()


def detect_people(
    pose: blazepose.BlazePose, image_rgb: np.ndarray, options: EstimatorOptions
) -> list[Detection]:
    """Every person BlazePose finds in an RGB image, best detection first."""
    found = blazepose.find_people(
        pose,
        image_rgb,
        min_score=options.min_detection_confidence,
        max_people=options.max_people,
        levels=options.detector_levels,
    )
    return [
        Detection(landmarks=p.landmarks, segmentation=blazepose.segmentation_mask(p))
        for p in found
    ]


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
    bgr = read_stored(path)
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
    unusable: set[str] = set()
    reports: list[PersonReport] = []
    seconds: dict[str, float] = {}
    with open_pose(options) as pose:
        for name in tqdm(image_names, desc="priors", disable=not options.show_progress):
            start = time.perf_counter()
            rgb = read_image(Path(image_dir) / name)
            camera = cameras[name]
            if rgb is None or rgb.shape[:2] != (camera.height, camera.width):
                unusable.add(name)
            if rgb is None:
                reason: str | None = f"cannot read {Path(image_dir) / name}"
                images[name] = ImagePrior(image_name=name, persons=())
            else:
                images[name], rep, reason = estimate_image(
                    pose, rgb, cameras[name], options, name
                )
                reports.extend(rep)
            images[name] = dataclasses.replace(
                images[name], focal_px=float(camera.mean_focal_length())
            )
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
    report = EstimatorReport(
        skipped=skipped,
        persons=tuple(reports),
        seconds=seconds,
        unusable=frozenset(unusable),
    )
    return ScenePriors(images=images), report
