"""Frozen dataclasses passed between stages, and the array aliases they use.

Conventions (see docs/ and ../shared/STYLE.md):
- pixels follow COLMAP: the centre of the top-left pixel is (0.5, 0.5);
- 3D points in a camera frame use OpenCV axes (x right, y down, z forward), metres;
- transforms are named ``b_from_a`` and stored as (3, 4) float64 ``[R | t]``.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]
IndexArray = npt.NDArray[np.int64]
BoolArray = npt.NDArray[np.bool_]


def _check_shape(name: str, array: np.ndarray, shape: tuple[int | None, ...]) -> None:
    """Raise ValueError unless ``array`` has ``shape`` (None matches any size)."""
    ok = array.ndim == len(shape) and all(
        want is None or have == want
        for have, want in zip(array.shape, shape, strict=True)
    )
    if not ok:
        raise ValueError(f"{name} has shape {array.shape}, expected {shape}")


class HitKind(enum.IntEnum):
    """How the two rays of a virtual correspondence meet (stored in the database)."""

    COVISIBLE = 0  # both pixels see the same surface point (a classic match)
    VIRTUAL = 1  # the point is visible in one image only (e.g. a back behind a chest)
    KEYPOINT = 2  # the rays meet at an invisible point (a joint centre)


@dataclass(frozen=True, kw_only=True, slots=True)
class SurfaceMap:
    """Dense pixel -> body-surface map of one person in one image (DensePose-like).

    A surface point is a face of the person's mesh and barycentric coordinates in it;
    all meshes of one template share the faces, so (face_idx, bary) names the same
    point of the body in every image.
    """

    xy_img: FloatArray  # (N, 2) float64 pixel centres, COLMAP convention
    face_idx: IndexArray  # (N,) int64
    bary: FloatArray  # (N, 3) float64, rows sum to 1

    def __post_init__(self) -> None:
        _check_shape("xy_img", self.xy_img, (None, 2))
        n = self.xy_img.shape[0]
        _check_shape("face_idx", self.face_idx, (n,))
        _check_shape("bary", self.bary, (n, 3))

    def __len__(self) -> int:
        return int(self.xy_img.shape[0])


@dataclass(frozen=True, kw_only=True, slots=True)
class PersonPrior:
    """The predicted human prior of one person in one image."""

    vertices_cam: FloatArray  # (V, 3) float64, metres, this camera's frame
    faces: IndexArray  # (F, 3) int64
    template: str | None = None  # named template shared across images, or None
    person_id: int | None = None  # identity across images, when known
    confidence: float = 1.0
    surface_map: SurfaceMap | None = None
    keypoints_xy: FloatArray | None = None  # (K, 2) float64 pixels, joint centres
    keypoints_cam: FloatArray | None = None  # (K, 3) float64, joint centres, metres
    keypoints_valid: BoolArray | None = None  # (K,) bool
    mask: BoolArray | None = None  # (H, W) bool silhouette
    appearance: FloatArray | None = None  # (R, 4) CIELAB colour + pixel weight per
    # body region (torso, upper arms, thighs, shins); weight 0 where unseen

    def __post_init__(self) -> None:
        _check_shape("vertices_cam", self.vertices_cam, (None, 3))
        _check_shape("faces", self.faces, (None, 3))
        if self.keypoints_xy is not None:
            k = self.keypoints_xy.shape[0]
            _check_shape("keypoints_xy", self.keypoints_xy, (k, 2))
            if self.keypoints_cam is not None:
                _check_shape("keypoints_cam", self.keypoints_cam, (k, 3))
            if self.keypoints_valid is not None:
                _check_shape("keypoints_valid", self.keypoints_valid, (k,))


@dataclass(frozen=True, kw_only=True, slots=True)
class ImagePrior:
    """All people predicted in one image."""

    image_name: str
    persons: tuple[PersonPrior, ...]
    focal_px: float | None = None
    """Mean focal length, pixels, of the camera the priors were made with (the
    meshes' depth scales with it); None: not recorded."""


@dataclass(frozen=True, kw_only=True, slots=True)
class ScenePriors:
    """Priors of a whole scene, keyed by image name (COLMAP's ``Image.name``)."""

    images: dict[str, ImagePrior] = field(default_factory=dict)
    version: int = 1


@dataclass(frozen=True, kw_only=True, slots=True)
class VcKeypoints:
    """The VC keypoints of one image, before they are appended to its keypoints.

    One row per (person, track) the image takes part in. ``track_id`` is the template
    surface sample (or keypoint) index, so the same id in two images is one 3D point.
    """

    image_id: int
    xy_img: FloatArray  # (K, 2) float64, COLMAP pixel convention
    person_id: IndexArray  # (K,) int64
    track_id: IndexArray  # (K,) int64

    def __post_init__(self) -> None:
        _check_shape("xy_img", self.xy_img, (None, 2))
        k = self.xy_img.shape[0]
        _check_shape("person_id", self.person_id, (k,))
        _check_shape("track_id", self.track_id, (k,))

    def __len__(self) -> int:
        return int(self.xy_img.shape[0])


@dataclass(frozen=True, kw_only=True, slots=True)
class PairGeometry:
    """A verified two-view geometry, in COLMAP's terms."""

    config: int  # pycolmap.TwoViewGeometryConfiguration value
    E: FloatArray  # (3, 3)
    F: FloatArray  # (3, 3)
    H: FloatArray  # (3, 3)
    cam2_from_cam1: FloatArray  # (3, 4) [R | t], unit-norm t


@dataclass(frozen=True, kw_only=True, slots=True)
class PairVcMatches:
    """Virtual correspondences of one image pair (image_id1 < image_id2).

    ``idx1``/``idx2`` index the rows of each image's :class:`VcKeypoints`.
    ``points1_cam`` is X1 (the first hit of ray 1) in camera 1, ``points2_cam`` is X2
    (the first hit of ray 2) in camera 2; X2 = X1 + a (X1 - o1) + b (o2 - o1) in world.
    """

    image_id1: int
    image_id2: int
    idx1: IndexArray  # (M,) int64
    idx2: IndexArray  # (M,) int64
    person_id: IndexArray  # (M,) int64
    kind: IndexArray  # (M,) int64, HitKind values
    points1_cam: FloatArray  # (M, 3) float64
    points2_cam: FloatArray  # (M, 3) float64
    a: FloatArray  # (M,) float64
    b: FloatArray  # (M,) float64
    is_inlier: BoolArray  # (M,) bool, after geometric verification

    def __post_init__(self) -> None:
        if self.image_id1 >= self.image_id2:
            raise ValueError(
                f"pair ({self.image_id1}, {self.image_id2}) must have image_id1 < "
                "image_id2"
            )
        _check_shape("idx1", self.idx1, (None,))
        m = self.idx1.shape[0]
        for name in ("idx2", "person_id", "kind", "a", "b", "is_inlier"):
            _check_shape(name, getattr(self, name), (m,))
        _check_shape("points1_cam", self.points1_cam, (m, 3))
        _check_shape("points2_cam", self.points2_cam, (m, 3))

    def __len__(self) -> int:
        return int(self.idx1.shape[0])
