"""Synchronized frames from static cameras' videos, at instants where people moved.

`colmap-vc frames VIDEO... --output IMAGES [--offsets ...] [--instants N]`: the
videos of static cameras, frame ``f`` of video ``k`` showing the same instant as frame
``f - offsets[k]`` of the first (the user's synchronisation, in frames). Instants are
chosen where the scene differs most from the instants already chosen (farthest-point
sampling): near-identical frames add nothing to the camera poses, different poses of
the people do. The descriptor of an instant is, per camera, a small grey thumbnail
minus that camera's median thumbnail over the video (the static background cancels,
the people remain). Frames are written as ``<video stem>_f<instant>.jpg``, the instant
being the frame index in the first video, so ``--static-cameras '(.+)_f\\d+'`` finds
the cameras and the instants agree across them.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .structs import FloatArray, IndexArray

logger = logging.getLogger(__name__)

THUMB = (48, 27)  # width, height of the descriptor thumbnails


@dataclass(frozen=True, kw_only=True, slots=True)
class FramesSummary:
    """What `colmap-vc frames` wrote."""

    output_dir: Path
    instants: IndexArray  # (N,) frame index of the first video at each instant, in
    # the order chosen (the first n: the n instants `--instants n` would choose)
    written: tuple[str, ...]  # image names
    static_cameras: str  # the expression that names the cameras


def _thumbnails(path: Path, step: int) -> tuple[FloatArray, int]:
    """Grey thumbnails (T, h*w) of every ``step``-th frame, and the frame count."""
    import cv2

    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        raise FileNotFoundError(f"cannot open video {path}")
    thumbs, index = [], 0
    while True:
        ok = cap.grab()
        if not ok:
            break
        if index % step == 0:
            _, frame = cap.retrieve()
            grey = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
            small = cv2.resize(grey, THUMB, interpolation=cv2.INTER_AREA)
            thumbs.append(small.astype(np.float64).ravel() / 255.0)
        index += 1
    cap.release()
    if not thumbs:
        raise ValueError(f"video {path} has no readable frame")
    return np.stack(thumbs), index


def farthest_instants(descriptors: FloatArray, num: int) -> IndexArray:
    """Indices of ``num`` rows chosen by farthest-point sampling (the first: the row
    farthest from the mean), deterministic, in the order chosen: the first ``n`` of
    them are the ``n`` rows it would choose."""
    num = min(num, len(descriptors))
    d_mean = np.linalg.norm(descriptors - descriptors.mean(axis=0), axis=1)
    chosen = [int(np.argmax(d_mean))]
    dist = np.linalg.norm(descriptors - descriptors[chosen[0]], axis=1)
    while len(chosen) < num:
        nxt = int(np.argmax(dist))
        if dist[nxt] <= 0:
            break  # the rest repeat chosen instants exactly
        chosen.append(nxt)
        dist = np.minimum(dist, np.linalg.norm(descriptors - descriptors[nxt], axis=1))
    return np.array(chosen, dtype=np.int64)


def extract_frames(
    videos: Sequence[Path],
    output_dir: Path,
    offsets: Sequence[int] | None = None,
    num_instants: int = 10,
    step: int = 5,
) -> FramesSummary:
    """Write ``num_instants`` synchronized frames of every video (module doc).

    Args:
        videos: one video per static camera.
        output_dir: image folder to write (created).
        offsets: per video, its frame index minus the first video's at one instant
            (default 0s).
        num_instants: instants to choose.
        step: candidate instants every ``step`` frames of the first video.

    Raises:
        FileNotFoundError: a video is missing or unreadable.
        ValueError: offsets do not match the videos, or the videos share no instant.
    """
    import cv2

    videos = [Path(v) for v in videos]
    offsets = list(offsets) if offsets else [0] * len(videos)
    if len(offsets) != len(videos):
        raise ValueError(f"{len(offsets)} offsets for {len(videos)} videos")
    stems = [v.stem for v in videos]
    if len(set(stems)) != len(stems):
        raise ValueError(f"two videos share a name stem: {stems}")
    for v in videos:
        if not v.is_file():
            raise FileNotFoundError(f"video {v} not found")
    # Frames of video k at reference frames r: r + offsets[k]; all must exist.
    thumbs, counts = zip(*(_thumbnails(v, 1) for v in videos), strict=True)
    first = max(0, *(-o for o in offsets))
    last = min(c - o for c, o in zip(counts, offsets, strict=True))
    ref = np.arange(first, last, step)
    if len(ref) == 0:
        raise ValueError(f"the videos share no instant with offsets {offsets}")
    parts = []
    for t, o in zip(thumbs, offsets, strict=True):  # loop over cameras
        people = t[ref + o] - np.median(t, axis=0)  # static background cancels
        parts.append(people)
    chosen = ref[farthest_instants(np.concatenate(parts, axis=1), num_instants)]
    output_dir = Path(output_dir)
    output_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for v, o, stem in zip(videos, offsets, stems, strict=True):  # loop over videos
        cap = cv2.VideoCapture(str(v))
        for r in chosen:
            cap.set(cv2.CAP_PROP_POS_FRAMES, int(r + o))
            ok, frame = cap.read()
            if not ok:
                raise ValueError(f"cannot read frame {r + o} of {v}")
            name = f"{stem}_f{int(r):06d}.jpg"  # the instant, as the first video
            cv2.imwrite(str(output_dir / name), frame, [cv2.IMWRITE_JPEG_QUALITY, 95])
            written.append(name)
        cap.release()
    logger.info(
        "frames: %d instants of %d videos -> %s (reference frames %s)",
        len(chosen),
        len(videos),
        output_dir,
        ", ".join(map(str, sorted(chosen.tolist()))),
    )
    return FramesSummary(
        output_dir=output_dir,
        instants=chosen,
        written=tuple(written),
        static_cameras=r"(.+)_f\d+\.jpg$",
    )
