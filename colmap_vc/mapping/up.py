"""`map`'s gravity step: the cameras agree on "up", measured from the scene's verticals.

After the refinement, each registered camera's gravity is measured from its images'
vertical lines (:mod:`colmap_vc.gravity`; a static camera pools all its images),
and the model is bundle-adjusted once more with every camera's up tied to one world
up (:mod:`colmap_vc.gba.up`). The angles are weighed against the keypoints' pixel
noise, estimated from the model's own residuals with the error each person's
keypoints share in an image (:func:`keypoint_noise_px`; 12.6 px on pose2sim_single's
static cameras, 4.7 px for the keypoints' spread alone). Weighed against the spread
alone, the up directions moved those cameras half as far (median pair error 2.28
deg against 1.11, when the step came, commit ec3cd4f). The residuals miss what
the poses absorb, so the noise is at least what the cameras' tilts show against
their ups (:func:`absorbed_noise_px`: 31 px there). A camera whose own image
(its vertical lines and its people's up) contradicts the pose the people gave it
leaves the model (:func:`contradicted_cameras`). When the cameras' own people say
the adjustment turned them the wrong way (:mod:`.people_up`: lines that are
not vertical, a geodesic dome's edges, can agree with each other and with the
25-deg search cone), the model is put back as it was. What was measured and how
well each camera agrees with it afterwards goes to ``gravity.json`` beside the model.
"""

from __future__ import annotations

import json
import logging
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import pycolmap

from ..evaluation import poses_by_name
from ..gba.ceres import (
    PeopleNoise,
    ba_options,
    bundle_adjust_inplace,
    weighted_points,
)
from ..gba.noise import cluster_noise
from ..gba.up import UpPriors
from ..gravity import Gravity, GravityOptions, measure_gravity
from ..keypoint_tracks import (
    KeypointTracks,
    keypoint_tracks,
    observed_in_posed_images,
    subset,
    triangulate_tracks,
)
from .inputs import MapInputs
from .people_up import MAX_PEOPLE_Z, PeopleVerdict, people_ups, people_verdict

logger = logging.getLogger(__name__)

GRAVITY_FILE = "gravity.json"
"""Written next to the model: each camera's measured up, its standard error, the
vertical lines it rests on (pixels; a static camera's from all its images), how
far the final model's up is from it, and the cameras the step left out, why."""


@dataclass(frozen=True, kw_only=True, slots=True)
class GravityResult:
    """What the gravity step measured and did (written to ``gravity.json``)."""

    measured: dict[str, Gravity]  # image name (a static camera's representative)
    pixel_noise_px: float | None  # None: no keypoint tracks to weigh against
    residual_deg: dict[str, float]  # angle between measured and model up, after
    used: bool  # False: fewer than two cameras measured, the model is unchanged
    left_out: dict[str, float]  # image name -> its up's angle to the others' (deg)
    cameras_left_out: dict[str, str]  # image name -> why it left the model
    people: PeopleVerdict | None = None  # the people's ups on the step's turn
    rejected: str | None = None  # why the adjusted model was not kept


def keypoint_noise_px(
    rec: pycolmap.Reconstruction, tracks: KeypointTracks, min_sigma_px: float
) -> float | None:
    """What one keypoint residual is worth, pixels: the median over the model's
    keypoint observations of their noise with the error they share with their
    (image, person), sqrt(sigma^2 + N tau^2) (:mod:`colmap_vc.gba.noise`: a
    person's N keypoints in one image count as about one observation at their
    shared error, not N). ``tracks`` as the model holds them (the keypoint BA's
    camera check may have exchanged a person's left and right: read as labelled,
    that person's residuals are hundreds of pixels). None without keypoint tracks
    in registered images."""
    tracks = subset(tracks, observed_in_posed_images(rec, tracks))
    if tracks.num_tracks == 0:
        return None
    X, _ = triangulate_tracks(rec, tracks)
    per_obs = cluster_noise(rec, tracks, X).observation_sigma_px(min_sigma_px)
    ok = np.isfinite(per_obs)
    return float(np.median(per_obs[ok])) if ok.any() else None


