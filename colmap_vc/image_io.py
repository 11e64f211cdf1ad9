"""Reading images as COLMAP sees them: the pixels as stored.

A phone photo often carries an EXIF orientation tag. COLMAP's feature extraction
and the bundled pose estimator read the stored pixels and ignore it; OpenCV's
``imread`` turns the image by it unless told not to. An image read turned has
its width and height exchanged against its camera, and its vertical lines
horizontal: the gravity step then measured an up 90 deg off from the same pixels
(a 1088 x 1920 frame tagged 6: AUC@15 90.0 -> 77.3). Every stage reads images
through :func:`read_image`.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np


def read_image(path: Path | str, *, grey: bool = False) -> np.ndarray | None:
    """The image's stored pixels (BGR, or grey), EXIF orientation ignored; None
    when it cannot be read."""
    flags = cv2.IMREAD_GRAYSCALE if grey else cv2.IMREAD_COLOR
    return cv2.imread(str(path), flags | cv2.IMREAD_IGNORE_ORIENTATION)
