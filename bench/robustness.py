"""The user's path on variants of real photos: sizes, crops, EXIF, grey, no intrinsics.

Unseen real data differs from pose2sim's 1920-px colour frames in ways that
should not matter: it is smaller, cropped, tagged with an EXIF orientation
(phone photos), or grey. Each variant of pose2sim_single's 20 photos goes through
what `bench/realdata.py` does for the originals (database with the known
intrinsics, adjusted to the variant; `priors`; `augment`; `map`; per instant,
pairs pooled over the five instants), and is compared with the originals in the
same run:

- ``original``: the photos as they are;
- ``half``: resized to 544 x 960 (intrinsics scaled);
- ``quarter``: resized to 272 x 480;
- ``top60``: the top 60 % of each frame (the people's feet cut; cx, cy kept);
- ``exif6``: the same JPEG bytes with an EXIF segment saying "rotate 90"
  (orientation 6), as a phone writes them; COLMAP and colmap-vc read the stored
  pixels;
- ``jpeg95``: decoded and saved again at JPEG quality 95 (a user's re-save: a
  change of a fraction of a grey level per pixel);
- ``grey``: single-channel JPEGs;
- ``guessed``: the original photos in a database made without the intrinsics
  (COLMAP's guess, f = 1.2 times the larger side, as for frames without EXIF):
  `map` then warns and keeps COLMAP's arbitrary scale.

    .venv/bin/python bench/robustness.py [--variants original half ...]   (~15 min)

Each instant also gives the metric scale `map` put on its model: its camera
distances over the calibration's, and whether the uncertainty `map` reported
covers the truth.

Writes bench/out/robustness.json and the "robustness" section of docs/results.md.
"""

from __future__ import annotations

import argparse
import logging
import shutil
import struct
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pycolmap
from common import DOCS, OUT, machine, replace_section, setup_logging, write_json
from realdata import (
    INSTANTS,
    SHARED,
    _largest_model,
    load_calibration,
    pooled,
    run_instant,
)

from colmap_vc.evaluation import camera_distance_ratio, poses_by_name
from colmap_vc.metric_scale import read_metric_scale

logger = logging.getLogger("bench.robustness")

DATA = SHARED / "pose2sim_single"


def _scaled(camera: pycolmap.Camera, s: float) -> pycolmap.Camera:
    """The camera of the image resized by ``s`` (OPENCV: fx fy cx cy k1 k2 p1 p2)."""
    p = np.asarray(camera.params, float).copy()
    p[:4] *= s
    return pycolmap.Camera(
        model="OPENCV",
        width=round(camera.width * s),
        height=round(camera.height * s),
        params=p,
    )


def _cropped(camera: pycolmap.Camera, keep: float) -> pycolmap.Camera:
    """The camera of the image's top ``keep`` rows (the principal point stays)."""
    return pycolmap.Camera(
        model="OPENCV",
        width=camera.width,
        height=round(camera.height * keep),
        params=camera.params,
    )


def _write_resized(s: float) -> Callable[[np.ndarray, Path], None]:
    def write(image: np.ndarray, path: Path) -> None:
        h, w = image.shape[:2]
        small = cv2.resize(
            image, (round(w * s), round(h * s)), interpolation=cv2.INTER_AREA
        )
        cv2.imwrite(str(path), small, [cv2.IMWRITE_JPEG_QUALITY, 95])

    return write


def _write_top(keep: float) -> Callable[[np.ndarray, Path], None]:
    def write(image: np.ndarray, path: Path) -> None:
        top = image[: round(image.shape[0] * keep)]
        cv2.imwrite(str(path), top, [cv2.IMWRITE_JPEG_QUALITY, 95])

    return write


def _write_exif(image: np.ndarray, path: Path) -> None:
    """The original JPEG's bytes with an EXIF segment (orientation 6, "rotate 90
    clockwise to display") after its start marker: the same pixels, tagged."""
    del image
    tiff = (
        b"MM\x00\x2a\x00\x00\x00\x08"  # big-endian TIFF, first IFD at 8
        + b"\x00\x01"  # one entry
        + b"\x01\x12\x00\x03\x00\x00\x00\x01\x00\x06\x00\x00"  # Orientation = 6
        + b"\x00\x00\x00\x00"  # no next IFD
    )
    payload = b"Exif\x00\x00" + tiff
    segment = b"\xff\xe1" + struct.pack(">H", len(payload) + 2) + payload
    data = (DATA / "images" / path.name).read_bytes()
    assert data[:2] == b"\xff\xd8", path.name
    path.write_bytes(data[:2] + segment + data[2:])


def _write_jpeg95(image: np.ndarray, path: Path) -> None:
    """Decoded and saved again at JPEG quality 95 (a user's re-save)."""
    cv2.imwrite(str(path), image, [cv2.IMWRITE_JPEG_QUALITY, 95])


def _write_grey(image: np.ndarray, path: Path) -> None:
    grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    cv2.imwrite(str(path), grey, [cv2.IMWRITE_JPEG_QUALITY, 95])


def _write_original(image: np.ndarray, path: Path) -> None:
    del image
    shutil.copyfile(DATA / "images" / path.name, path)


VARIANTS: dict[
    str,
    tuple[
        Callable[[np.ndarray, Path], None],
        Callable[[pycolmap.Camera], pycolmap.Camera | None],
    ],
] = {
    "original": (_write_original, lambda c: c),
    "half": (_write_resized(0.5), lambda c: _scaled(c, 0.5)),
    "quarter": (_write_resized(0.25), lambda c: _scaled(c, 0.25)),
    "top60": (_write_top(0.6), lambda c: _cropped(c, 0.6)),
    "exif6": (_write_exif, lambda c: c),
    "jpeg95": (_write_jpeg95, lambda c: c),
    "grey": (_write_grey, lambda c: c),
    "guessed": (_write_original, lambda c: None),
}


