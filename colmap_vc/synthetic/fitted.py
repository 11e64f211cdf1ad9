"""The bundled estimator's priors on the synthetic world: noisy landmarks, then its fit.

On real photos the bundled estimator (:mod:`colmap_vc.estimators`) detects
BlazePose's landmarks, fits the Anny body to them and ray-casts the person's mask
on the fitted mesh for the dense surface map. Its map therefore repeats the
landmarks' errors: on pose2sim a surface sample's error correlates 0.74 with
the keypoint errors around it, against 0.26 for the DensePose-like map of the
``realistic`` level, whose sliding is drawn independently of the keypoints, and
0.49 for this level (``bench/landmark_noise.py``; docs/synthetic.md, "The fitted
level"), whose surface samples spread as pose2sim's do against its keypoints
(1.08 times them; pose2sim 0.97-1.12). This level runs the same fit on the
synthetic people:

- the exact BlazePose landmarks of the true body (:func:`landmarks_from_mesh`);
  with ``turn_prob`` the detector takes a back view for a front view (2 of 20
  person views on pose2sim_single): the same pixels labelled left for right, 3D
  points of a body facing the camera;
- 2D noise per landmark, Gaussian with the spread measured on pose2sim against
  its calibration (:data:`LANDMARK_SIGMA`, a fraction of the person's height in
  the image, per coordinate), plus one offset shared by all landmarks of the
  person in the image (:data:`SHARED_SIGMA`);
- 3D ("world") landmarks with the noise measured on pose2sim per landmark and
  camera axis (:data:`LANDMARK_SIGMA_3D`, a fraction of the landmarks' extent),
  against the landmarks its calibrated cameras triangulate, following the 2D
  error as measured there (:data:`CORRELATION_2D_3D`), and scaled by the
  person's size error, shared by its views (``NoiseModel.person_size_error``:
  MediaPipe's world landmarks are in metres, but of the body it takes the
  person for);
- :func:`~colmap_vc.estimators.fit.fit_body`, then
  :func:`~colmap_vc.estimators.prior.prior_from_fit` with the predicted mask.

A fit that fails (too few landmarks in the image) reports no person, as the
estimator does.
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

import numpy as np
import pycolmap

from ..structs import PersonPrior

if TYPE_CHECKING:
    from ..estimators.body import BodyLandmarks, FitTemplate
    from .bodies import BodyModel
    from .noise import PersonView

LANDMARK_SIGMA: dict[str, float] = {
    "nose": 0.011,
    "left_ear": 0.011,
    "right_ear": 0.012,
    "left_shoulder": 0.012,
    "right_shoulder": 0.011,
    "left_elbow": 0.018,
    "right_elbow": 0.024,
    "left_wrist": 0.022,
    "right_wrist": 0.022,
    "left_hip": 0.013,
    "right_hip": 0.017,
    "left_knee": 0.015,
    "right_knee": 0.014,
    "left_ankle": 0.023,
    "right_ankle": 0.019,
    "left_heel": 0.024,
    "right_heel": 0.026,
    "left_foot_index": 0.03,
    "right_foot_index": 0.025,
}
"""Spread per coordinate of MediaPipe's landmarks on pose2sim (single and multi,
73 person views; the composited avatar left out), as a fraction of the person's
landmark height in the image (its valid landmarks' extent in y), against the
points the calibrated cameras triangulate, corrected for the fit of a point to
its own views, each view's median offset taken out (``bench/landmark_noise.py``,
docs/synthetic.md)."""

LANDMARK_SIGMA_3D: dict[str, tuple[float, float, float]] = {
    "left_shoulder": (0.032, 0.051, 0.093),
    "right_shoulder": (0.032, 0.038, 0.083),
    "left_elbow": (0.055, 0.051, 0.092),
    "right_elbow": (0.050, 0.039, 0.122),
    "left_wrist": (0.060, 0.063, 0.177),
    "right_wrist": (0.058, 0.050, 0.129),
    "left_hip": (0.028, 0.013, 0.022),
    "right_hip": (0.028, 0.013, 0.022),
    "left_knee": (0.043, 0.050, 0.067),
    "right_knee": (0.043, 0.035, 0.096),
    "left_ankle": (0.053, 0.072, 0.145),
    "right_ankle": (0.063, 0.072, 0.168),
    "nose": (0.041, 0.059, 0.105),
    "left_ear": (0.045, 0.053, 0.109),
    "right_ear": (0.039, 0.051, 0.103),
    "left_heel": (0.059, 0.068, 0.126),
    "right_heel": (0.060, 0.074, 0.176),
    "left_foot_index": (0.067, 0.065, 0.135),
    "right_foot_index": (0.077, 0.058, 0.165),
}
"""Spread of MediaPipe's 3D ("world") landmarks on pose2sim per camera axis (x,
y, depth), as a fraction of the view's landmark extent, against the landmarks the
calibrated cameras triangulate, with the hips' midpoint as origin (56 person
views; ``bench/landmark_noise.py``, docs/synthetic.md). Three to eight times the
2D fractions, and largest in depth: one rotation per view explains little of it
(all landmarks: 4.2 / 4.8 / 10.4%, 3.8 / 4.6 / 8.8% after it)."""

CORRELATION_2D_3D: tuple[float, float] = (0.47, 0.29)
"""Correlation of a landmark's 3D error across the image (x, y) with its 2D error
on pose2sim, each view's median offset taken out (``bench/landmark_noise.py``):
MediaPipe's two outputs come from one network and err together."""

