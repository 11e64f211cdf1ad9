"""`colmap-vc frames`: synchronized frames of static cameras, where people moved."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from colmap_vc import cli
from colmap_vc.frames import extract_frames, farthest_instants
from colmap_vc.static_cameras import parse_static_cameras


def _video(path: Path, positions: list[int], offset: int, shade: int) -> None:
    """A static grey room with a white square (a 'person') at x = positions[f -
    offset] in frame f (frames before the offset: the square at its first place)."""
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, (96, 64))
    assert writer.isOpened()
    for f in range(len(positions) + offset):
        img = np.full((64, 96, 3), shade, np.uint8)
        x = positions[max(0, f - offset)]
        img[20:44, x : x + 12] = 255
        writer.write(img)
    writer.release()


def test_farthest_instants_skip_repeats() -> None:
    d = np.array([[0.0], [0.0], [0.0], [1.0], [1.0], [5.0]])
    # The row farthest from the mean first, then the farthest from those chosen.
    assert farthest_instants(d, 3).tolist() == [5, 0, 3]
    assert farthest_instants(d, 10).tolist() == [5, 0, 3]  # the rest repeat
    assert farthest_instants(d, 2).tolist() == [5, 0]  # a prefix of the longer run


def test_frames_are_synchronized_and_diverse(tmp_path: Path) -> None:
    # The 'person' stands still for 20 frames, then walks right.
    positions = [4] * 20 + [4 + 3 * k for k in range(25)]
    _video(tmp_path / "camA.avi", positions, offset=0, shade=90)
    _video(tmp_path / "camB.avi", positions, offset=3, shade=140)
    summary = extract_frames(
        [tmp_path / "camA.avi", tmp_path / "camB.avi"],
        tmp_path / "images",
        offsets=[0, 3],
        num_instants=3,
        step=1,
    )
    assert len(summary.instants) == 3 and len(summary.written) == 6
    # at most one instant from the 20 identical standing frames
    assert (summary.instants < 20).sum() <= 1
    names = sorted(p.name for p in (tmp_path / "images").iterdir())
    assert names == sorted(summary.written)
    static = parse_static_cameras(summary.static_cameras, names)
    assert set(static.camera_of.values()) == {"camA", "camB"}
    assert len(set(static.instant_of.values())) == 3  # instants agree across cameras
    for r in summary.instants:  # the same instant: the square at the same place
        a = cv2.imread(str(tmp_path / "images" / f"camA_f{r:06d}.jpg"), 0)
        b = cv2.imread(str(tmp_path / "images" / f"camB_f{r:06d}.jpg"), 0)
        xa = np.flatnonzero(a[32] > 220).mean()
        xb = np.flatnonzero(b[32] > 220).mean()
        assert abs(xa - xb) < 2


def test_frames_cli_errors(tmp_path: Path) -> None:
    _video(tmp_path / "a.avi", [4] * 10, 0, 90)
    out = str(tmp_path / "o")
    assert (
        cli.main(
            [
                "frames",
                str(tmp_path / "a.avi"),
                str(tmp_path / "missing.avi"),
                "--output",
                out,
            ]
        )
        == 1
    )
    assert (
        cli.main(
            ["frames", str(tmp_path / "a.avi"), "--output", out, "--offsets", "1", "2"]
        )
        == 1
    )
    with pytest.raises(ValueError, match="share no instant"):
        extract_frames([tmp_path / "a.avi"], tmp_path / "o2", offsets=[50])
