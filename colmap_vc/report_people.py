"""The report's "people" section: who is who across the views.

Every image with its VC keypoints coloured by the identity `augment`'s association
gave their person (one colour per identity in every view; grey: a person the
association left out), so a user sees at a glance whether the people were linked
right.
"""

from __future__ import annotations

import numpy as np

from colmap_vc.structs import FloatArray, IndexArray

# BGR, distinct for the first eight identities (Okabe-Ito), then cycling.
PALETTE = np.array(
    [
        [0, 159, 230],
        [178, 114, 0],
        [115, 158, 0],
        [66, 228, 240],
        [0, 94, 213],
        [167, 121, 204],
        [233, 180, 86],
        [0, 0, 0],
    ],
    dtype=np.uint8,
)
GREY = np.array([150, 150, 150], dtype=np.uint8)


def identity_colors(identity: IndexArray) -> np.ndarray:
    """(N, 3) uint8 BGR colour per identity (-1: grey)."""
    out = np.tile(GREY, (len(identity), 1))
    known = identity >= 0
    out[known] = PALETTE[identity[known] % len(PALETTE)]
    return out


def keypoint_identities(
    identity: dict[tuple[int, int], int], image_id: int, person_id: IndexArray
) -> IndexArray:
    """(N,) identity of each VC keypoint of an image from its person (-1: none);
    ``identity``: (image_id, person_id) -> identity (``person_identities``)."""
    lookup = {p: i for (img, p), i in identity.items() if img == image_id}
    return np.array([lookup.get(int(p), -1) for p in np.unique(person_id)])[
        np.searchsorted(np.unique(person_id), person_id)
    ]


def draw_people(
    image_bgr: np.ndarray,
    xy_img: FloatArray,
    identity: IndexArray,
    height: int,
    max_dots: int = 600,
) -> np.ndarray:
    """The image scaled to ``height`` with the keypoints as dots, by identity."""
    import cv2

    scale = height / image_bgr.shape[0]
    width = max(1, round(image_bgr.shape[1] * scale))
    canvas = cv2.resize(image_bgr, (width, height), interpolation=cv2.INTER_AREA)
    if len(xy_img) > max_dots:  # an even subset, deterministic
        keep = np.linspace(0, len(xy_img) - 1, max_dots).round().astype(np.int64)
        xy_img, identity = xy_img[keep], identity[keep]
    pts = np.round((xy_img - 0.5) * scale).astype(np.int32)  # COLMAP -> OpenCV
    colors = identity_colors(identity)
    radius = max(2, height // 160)
    for (x, y), c in zip(pts, colors, strict=True):  # drawing: one call per dot
        cv2.circle(canvas, (int(x), int(y)), radius, tuple(int(v) for v in c), -1)
    return canvas
