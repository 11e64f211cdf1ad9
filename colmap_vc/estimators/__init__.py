"""Prior estimators: human priors (docs/priors.md) from photos, offline on a CPU.

The bundled default is :mod:`colmap_vc.estimators.mediapipe` (MediaPipe Pose 0.10.14,
whose model ships inside its wheel) + :mod:`colmap_vc.estimators.fit` (the Anny body
fitted to its landmarks in the known camera). MediaPipe is an optional dependency and
is imported only when an estimator runs. Stronger networks plug in through the priors
format itself or through :mod:`colmap_vc.adapters`.
"""

from __future__ import annotations

import enum
import logging
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import pycolmap

from colmap_vc.estimators.fit import FitOptions
from colmap_vc.image_io import read_image

logger = logging.getLogger(__name__)

IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".webp")


class EstimatorKind(enum.StrEnum):
    """Which estimator makes the priors."""

    MEDIAPIPE = "mediapipe"


@dataclass(frozen=True, kw_only=True, slots=True)
class EstimatorOptions:
    """Options of `colmap-vc priors`."""

    estimator: EstimatorKind = EstimatorKind.MEDIAPIPE
    """The estimator (only MediaPipe Pose is bundled)."""
    max_people: int = 4
    """Most people kept per image (best detections first)."""
    min_detection_confidence: float = 0.5
    """Score threshold of the BlazePose person detector."""
    detector_levels: int = 3
    """Detector passes: 1 = the whole image (as MediaPipe), 2 = also squares of the
    shorter side, 3 = also half-size squares, which find people far away (the
    bystander of pose2sim) and people partly hidden by others, for ~0.5 s more per
    image. With 3, pose2sim_multi (user path, per instant) goes from 48.8 to 55.9
    AUC@15; pose2sim_single is unchanged (docs/results.md)."""
    min_visibility: float = 0.5
    """Landmarks below this visibility are neither 2D evidence nor valid keypoints."""
    min_mean_visibility: float = 0.5
    """Skip a detection whose 12 body landmarks have a lower mean visibility."""
    min_person_size_px: float = 100.0
    """Skip people whose landmarks span fewer pixels (longer side of their box)."""
    min_body_landmarks_inside: int = 8
    """Skip people with fewer of the 12 body landmarks inside the image (cut off)."""
    min_mask_iou: float = 0.3
    """Skip fits whose silhouette overlaps the segmentation mask less (IoU)."""
    max_reprojection_error_frac: float = 0.06
    """Skip fits whose median landmark reprojection error exceeds this fraction of
    the person's size in pixels."""
    surface_stride_px: int = 2
    """Ray-cast every n-th row and column of the mask for the dense surface map."""
    fit: FitOptions = field(default_factory=FitOptions)
    """Options of the body fit."""
    show_progress: bool = True
    """Progress bar on stderr."""


@dataclass(frozen=True, kw_only=True, slots=True)
class PersonReport:
    """What became of one detection."""

    image_name: str
    detection: int  # image-local index, in detection order
    kept: bool
    reason: str  # why it was skipped; "" when kept
    depth_m: float = float("nan")  # median vertex depth of the fitted mesh
    mask_iou: float = float("nan")  # fitted silhouette vs segmentation mask
    reprojection_error_px: float = float("nan")  # median over the 2D landmarks used
    size_px: float = float("nan")  # longer side of the landmarks' box
    relabelled_left_right: bool = False
    shape: str = ""  # phenotype blend, e.g. "man_average" or "0.75 child + ..."


@dataclass(frozen=True, kw_only=True, slots=True)
class EstimatorReport:
    """Per-image outcome of an estimator run."""

    skipped: dict[str, str] = field(default_factory=dict)
    """Image name -> why no person was kept (no detection, too small, cut, ...)."""
    persons: tuple[PersonReport, ...] = ()
    """Every detection, kept or skipped, in image then detection order."""
    seconds: dict[str, float] = field(default_factory=dict)
    """Image name -> wall-clock seconds spent on it."""
    unusable: frozenset[str] = frozenset()
    """Images nothing was looked for in: unreadable, or not the size of their
    camera (their reason is in ``skipped``)."""


@dataclass(frozen=True, kw_only=True, slots=True)
class EstimatorSummary:
    """What `colmap-vc priors` did."""

    priors_path: Path  # priors.json
    num_images: int
    num_images_with_people: int
    num_persons: int
    skipped: dict[str, str]  # image name -> reason
    report: EstimatorReport
    seconds: float


def _list_images(image_dir: Path) -> list[str]:
    """Image files below ``image_dir``, as POSIX paths relative to it, sorted."""
    return sorted(
        p.relative_to(image_dir).as_posix()
        for p in image_dir.rglob("*")
        if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS
    )