def run_variant(name: str) -> dict:
    """The variant's photos, then each instant through the user's path."""
    write, camera_of = VARIANTS[name]
    cameras, gt = load_calibration(DATA)
    work = OUT / "robustness" / name
    data = work / "data"
    images = data / "images"
    if images.exists():
        shutil.rmtree(images)  # the bench's own copies, made again
    images.mkdir(parents=True)
    for image_name in sorted(gt):  # loop over the 20 photos
        write(cv2.imread(str(DATA / "images" / image_name)), images / image_name)
    known = {n: camera_of(c) for n, c in cameras.items()}
    t0 = time.perf_counter()
    cams = sorted({n.split("_")[0] for n in gt})
    metrics, scales = [], []
    for instant in INSTANTS:
        names = [f"{c}_{instant}.jpg" for c in cams]
        priors = work / instant / "priors"
        if priors.exists():
            shutil.rmtree(priors)  # new photos, new priors
        m, _ = run_instant(data, names, known, gt, work / instant, priors)
        metrics.append(m)
        scales.append(_scale(work / instant / "sparse", gt))
        logger.info("%s %s: AUC@15 %.1f", name, instant, m.auc["15"])
    out = pooled(metrics)
    out["per_instant"] = [round(m.auc["15"], 1) for m in metrics]
    out["scale"] = scales
    stored = cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION  # as COLMAP reads
    h, w = cv2.imread(str(images / names[0]), stored).shape[:2]
    out["size"] = [w, h]
    out["seconds"] = time.perf_counter() - t0
    return out


def _scale(sparse: Path, gt: dict[str, np.ndarray]) -> dict:
    """The metric scale `map` wrote with its model (``sparse/0``): the model's
    camera distances over the calibration's (``ratio``; arbitrary where `map`
    kept COLMAP's scale) and the uncertainty it reported (None: no scale)."""
    rec = _largest_model(sparse)
    pred = {} if rec is None else poses_by_name(rec)
    scale = read_metric_scale(sparse / "0") if rec is not None else None
    return {
        "ratio": camera_distance_ratio(pred, gt),
        "uncertainty": None if scale is None else scale.uncertainty,
    }


def _scale_cells(scales: list[dict]) -> tuple[str, str]:
    """(per instant ratios, truth within one / two uncertainties) for the table."""
    if not scales or any(s["uncertainty"] is None for s in scales):
        return "none (scale arbitrary)", "-"
    ratios = [s["ratio"] for s in scales]
    z = [abs(np.log(s["ratio"])) / s["uncertainty"] for s in scales]
    return (
        " ".join(f"{r:.3f}" for r in ratios),
        f"{sum(x <= 1 for x in z)} / {sum(x <= 2 for x in z)} of {len(z)}",
    )


def table(results: dict) -> str:
    lines = [
        "| photos | size | registered | AUC@15 | AUC@30 | AUC@45 | median pair "
        "error (deg) | per instant AUC@15 | camera distances / calibration, "
        "per instant | truth within 1 / 2 scale uncertainties |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, r in results.items():
        a = r["auc"]
        ratios, within = _scale_cells(r.get("scale", []))
        lines.append(
            f"| {name} | {r['size'][0]} x {r['size'][1]} | {r['registered']}/"
            f"{r['images']} | {a['15']:.1f} | {a['30']:.1f} | {a['45']:.1f} | "
            f"{r['median_error_deg']:.2f} | "
            f"{' '.join(f'{x:.0f}' for x in r['per_instant'])} | {ratios} | "
            f"{within} |"
        )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS))
    parser.add_argument("--no-docs", action="store_true")
    args = parser.parse_args()
    setup_logging()
    t0 = time.perf_counter()
    results = {name: run_variant(name) for name in args.variants}
    seconds = time.perf_counter() - t0
    info = machine()
    write_json(
        "robustness.json", {"machine": info, "seconds": seconds, "results": results}
    )
    body = table(results)
    print(body)
    if args.no_docs:
        return
    replace_section(
        DOCS / "results.md",
        "robustness",
        "## Real photos in other forms: sizes, crops, EXIF, grey, no intrinsics\n\n"
        + body
        + "\n\npose2sim_single's 20 photos, each instant mapped on its own as in "
        '"Real photos, the user\'s path" (the same harness, new priors for every '
        "variant), pairs pooled over the five instants. half / quarter: resized, "
        "intrinsics scaled; top60: the top 60 % of each frame, the people's feet "
        'cut; exif6: the same JPEG bytes tagged "rotate 90" (EXIF orientation '
        "6); jpeg95: decoded and saved again at quality 95; grey: single-channel "
        "JPEGs; guessed: the original photos in a database made without their "
        "intrinsics (COLMAP's guess, f = 1.2 times the larger side: 2304 px "
        "against the calibration's 1674-1682). Camera distances / calibration: "
        "the median over camera pairs of the model's distance between two cameras "
        "over the calibration's, each instant's model at the metric scale `map` "
        "gave it from the people; truth within: instants whose |log ratio| is at "
        "most one and two of the uncertainty `map` reported with the scale. "
        f"Measured at commit {info['commit']} by `.venv/bin/python "
        f"bench/robustness.py` ({seconds / 60:.0f} min); raw numbers in "
        "`bench/out/robustness.json`.",
    )


if __name__ == "__main__":
    main()