def refine_with_gravity_inplace(
    rec: pycolmap.Reconstruction,
    inputs: MapInputs,
    image_dir: Path,
    people: PeopleNoise | None,
    tracks: KeypointTracks | None,
    options: GravityOptions,
    *,
    loss_scale_px: float,
    min_sigma_px: float,
    robust_sigmas: float,
) -> GravityResult:
    """Measure the registered cameras' gravity and bundle-adjust ``rec`` with it
    (``loss_scale_px``: the reprojections' Cauchy scale; ``min_sigma_px`` and
    ``robust_sigmas``: the keypoint noise's floor and the up residuals' Cauchy
    scale in standard errors, as the keypoint BA's options give them; ``tracks``:
    the keypoint tracks as the model holds them, None to make them from the
    database's records in ``inputs``)."""
    registered = {
        rec.image(i).name: i for i in rec.reg_image_ids() if rec.image(i).has_pose
    }
    groups = {
        name: (
            inputs.static.members(name)
            if inputs.static is not None
            and name in inputs.static.representative.values()
            else [name]
        )
        for name in registered
    }
    names = sorted({n for members in groups.values() for n in members})
    raw = inputs.image_priors  # static cameras: not the merged views
    persons = {
        n: raw.images[n].persons for n in names if raw is not None and n in raw.images
    }
    camera_of = dict(
        zip(inputs.views.image_names, inputs.views.camera_ids.tolist(), strict=True)
    )
    cameras = {n: inputs.views.cameras[camera_of[n]] for n in names}
    measured = measure_gravity(image_dir, groups, cameras, persons, options)
    every = measured
    measured, disagree = agreeing_ups(rec, registered, measured, options.max_hint_deg)
    contradicted = contradicted_cameras(
        rec, registered, every, measured, disagree, options.max_hint_deg
    )
    for name, reason in contradicted.items():
        logger.warning("gravity: %s %s", name, reason)
        rec.deregister_frame(rec.image(registered[name]).frame_id)
        del registered[name]
    if tracks is None:
        registered_ids = np.array(sorted(registered.values()), dtype=np.int64)
        tracks = keypoint_tracks(inputs.records, registered_ids)
    noise = keypoint_noise_px(rec, tracks, min_sigma_px)
    surface = (  # the covariance is the keypoints', repeated or not (at 1 px)
        None if people is None else people.without(tracks.image_id, tracks.point2D_idx)
    )
    absorbed = absorbed_noise_px(rec, registered, measured, loss_scale_px, surface)
    if noise is not None and absorbed is not None and absorbed > noise:
        logger.info(
            "gravity: the cameras' tilts disagree with their ups as if the keypoints "
            "were %.1f px off, not %.1f px: weighed at %.1f px",
            absorbed,
            noise,
            absorbed,
        )
        noise = absorbed
    keys = sorted(measured)
    used = len(keys) >= 2 and noise is not None
    turn: PeopleVerdict | None = None
    rejected: str | None = None
    if used:
        assert noise is not None
        up = UpPriors(
            image_id=np.array([registered[k] for k in keys], dtype=np.int64),
            up_cam=np.array([measured[k].up_cam for k in keys]),
            sigma_rad=np.array([measured[k].sigma_rad for k in keys]),
            pixel_noise_px=noise,
            robust_sigmas=robust_sigmas,
        )
        before = _Snapshot.of(rec)
        posed_before = poses_by_name(rec)
        bundle_adjust_inplace(rec, loss_scale_px, people, up)
        turn = people_verdict(
            posed_before, poses_by_name(rec), people_ups(persons, groups)
        )
        if turn is not None and turn.z > MAX_PEOPLE_Z:
            before.restore(rec)
            used = False
            rejected = (
                f"the ups turned the cameras by {turn.turn_deg:.1f} deg (rms over "
                f"{turn.num_cameras}) and their people's ups, independent of the "
                f"lines and of the model, say the turn is wrong (they spread "
                f"{turn.spread_after_deg:.1f} deg after it, "
                f"{turn.spread_before_deg:.1f} before; z = {turn.z:.1f} > "
                f"{MAX_PEOPLE_Z:g}): the lines are likely not vertical (a dome's or "
                f"a roof's edges), and the model is left as the people made it"
            )
            logger.warning("gravity: ups not used: %s", rejected)
    residual = _residuals_deg(rec, registered, measured)
    logger.info(
        "gravity: %d of %d cameras measured (keypoint noise %s px)%s; after: %s",
        len(keys),
        len(registered),
        "?" if noise is None else f"{noise:.1f}",
        "" if used else ": model unchanged",
        ", ".join(f"{k} {v:.2f} deg" for k, v in residual.items()),
    )
    return GravityResult(
        measured=measured,
        pixel_noise_px=noise,
        residual_deg=residual,
        used=used,
        left_out=disagree,
        cameras_left_out=contradicted,
        people=turn,
        rejected=rejected,
    )


@dataclass(frozen=True, kw_only=True, slots=True)
class _Snapshot:
    """The poses and points of a model, to put back."""

    frames: dict[int, np.ndarray]  # frame id -> rig_from_world (3, 4)
    points: dict[int, np.ndarray]  # point id -> xyz

    @classmethod
    def of(cls, rec: pycolmap.Reconstruction) -> _Snapshot:
        return cls(
            frames={
                f: T.matrix()
                for f in rec.reg_frame_ids()
                if (T := rec.frame(f).rig_from_world) is not None
            },
            points={i: p.xyz.copy() for i, p in rec.points3D.items()},
        )

    def restore(self, rec: pycolmap.Reconstruction) -> None:
        """Put the poses and points back (the adjustment moves nothing else)."""
        for frame_id, T in self.frames.items():  # loop over frames
            rec.frame(frame_id).rig_from_world = pycolmap.Rigid3d(T)
        for point_id, xyz in self.points.items():  # loop over points
            rec.point3D(point_id).xyz = xyz