SHARED_SIGMA = 0.0092
"""Spread per coordinate of the offset shared by one person's landmarks in one
image, as a fraction of the landmark height: the per-view median offset on
pose2sim spreads 1.05 %, of which independent landmark errors explain 0.51 %
(``bench/landmark_noise.py``)."""

_TEMPLATE: list[tuple[BodyModel, FitTemplate]] = []
"""The fit's template of the last body model asked for (a scene uses one)."""


def _template(bodies: BodyModel) -> FitTemplate:
    from ..estimators.body import load_template

    if not _TEMPLATE or _TEMPLATE[0][0] is not bodies:
        _TEMPLATE[:] = [(bodies, load_template(bodies))]
    return _TEMPLATE[0][1]


def _turned(landmarks: BodyLandmarks) -> BodyLandmarks:
    """The landmarks a detector reports for a person it takes for facing the
    camera while seen from the back: the same pixels with left and right
    exchanged, and 3D points of a body facing the camera (depth mirrored about
    the hips)."""
    from ..estimators.body import BodyLandmarks

    out = landmarks.relabelled()
    p3 = out.points_3d.copy()
    p3[:, 2] *= -1.0  # hip-centred, camera orientation: depth about the hips
    return BodyLandmarks(xy_img=out.xy_img, points_3d=p3, visibility=out.visibility)


def noisy_landmarks(
    exact: BodyLandmarks,
    *,
    fitted_idx: np.ndarray,
    noise_scale: float,
    rng: np.random.Generator,
) -> BodyLandmarks:
    """``exact`` with the measured noise (module doc) times ``noise_scale``: per
    landmark, and one offset shared by all, as fractions of the landmark height
    in the image (the extent in y of the ``fitted_idx`` landmarks); 3D points per
    landmark and camera axis as fractions of the ``fitted_idx`` landmarks' 3D
    extent (:data:`LANDMARK_SIGMA_3D`), across the image correlated with the
    landmark's own 2D error (:data:`CORRELATION_2D_3D`)."""
    from ..estimators.body import NUM_LANDMARKS, BodyLandmarks, landmark_index

    height_px = float(np.ptp(exact.xy_img[fitted_idx, 1]))
    extent_m = float(np.ptp(exact.points_3d[fitted_idx], axis=0).max())
    sigma = np.zeros(NUM_LANDMARKS)
    sigma_3d = np.zeros((NUM_LANDMARKS, 3))
    for name, s in LANDMARK_SIGMA.items():  # loop over 19 names
        sigma[landmark_index(name)] = noise_scale * s
        sigma_3d[landmark_index(name)] = noise_scale * np.asarray(
            LANDMARK_SIGMA_3D[name]
        )
    shared = rng.normal(0.0, noise_scale * SHARED_SIGMA * height_px, 2)
    z2 = rng.normal(size=(NUM_LANDMARKS, 2))
    xy = exact.xy_img + shared + z2 * (sigma[:, None] * height_px)
    # Across the image the 3D error follows the landmark's own 2D error.
    rho = np.array([*CORRELATION_2D_3D, 0.0])
    z3 = (
        rng.normal(size=(NUM_LANDMARKS, 3)) * np.sqrt(1.0 - rho**2)
        + rho * np.c_[z2, np.zeros(NUM_LANDMARKS)]
    )
    p3 = exact.points_3d + z3 * sigma_3d * extent_m
    return BodyLandmarks(xy_img=xy, points_3d=p3, visibility=exact.visibility)


def fitted_person(
    bodies: BodyModel,
    view: PersonView,
    camera: pycolmap.Camera,
    *,
    noise_scale: float,
    turn_prob: float,
    mask: np.ndarray,
    confidence: float,
    rng: np.random.Generator,
    size_error: float = 0.0,
) -> PersonPrior | None:
    """The bundled estimator's prior of one person (module doc); None when its
    fit fails. ``noise_scale`` multiplies the measured landmark noise;
    ``size_error`` scales the person's 3D landmarks about the hips (the size
    error shared by its views, ``noise.person_size_error``)."""
    from ..estimators import body, fit, prior

    template = _template(bodies)
    exact = body.landmarks_from_mesh(
        template, view.body_vertices, view.cam_from_body, camera
    )
    if size_error:
        exact = dataclasses.replace(
            exact, points_3d=exact.points_3d * (1.0 + size_error)
        )
    if turn_prob > 0 and rng.random() < turn_prob:
        exact = _turned(exact)
    landmarks = noisy_landmarks(
        exact,
        fitted_idx=template.landmark_idx,
        noise_scale=noise_scale,
        rng=rng,
    )
    try:
        fitted = fit.fit_body(landmarks, camera, template)
    except ValueError:
        return None
    person, _ = prior.prior_from_fit(
        fitted, camera, mask, template=template, confidence=confidence
    )
    return person