def _guess_cameras(image_dir: Path, names: list[str]) -> dict[str, pycolmap.Camera]:
    """COLMAP's own default for unknown cameras: SIMPLE_RADIAL, f = 1.2 max(w, h)."""
    cameras = {}
    for name in names:
        image = read_image(image_dir / name)
        if image is None:
            continue
        h, w = image.shape[:2]
        cameras[name] = pycolmap.Camera(
            model="SIMPLE_RADIAL",
            width=w,
            height=h,
            params=[1.2 * max(w, h), w / 2.0, h / 2.0, 0.0],
        )
    return cameras


def run_estimator(
    image_dir: Path,
    output: Path,
    *,
    cameras: Mapping[str, pycolmap.Camera] | None = None,
    database_path: Path | None = None,
    options: EstimatorOptions | None = None,
) -> EstimatorSummary:
    """Estimate the priors of the images in ``image_dir`` and write them to ``output``.

    The cameras (intrinsics) come from ``cameras`` (image name -> camera), else from
    the COLMAP database (the images it lists), else COLMAP's default guess for every
    image found under ``image_dir`` (with a warning: the meshes' depth then scales with
    the guessed focal length).

    Raises:
        FileNotFoundError: ``image_dir`` or the database does not exist.
        ImportError: MediaPipe is not installed (the message says how to install it).
    """
    options = options or EstimatorOptions()
    start = time.perf_counter()
    image_dir = Path(image_dir)
    if not image_dir.is_dir():
        raise FileNotFoundError(f"image directory {image_dir} does not exist")
    if cameras is None and database_path is not None:
        from colmap_vc.database import read_views

        if not Path(database_path).is_file():
            raise FileNotFoundError(f"database {database_path} does not exist")
        views = read_views(database_path)
        cameras = {
            name: views.cameras[int(cid)]
            for name, cid in zip(views.image_names, views.camera_ids, strict=True)
        }
        guessed = sorted(n for n, c in cameras.items() if not c.has_prior_focal_length)
        if guessed:
            logger.warning(
                "%d of %d images in %s have no known focal length (COLMAP's "
                "guess, 1.2 max(width, height), e.g. %s): the meshes' depth "
                "scales with it; give the intrinsics when you extract features",
                len(guessed),
                len(cameras),
                database_path,
                guessed[0],
            )
    unreadable: dict[str, str] = {}
    if cameras is None:
        names = _list_images(image_dir)
        if not names:
            raise FileNotFoundError(
                f"no images ({', '.join(sorted(IMAGE_EXTENSIONS))}) in {image_dir}"
            )
        logger.warning(
            "no cameras and no database: guessing intrinsics of %d images as COLMAP "
            "does (f = 1.2 max(width, height)); pass --database for real ones",
            len(names),
        )
        cameras = _guess_cameras(image_dir, names)
        unreadable = {
            n: f"cannot read {image_dir / n}" for n in names if n not in cameras
        }
    names = sorted(cameras)
    if not names:
        raise FileNotFoundError(f"none of the images in {image_dir} can be read")
    if options.estimator is not EstimatorKind.MEDIAPIPE:
        raise ValueError(f"unknown estimator {options.estimator!r}")
    from colmap_vc.estimators import mediapipe as mp_estimator
    from colmap_vc.priors import write_priors

    priors, report = mp_estimator.estimate_priors(image_dir, names, cameras, options)
    if len(report.unusable) == len(names):
        name = min(report.unusable)
        raise ValueError(
            f"none of the {len(names)} images could be used (e.g. {name}: "
            f"{report.skipped[name]}): no priors written. Check the image folder "
            "against the database's image names and camera sizes."
        )
    from colmap_vc.estimators.body import TEMPLATE_NAME, load_template

    path = write_priors(
        priors,
        Path(output),
        templates={TEMPLATE_NAME: load_template().model.faces},
        image_sizes={n: (cameras[n].width, cameras[n].height) for n in priors.images},
    )
    num_persons = sum(len(p.persons) for p in priors.images.values())
    summary = EstimatorSummary(
        priors_path=path,
        num_images=len(names),
        num_images_with_people=sum(1 for p in priors.images.values() if p.persons),
        num_persons=num_persons,
        skipped={**unreadable, **report.skipped},
        report=report,
        seconds=time.perf_counter() - start,
    )
    logger.info(
        "priors: %d persons in %d of %d images (%.1f s), %d images skipped -> %s",
        num_persons,
        summary.num_images_with_people,
        len(names),
        summary.seconds,
        len(summary.skipped),
        path,
    )
    for name, reason in summary.skipped.items():
        logger.info("  skipped %s: %s", name, reason)
    return summary


__all__ = [
    "EstimatorKind",
    "EstimatorOptions",
    "EstimatorReport",
    "EstimatorSummary",
    "PersonReport",
    "run_estimator",
]