def agreeing_ups(
    rec: pycolmap.Reconstruction,
    registered: dict[str, int],
    measured: dict[str, Gravity],
    max_deg: float,
) -> tuple[dict[str, Gravity], dict[str, float]]:
    """The measured cameras whose up, turned into the world by the people's model,
    lies within ``max_deg`` of the mean of all the measured ups, its own included
    (the farthest left out first, one at a time), and those left out with their
    angle. The people place cameras to a few degrees, and a vanishing point found
    in the wrong lines, or near a person who is not upright, is far off; two that
    disagree are both left out. With two cameras the angle is half of theirs:
    two ups up to 2 ``max_deg`` apart are both used, since a model of two
    cameras can leave their tilts 15-31 deg apart where both ups are right
    (bench/subsets.py; ``GravityOptions.max_hint_deg``)."""
    kept = dict(measured)
    left_out: dict[str, float] = {}
    while len(kept) >= 2:
        angle = _residuals_deg(rec, registered, kept)
        worst = max(angle, key=lambda k: (angle[k], k))
        if angle[worst] <= max_deg:
            break
        if len(kept) == 2:  # nothing says which of the two is right
            left_out.update(angle)
            kept = {}
            break
        left_out[worst] = angle[worst]
        del kept[worst]
    for k, a in left_out.items():
        logger.info(
            "gravity: %s left out: its up is %.1f deg from the measured ups' mean", k, a
        )
    return {k: measured[k] for k in sorted(kept)}, left_out


def absorbed_noise_px(
    rec: pycolmap.Reconstruction,
    registered: dict[str, int],
    measured: dict[str, Gravity],
    loss_scale_px: float,
    people: PeopleNoise | None = None,
) -> float | None:
    """The keypoint noise the cameras' tilts show, pixels: what the residuals
    cannot (None with fewer than three measured ups, or without a covariance;
    ``people``: the weighted surface observations, left out of the covariance;
    keypoints count at one pixel each, repeated or not).

    The residuals see the keypoints' spread and the error a person's keypoints
    share in an image (:func:`keypoint_noise_px`), but not an error the poses
    absorb: landmark biases a camera repeats at every instant move the camera, not
    the residuals. The measured ups see it. Before they are used, camera i's up in
    the model is d_i from its measurement (the world's up: their mean); per axis,
    E[sum d_i^2] = 2 (n - 1) (s^2 + sigma^2), with s the tilt error the keypoints
    leave and sigma the ups' standard errors. The model's covariance (COLMAP's, at
    one pixel of keypoint noise, the tilt's share: the rotation's covariance
    across the camera's up, halved per camera since the gauge camera's error is
    in every other) gives c, the tilt variance per pixel^2; s^2 / c is the noise
    that tilt error means. On pose2sim_single's static cameras: s = 0.72 deg,
    31 px against 12.6 px from the residuals; pose2sim_multi's tilts agree with
    their ups within the ups' own error (s = 0).
    """
    keys = sorted(measured)
    if len(keys) < 3:
        return None
    rotations = {
        k: rec.image(registered[k]).cam_from_world().rotation.matrix() for k in keys
    }
    world = _world_ups(rec, registered, measured)[1]
    up = world.mean(axis=0)
    up /= np.linalg.norm(up)
    d2 = np.arccos(np.clip(world @ up, -1.0, 1.0)) ** 2
    sigma2 = np.array([measured[k].sigma_rad ** 2 for k in keys])
    s2 = d2.sum() / (2 * (len(keys) - 1)) - sigma2.mean()
    if s2 <= 0:
        return 0.0
    # COLMAP's covariance reads every frame's pose: a camera left out before
    # (contradicted_cameras) has none, so the estimate runs on a copy without it.
    posed = pycolmap.Reconstruction(rec)
    # The covariance is the keypoints' (at one pixel each): surface points
    # weighted to a few observations per image would count thousands of times.
    for point_id in [] if people is None else weighted_points(posed, people):
        posed.delete_point3D(point_id)
    posed.tear_down()
    config = pycolmap.BundleAdjustmentConfig()
    for image_id in sorted(posed.reg_image_ids()):
        config.add_image(image_id)
    config.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
    adjuster = pycolmap.create_default_ceres_bundle_adjuster(
        ba_options(loss_scale_px), config, posed
    )
    cov = pycolmap.estimate_ba_covariance(
        pycolmap.BACovarianceOptions(), posed, adjuster
    )
    if cov is None:
        return None
    per_px2 = []
    for k in keys:  # loop over the measured cameras
        C = cov.get_cam_cov_from_world(registered[k])
        if C is None or C.shape[0] < 3:
            continue  # the gauge camera
        u = rotations[k] @ up
        across = np.eye(3) - np.outer(u, u)
        per_px2.append(np.trace(across @ C[:3, :3] @ across) / 4)
    if not per_px2:
        return None
    return float(np.sqrt(s2 / np.median(per_px2)))


