"""What a person looks like: median clothing colour of four body regions.

People are anonymous across cameras; their clothes are the cue a human uses first
(the association in :mod:`colmap_vc.association` weighs it with the geometry). Per
person, four regions are cut from the 2D landmarks: the torso (shoulders-hips
quadrilateral), the upper arms, the thighs and the shins (limb segments as thick
lines). Each region's pixels inside the person's segmentation mask give a median
CIELAB colour (OpenCV's 8-bit Lab) and a weight (pixel count relative to the largest
region; 0 where the region is not seen). Medians are robust to a few background or
skin pixels at the region borders.
"""

from __future__ import annotations

import cv2
import numpy as np

from colmap_vc.structs import BoolArray, FloatArray

# BlazePose landmark indices.
_L_SHOULDER, _R_SHOULDER, _L_ELBOW, _R_ELBOW = 11, 12, 13, 14
_L_HIP, _R_HIP, _L_KNEE, _R_KNEE, _L_ANKLE, _R_ANKLE = 23, 24, 25, 26, 27, 28
REGIONS = ("torso", "upper_arms", "thighs", "shins")
_LIMBS = {
    "upper_arms": ((_L_SHOULDER, _L_ELBOW), (_R_SHOULDER, _R_ELBOW)),
    "thighs": ((_L_HIP, _L_KNEE), (_R_HIP, _R_KNEE)),
    "shins": ((_L_KNEE, _L_ANKLE), (_R_KNEE, _R_ANKLE)),
}
_LIMB_WIDTH = {"upper_arms": 0.25, "thighs": 0.35, "shins": 0.25}  # x torso height
NUM_LANDMARKS = 33
LANDMARK_INDEX: dict[str, int] = {
    f"{side}_{joint}": index
    for joint, (left, right) in {
        "shoulder": (_L_SHOULDER, _R_SHOULDER),
        "elbow": (_L_ELBOW, _R_ELBOW),
        "hip": (_L_HIP, _R_HIP),
        "knee": (_L_KNEE, _R_KNEE),
        "ankle": (_L_ANKLE, _R_ANKLE),
    }.items()
    for side, index in (("left", left), ("right", right))
}
"""BlazePose index of every landmark the regions use, by joint name."""


def describe_person(
    image_rgb: np.ndarray,
    landmarks_xy: FloatArray,
    visible: BoolArray,
    mask: BoolArray | None,
) -> FloatArray:
    """(4, 4) Lab colour + weight of torso, upper arms, thighs, shins.

    Args:
        image_rgb: (H, W, 3) uint8.
        landmarks_xy: (33, 2) BlazePose landmarks, pixels (COLMAP convention).
        visible: (33,) landmarks seen (visibility and inside the image).
        mask: (H, W) the person's segmentation, or None (regions used as they are).
    """
    h, w = image_rgb.shape[:2]
    out = np.zeros((len(REGIONS), 4))
    xy = landmarks_xy - 0.5  # COLMAP -> OpenCV pixel centres
    torso = (_L_SHOULDER, _R_SHOULDER, _R_HIP, _L_HIP)
    if not visible[list(torso)].all():
        return out
    shoulders = 0.5 * (xy[_L_SHOULDER] + xy[_R_SHOULDER])
    hips = 0.5 * (xy[_L_HIP] + xy[_R_HIP])
    torso_h = float(np.linalg.norm(shoulders - hips))
    if torso_h < 4.0:
        return out
    lab = cv2.cvtColor(image_rgb, cv2.COLOR_RGB2LAB)
    counts = np.zeros(len(REGIONS))
    for r, name in enumerate(REGIONS):
        region = np.zeros((h, w), dtype=np.uint8)
        if name == "torso":
            cv2.fillConvexPoly(region, np.round(xy[list(torso)]).astype(np.int32), 1)
        else:
            thickness = max(2, round(_LIMB_WIDTH[name] * torso_h))
            for a, b in _LIMBS[name]:
                if visible[a] and visible[b]:
                    pa = tuple(int(v) for v in np.round(xy[a]))
                    pb = tuple(int(v) for v in np.round(xy[b]))
                    cv2.line(region, pa, pb, 1, thickness)
        sel = region.astype(bool)
        if mask is not None:
            sel &= mask
        if sel.sum() < 20:
            continue
        out[r, :3] = np.median(lab[sel].astype(np.float64), axis=0)
        counts[r] = sel.sum()
    if counts.max() > 0:
        out[:, 3] = counts / counts.max()
    return out
