"""Pictures for people: contact sheets of scenes (more figures join as stages land)."""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from .image_io import read_image

logger = logging.getLogger(__name__)


def contact_sheet(
    image_paths: Sequence[Path],
    out_path: Path,
    *,
    columns: int = 4,
    tile_width: int = 320,
    labels: Sequence[str] | None = None,
    title: str | None = None,
) -> Path:
    """Tile images into one JPEG/PNG with a label on each tile."""
    if not image_paths:
        raise ValueError("contact_sheet needs at least one image")
    tiles = []
    for i, path in enumerate(image_paths):
        image = read_image(path)
        if image is None:
            raise FileNotFoundError(f"cannot read image {path}")
        h = round(image.shape[0] * tile_width / image.shape[1])
        tile = cv2.resize(image, (tile_width, h), interpolation=cv2.INTER_AREA)
        label = labels[i] if labels is not None else Path(path).name
        cv2.putText(
            tile,
            label,
            (6, 18),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.5,
            (0, 0, 0),
            3,
            cv2.LINE_AA,
        )
        cv2.putText(
            tile,
            label,
            (6, 18),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.5,
            (255, 255, 255),
            1,
            cv2.LINE_AA,
        )
        tiles.append(tile)
    h = max(t.shape[0] for t in tiles)
    rows = math.ceil(len(tiles) / columns)
    sheet = np.full((rows * h, columns * tile_width, 3), 255, np.uint8)
    for i, tile in enumerate(tiles):
        r, c = divmod(i, columns)
        sheet[r * h : r * h + tile.shape[0], c * tile_width : (c + 1) * tile_width] = (
            tile
        )
    if title:
        bar = np.full((32, sheet.shape[1], 3), 255, np.uint8)
        cv2.putText(
            bar,
            title,
            (8, 22),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.6,
            (0, 0, 0),
            1,
            cv2.LINE_AA,
        )
        sheet = np.concatenate([bar, sheet])
    out_path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(out_path), sheet)
    logger.info("contact sheet written to %s", out_path)
    return out_path