def contradicted_cameras(
    rec: pycolmap.Reconstruction,
    registered: dict[str, int],
    measured: dict[str, Gravity],
    agreeing: dict[str, Gravity],
    disagree: dict[str, float],
    max_deg: float,
) -> dict[str, str]:
    """The cameras whose own image contradicts their pose: name -> reason.

    A measured up that disagrees with the others' (:func:`agreeing_ups`) is a
    wrong vanishing point, or a wrong camera. When two or more other cameras
    agree on the world's up, and the model's up in that camera is more than
    ``max_deg`` both from its vertical lines and from its own people's up (the
    hint the lines were searched near, from its meshes, independent of the
    model), two cues of the image agree with each other and not with the
    pose: the camera is what is wrong (pose2sim_multi t090: a detection that
    merged the two people put cam03 55 deg off, its lines 38 deg away). A wrong
    camera is worse than none, so it leaves the model.
    """
    if len(agreeing) < 2:
        return {}  # no consensus on the world's up
    up = _world_ups(rec, registered, agreeing)[1].mean(axis=0)
    up /= np.linalg.norm(up)
    out: dict[str, str] = {}
    for name in sorted(disagree):  # loop over the disagreeing cameras
        g = measured[name]
        if g.people_up_cam is None:
            continue
        model_up = rec.image(registered[name]).cam_from_world().rotation.matrix() @ up
        to_lines, to_people = (
            float(np.degrees(np.arccos(np.clip(model_up @ v, -1.0, 1.0))))
            for v in (g.up_cam, g.people_up_cam)
        )
        if min(to_lines, to_people) > max_deg:
            out[name] = (
                f"left out: its pose contradicts its own image (the up the other "
                f"cameras agree on is {to_lines:.0f} deg from its vertical lines and "
                f"{to_people:.0f} deg from its people's up, more than {max_deg:g})"
            )
    return out


def _world_ups(
    rec: pycolmap.Reconstruction,
    registered: dict[str, int],
    measured: dict[str, Gravity],
) -> tuple[list[str], np.ndarray]:
    """The measured cameras' names, sorted, and their ups (n, 3) turned into the
    world by the model."""
    keys = sorted(measured)
    world = np.array(
        [
            rec.image(registered[k]).cam_from_world().rotation.matrix().T
            @ measured[k].up_cam
            for k in keys
        ]
    ).reshape(-1, 3)
    return keys, world


def _residuals_deg(
    rec: pycolmap.Reconstruction,
    registered: dict[str, int],
    measured: dict[str, Gravity],
) -> dict[str, float]:
    """Per measured camera: the angle between its measured up and the model's
    common up (the mean of the measurements turned into the world)."""
    if len(measured) < 2:
        return {}
    keys, world = _world_ups(rec, registered, measured)
    mean = world.mean(axis=0)
    mean /= np.linalg.norm(mean)
    angle = np.degrees(np.arccos(np.clip(world @ mean, -1.0, 1.0)))
    return dict(zip(keys, angle.tolist(), strict=True))


def write_gravity(model_dir: Path, result: GravityResult) -> Path:
    """``gravity.json`` next to the model."""
    path = Path(model_dir) / GRAVITY_FILE
    payload = {
        "used": result.used,
        "pixel_noise_px": result.pixel_noise_px,
        "cameras": {
            k: {
                "up_cam": g.up_cam.tolist(),
                "sigma_deg": float(np.degrees(g.sigma_rad)),
                "num_segments": g.num_segments,
                "num_images": g.num_images,
                "residual_deg": result.residual_deg.get(k),
                "people_up_cam": (
                    None if g.people_up_cam is None else g.people_up_cam.tolist()
                ),
                "lines_px": np.round(g.lines_px, 1).tolist(),
            }
            for k, g in sorted(result.measured.items())
        },
        "left_out_deg": dict(sorted(result.left_out.items())),
        "people": None if result.people is None else asdict(result.people),
        "rejected": result.rejected,
        "cameras_left_out": dict(sorted(result.cameras_left_out.items())),
    }
    path.write_text(json.dumps(payload, indent=2) + "\n")
    return path
