"""Gravity from vertical lines, and the bundle adjustment that makes cameras agree
on it."""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys

import cv2
import numpy as np
import pycolmap
import pytest
from scipy.spatial.transform import Rotation

from colmap_vc.evaluation import evaluate_reconstruction
from colmap_vc.gba.ceres import PeopleNoise, bundle_adjust_inplace
from colmap_vc.gba.up import UpPriors, rotate_with_jacobian
from colmap_vc.gravity import (
    Gravity,
    GravityOptions,
    Segments,
    detect_segments,
    endpoint_distance,
    measure_gravity,
    min_segment_px,
    people_up,
    vertical_direction,
)
from colmap_vc.mapping.people_up import MAX_PEOPLE_Z, people_ups, people_verdict
from colmap_vc.mapping.up import (
    absorbed_noise_px,
    agreeing_ups,
    contradicted_cameras,
)
from colmap_vc.structs import PersonPrior

WORLD_UP = np.array([0.0, 0.0, 1.0])


def _camera() -> pycolmap.Camera:
    return pycolmap.Camera(
        model="PINHOLE", width=640, height=960, params=[700.0, 700.0, 320.0, 480.0]
    )


def _cam_from_world(pitch_deg: float, roll_deg: float) -> np.ndarray:
    """A camera at the origin looking along world +Y, pitched down and rolled."""
    look = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])  # x, y down, z fwd
    tilt = Rotation.from_euler("xz", [-pitch_deg, roll_deg], degrees=True)
    return tilt.as_matrix() @ look


def _render(
    R: np.ndarray, camera: pycolmap.Camera, rng, *, vertical: bool
) -> np.ndarray:
    """A grey image of 3D segments in front of the camera: vertical ones (door
    frames, pillars) when ``vertical``, and horizontal ones in any direction."""
    image = np.full((camera.height, camera.width), 120, np.uint8)
    segments = []
    for _ in range(60 if vertical else 0):
        base = np.r_[rng.uniform(-4, 4), rng.uniform(3, 8), rng.uniform(-2.0, 0.0)]
        segments.append((base, base + WORLD_UP * rng.uniform(0.8, 2.5)))
    for _ in range(40):
        base = np.r_[rng.uniform(-4, 4), rng.uniform(3, 8), rng.uniform(-2.0, 1.0)]
        direction = np.r_[rng.normal(size=2), 0.0]
        segments.append((base, base + direction / np.linalg.norm(direction) * 1.5))
    for a, b in segments:
        uv = np.asarray(camera.img_from_cam(np.stack([a, b]) @ R.T))
        shade = int(rng.choice([30, 220]))
        cv2.line(
            image,
            *[tuple(np.round(p * 16).astype(int)) for p in uv],
            shade,
            3,
            cv2.LINE_AA,
            4,
        )
    return image


@pytest.mark.parametrize(("pitch", "roll"), [(25.0, 4.0), (5.0, -8.0)])
def test_vertical_lines_give_the_camera_its_up(rng, pitch, roll) -> None:
    camera = _camera()
    R = _cam_from_world(pitch, roll)
    truth = R @ WORLD_UP
    image = _render(R, camera, rng, vertical=True)
    mask = np.zeros(image.shape, bool)
    segments = detect_segments(image, camera, mask, GravityOptions())
    hint = Rotation.from_rotvec(np.radians(12) * np.array([1.0, 0, 0])).apply(truth)
    found = vertical_direction(segments, hint, 700.0, GravityOptions())
    assert found is not None
    up, sigma, lines = found
    error = np.degrees(np.arccos(np.clip(up @ truth, -1, 1)))
    assert error < 0.3, error
    assert 0 < np.degrees(sigma) < 0.3 and len(lines.normal) >= 20
    # every supporting line points at the vanishing point, to its endpoints' pixel
    assert (endpoint_distance(lines, up[None])[0] * 700.0).max() < 1.0


def test_no_vertical_lines_no_up(rng) -> None:
    camera = _camera()
    R = _cam_from_world(20.0, 0.0)
    image = _render(R, camera, rng, vertical=False)
    segments = detect_segments(
        image, camera, np.zeros(image.shape, bool), GravityOptions()
    )
    assert vertical_direction(segments, R @ WORLD_UP, 700.0, GravityOptions()) is None


def test_segments_inside_the_people_are_left_out(rng) -> None:
    camera = _camera()
    R = _cam_from_world(20.0, 0.0)
    image = _render(R, camera, rng, vertical=True)
    options = GravityOptions()
    everything = detect_segments(image, camera, np.zeros(image.shape, bool), options)
    mask = np.zeros(image.shape, bool)
    mask[:, :320] = True
    right = detect_segments(image, camera, mask, options)
    assert 0 < len(right.normal) < len(everything.normal)
    assert np.all(right.midpoint[:, 0] * 700.0 + 320.0 >= 320.0 - 1)


def test_the_shortest_segment_follows_the_image_scale(rng) -> None:
    # The same short edges (20-40 px at f = 700 px, 40-80 px at f = 1400 px;
    # LSD finds both sides of each) drawn at two scales: the threshold is an
    # angle (its 15 px floor and 25 px), so both keep them all; a fixed 30 px
    # kept about half of them at the smaller scale.
    small, large = (
        _camera(),
        pycolmap.Camera(
            model="PINHOLE", width=1280, height=1920, params=[1400, 1400, 640, 960]
        ),
    )
    starts = np.c_[rng.uniform(40, 600, 40), rng.uniform(40, 880, 40)]
    lengths = rng.uniform(20, 40, 40)
    angle = GravityOptions()  # the threshold as an angle, with a floor in pixels
    kept = {}
    for cam, scale in ((small, 1), (large, 2)):
        image = np.full((cam.height, cam.width), 200, np.uint8)
        for (x, y), n in zip(starts * scale, lengths * scale, strict=True):
            cv2.line(image, (int(x), int(y)), (int(x), int(y + n)), 20, 2 * scale)
        none = np.zeros(image.shape, bool)
        kept[scale] = len(detect_segments(image, cam, none, angle).normal)
        if scale == 1:
            fixed = GravityOptions(min_segment_px=30.0)
            kept["fixed"] = len(detect_segments(image, cam, none, fixed).normal)
    # The threshold is an angle: it follows the focal length, not the image size.
    one_degree = np.radians(angle.min_segment_deg)
    assert min_segment_px(angle, small) == angle.min_segment_floor_px  # 12.5 px
    assert min_segment_px(angle, large) == pytest.approx(1400 * one_degree)
    cropped = pycolmap.Camera(
        model="PINHOLE", width=640, height=640, params=[1400, 1400, 320, 320]
    )
    assert min_segment_px(angle, cropped) == pytest.approx(1400 * one_degree)
    assert min_segment_px(fixed, large) == 30.0  # a fixed threshold: pixels
    assert kept[1] == pytest.approx(kept[2], rel=0.1), kept
    assert kept["fixed"] < 0.75 * kept[1], kept


def _box_person(R: np.ndarray) -> PersonPrior:
    """A standing box-shaped "person" 1.7 m tall, 5 m in front of the camera."""
    corners = np.array(
        [[x, y, z] for x in (-0.2, 0.2) for y in (4.8, 5.1) for z in (-1.5, 0.2)]
    )
    return PersonPrior(
        vertices_cam=np.repeat(corners, 20, axis=0) @ R.T,
        faces=np.zeros((0, 3), np.int64),
    )


def test_gravity_reads_the_stored_pixels_whatever_the_exif_orientation(
    rng, tmp_path, caplog
) -> None:
    # Phone photos carry an EXIF orientation; COLMAP and the pose estimator read
    # the stored pixels, so must the gravity step: turned by the tag, the image
    # no longer fits its camera and its verticals lie on their side.
    from PIL import Image

    camera = _camera()
    R = _cam_from_world(20.0, 3.0)
    image = _render(R, camera, rng, vertical=True)
    for tag in (1, 6):
        exif = Image.Exif()
        exif[0x0112] = tag  # Orientation
        Image.fromarray(image).save(tmp_path / f"tag{tag}.jpg", quality=95, exif=exif)
    names = ("tag1.jpg", "tag6.jpg")
    person = {n: [_box_person(R)] for n in names}
    found = measure_gravity(
        tmp_path, {n: [n] for n in names}, dict.fromkeys(names, camera), person
    )
    assert set(found) == set(names)
    assert np.allclose(found["tag1.jpg"].up_cam, found["tag6.jpg"].up_cam)
    cosine = found["tag6.jpg"].up_cam @ (R @ WORLD_UP)
    assert np.degrees(np.arccos(np.clip(cosine, -1, 1))) < 0.5
    # An image that does not fit its camera gives no up, and says why.
    big = pycolmap.Camera(
        model="PINHOLE", width=1280, height=1920, params=[1400, 1400, 640, 960]
    )
    with caplog.at_level("WARNING", logger="colmap_vc.gravity"):
        one = {"tag1.jpg": ["tag1.jpg"]}
        none = measure_gravity(tmp_path, one, {"tag1.jpg": big}, person)
    assert none == {}
    assert "is 640x960 but its camera is 1280x1920" in caplog.text


def test_people_up_points_from_feet_to_head() -> None:
    # A standing box-shaped "person" 1.7 m tall, seen by a camera pitched down.
    R = _cam_from_world(30.0, 0.0)
    up = people_up([_box_person(R)])
    assert up is not None
    assert np.degrees(np.arccos(np.clip(up @ (R @ WORLD_UP), -1.0, 1.0))) < 1.0
    assert people_up([]) is None


def test_rotation_jacobian_matches_scipy(rng) -> None:
    q = Rotation.random(random_state=3).as_quat()  # x, y, z, w
    u = rng.normal(size=3)
    Ru, J = rotate_with_jacobian(q, u)
    np.testing.assert_allclose(Ru, Rotation.from_quat(q).apply(u), atol=1e-12)
    for _ in range(3):  # along the unit sphere's tangent
        d = rng.normal(size=4)
        d -= (d @ q) * q
        step = q + 1e-6 * d
        numeric = (Rotation.from_quat(step / np.linalg.norm(step)).apply(u) - Ru) / 1e-6
        np.testing.assert_allclose(numeric, J @ d, atol=1e-4)


def _orbited(rec: pycolmap.Reconstruction, centre: np.ndarray, deg: float) -> None:
    """Turn every camera about ``centre`` by ``deg`` about its own x axis."""
    turn = Rotation.from_rotvec(np.radians(deg) * np.array([1.0, 0, 0])).as_matrix()
    for image in rec.images.values():
        T = image.cam_from_world().matrix()
        c = T[:, :3] @ centre + T[:, 3]
        rec.frame(image.frame_id).rig_from_world = pycolmap.Rigid3d(
            pycolmap.Rotation3d(turn @ T[:, :3]), turn @ (T[:, 3] - c) + c
        )


def test_measured_up_fixes_the_turn_the_points_cannot_see(dome_scene, rng) -> None:
    """Cameras around a small cluster of points, seen as if every camera were
    turned by 3 deg about the cluster (a bias the points share): the points' own
    optimum keeps the turn, and each camera's true up (weighed against points of
    10 px noise) undoes it."""
    gt = pycolmap.Reconstruction(dome_scene / "gt" / "sparse")
    centre = np.mean([im.projection_center() for im in gt.images.values()], axis=0)
    X = centre + rng.normal(0, 0.3, (40, 3))
    rec = pycolmap.Reconstruction(gt)
    for point_id in list(rec.point3D_ids()):
        rec.delete_point3D(point_id)
    world_up = np.array([0.0, 0.0, 1.0])  # the synthetic world is Z up
    ids = np.array(sorted(rec.reg_image_ids()), dtype=np.int64)
    up = UpPriors(
        image_id=ids,
        up_cam=np.array(
            [
                rec.image(int(i)).cam_from_world().rotation.matrix() @ world_up
                for i in ids
            ]
        ),
        sigma_rad=np.full(len(ids), np.radians(1.0)),
        pixel_noise_px=10.0,
    )
    _orbited(rec, centre, 3.0)
    for image in rec.images.values():  # noise-free observations by the turned cameras
        T = image.cam_from_world().matrix()
        uv = np.asarray(
            rec.camera(image.camera_id).img_from_cam(X @ T[:, :3].T + T[:, 3])
        )
        image.points2D = pycolmap.Point2DList([pycolmap.Point2D(p) for p in uv])
    for k in range(len(X)):
        track = pycolmap.Track()
        for image_id in ids.tolist():
            track.add_element(image_id, k)
        rec.add_point3D(X[k], track)
    assert _rotation_error_deg(rec, gt) > 2.0
    plain = pycolmap.Reconstruction(rec)
    bundle_adjust_inplace(plain, 1.0)
    before = _rotation_error_deg(plain, gt)
    assert before > 2.0
    bundle_adjust_inplace(rec, 1.0, None, up)
    # Every camera's up agrees; what is left is about the vertical (a point seen
    # from a camera moved up or down, which the ups cannot see), under half.
    seen = np.array(
        [
            rec.image(int(i)).cam_from_world().rotation.matrix().T @ g
            for i, g in zip(ids, up.up_cam, strict=True)
        ]
    )
    assert (
        np.degrees(
            np.arccos(
                np.clip(seen @ seen.mean(0) / np.linalg.norm(seen.mean(0)), -1, 1)
            )
        ).max()
        < 0.2
    )
    assert _rotation_error_deg(rec, gt) < before / 2


def _rotation_error_deg(rec: pycolmap.Reconstruction, gt: pycolmap.Reconstruction):
    """Median relative-rotation error over the camera pairs."""
    pairs = evaluate_reconstruction(rec, gt).pairs
    return float(np.median([p.rotation_deg for p in pairs]))


def test_up_priors_check_their_shapes() -> None:
    with pytest.raises(ValueError, match="UpPriors"):
        UpPriors(
            image_id=np.array([1, 2]),
            up_cam=np.zeros((3, 3)),
            sigma_rad=np.ones(2),
            pixel_noise_px=1.0,
        )
    with pytest.raises(ValueError, match="positive"):
        UpPriors(
            image_id=np.array([1]),
            up_cam=np.zeros((1, 3)),
            sigma_rad=np.zeros(1),
            pixel_noise_px=1.0,
        )


def _gravity(up_cam: np.ndarray, people_up_cam: np.ndarray | None = None) -> Gravity:
    return Gravity(
        up_cam=up_cam / np.linalg.norm(up_cam),
        sigma_rad=np.radians(0.3),
        num_segments=30,
        num_images=1,
        lines_px=np.zeros((0, 4)),
        people_up_cam=up_cam if people_up_cam is None else people_up_cam,
    )


def test_an_up_that_disagrees_with_the_other_cameras_is_left_out(dome_scene) -> None:
    gt = pycolmap.Reconstruction(dome_scene / "gt" / "sparse")
    registered = {im.name: i for i, im in gt.images.items()}
    names = sorted(registered)
    true_up = {
        n: gt.image(registered[n]).cam_from_world().rotation.matrix() @ WORLD_UP
        for n in names
    }
    measured = {n: _gravity(true_up[n]) for n in names}
    # One camera's vanishing point is a horizontal one (60 deg off).
    turn = Rotation.from_rotvec(np.radians(60) * np.array([1.0, 0, 0]))
    measured[names[2]] = _gravity(turn.apply(true_up[names[2]]), true_up[names[2]])
    kept, left_out = agreeing_ups(gt, registered, measured, 25.0)
    assert sorted(kept) == sorted(set(names) - {names[2]})
    assert list(left_out) == [names[2]] and left_out[names[2]] > 25.0
    # Its people stand along the model's up: the lines are wrong, not the camera.
    assert not contradicted_cameras(gt, registered, measured, kept, left_out, 25.0)
    # Two cameras that disagree: nothing says which is right.
    two = {n: measured[n] for n in names[1:3]}
    kept, left_out = agreeing_ups(gt, registered, two, 25.0)
    assert kept == {} and sorted(left_out) == names[1:3]
    # All agree: all kept.
    kept, left_out = agreeing_ups(
        gt, registered, {n: _gravity(true_up[n]) for n in names}, 25.0
    )
    assert sorted(kept) == names and left_out == {}


def test_a_camera_its_own_lines_and_people_contradict_leaves_the_model(
    dome_scene,
) -> None:
    """A camera posed 40 deg off (a merged detection can do that): its vertical
    lines and its people's up, both measured in its own image, agree with each
    other and not with the model's up there, while the other cameras agree: the
    camera, not its up, is wrong."""
    gt = pycolmap.Reconstruction(dome_scene / "gt" / "sparse")
    registered = {im.name: i for i, im in gt.images.items()}
    names = sorted(registered)
    true_up = {
        n: gt.image(registered[n]).cam_from_world().rotation.matrix() @ WORLD_UP
        for n in names
    }
    measured = {n: _gravity(true_up[n]) for n in names}
    image = gt.image(registered[names[2]])
    T = image.cam_from_world().matrix()
    turn = Rotation.from_rotvec(np.radians(40) * np.array([1.0, 0, 0])).as_matrix()
    gt.frame(image.frame_id).rig_from_world = pycolmap.Rigid3d(
        pycolmap.Rotation3d(turn @ T[:, :3]), turn @ T[:, 3]
    )
    kept, left_out = agreeing_ups(gt, registered, measured, 25.0)
    assert list(left_out) == [names[2]]
    found = contradicted_cameras(gt, registered, measured, kept, left_out, 25.0)
    assert (
        list(found) == [names[2]]
        and "40 deg from its vertical lines" in (found[names[2]])
    )
    # Its people disagree with its lines too: nothing says the camera is wrong.
    tilted = {
        **measured,
        names[2]: _gravity(true_up[names[2]], turn @ true_up[names[2]]),
    }
    assert not contradicted_cameras(gt, registered, tilted, kept, left_out, 25.0)
    # Two measured cameras: no consensus on the world's up.
    two = {n: measured[n] for n in names[1:3]}
    kept2, left2 = agreeing_ups(gt, registered, two, 25.0)
    assert not contradicted_cameras(gt, registered, two, kept2, left2, 25.0)


def _model_with_tilts(dome_scene, tilt_deg: float, rng) -> pycolmap.Reconstruction:
    """The dome's cameras with 60 points seen by all of them (1 px of noise), each
    camera then tilted by ``tilt_deg`` about a random axis across its up."""
    rec = pycolmap.Reconstruction(dome_scene / "gt" / "sparse")
    points = rng.normal(0, 0.5, (60, 3)) * [1, 2, 1] + [0, -0.9, 0]
    ids = sorted(rec.images)
    for image_id in ids:  # loop over cameras
        image = rec.image(image_id)
        T = image.cam_from_world().matrix()
        uv = rec.camera(image.camera_id).img_from_cam(points @ T[:, :3].T + T[:, 3])
        uv = np.asarray(uv) + rng.normal(0, 1.0, uv.shape)
        image.points2D = pycolmap.Point2DList([pycolmap.Point2D(p) for p in uv])
    for k, X in enumerate(points):
        track = pycolmap.Track()
        for image_id in ids:
            track.add_element(image_id, k)
        rec.add_point3D(X, track)
    for image_id in ids:  # loop over cameras
        image = rec.image(image_id)
        T = image.cam_from_world().matrix()
        up = T[:, :3] @ WORLD_UP
        axis = np.cross(up, rng.normal(size=3))
        turn = Rotation.from_rotvec(np.radians(tilt_deg) * axis / np.linalg.norm(axis))
        R = turn.as_matrix()
        rec.frame(image.frame_id).rig_from_world = pycolmap.Rigid3d(
            pycolmap.Rotation3d(R @ T[:, :3]), R @ T[:, 3]
        )
    return rec


def _exact_ups(dome_scene, registered: dict[str, int]) -> dict:
    """Each camera's true up (standard error 1e-4 rad), by image name."""
    gt = pycolmap.Reconstruction(dome_scene / "gt" / "sparse")
    return {
        n: dataclasses.replace(
            _gravity(gt.image(i).cam_from_world().rotation.matrix() @ WORLD_UP),
            sigma_rad=1e-4,
        )
        for n, i in registered.items()
    }


def test_the_tilt_error_the_residuals_cannot_see_is_read_from_the_ups(
    dome_scene,
) -> None:
    """Cameras tilted by an error their keypoints do not show (the ups, exact, do):
    no tilt, no extra noise; twice the tilt, twice the noise; under three ups,
    nothing to say."""
    found = []
    for tilt in (0.0, 1.0, 2.0):
        rec = _model_with_tilts(dome_scene, tilt, np.random.default_rng(3))
        registered = {im.name: i for i, im in rec.images.items()}
        measured = _exact_ups(dome_scene, registered)
        # A loss far above the residuals: the covariance at the tilted poses is
        # the one at the adjusted poses (where the step runs, residuals are small).
        found.append(absorbed_noise_px(rec, registered, measured, 1e3))
    assert found[0] == 0.0
    assert found[1] > 5.0 and found[2] / found[1] == pytest.approx(2.0, rel=0.1), found
    two = dict(list(measured.items())[:2])
    assert absorbed_noise_px(rec, registered, two, 1e3) is None
    # A camera the up check left out (deregistered, no pose) is not read: the
    # others' estimate stands (it raised "Frame does not have a valid pose").
    name = max(registered)
    rec.deregister_frame(rec.image(registered.pop(name)).frame_id)
    del measured[name]
    assert absorbed_noise_px(rec, registered, measured, 1e3) > 5.0


def test_weighted_surface_points_do_not_count_in_the_tilt_covariance(dome_scene):
    """The covariance that turns the tilt error into pixels is the keypoints':
    points weighted as surface observations (a few per image together) are left
    out of it, as if they were not in the model; counted at full weight, they
    shrink the covariance and inflate the noise."""
    rec = _model_with_tilts(dome_scene, 2.0, np.random.default_rng(3))
    registered = {im.name: i for i, im in rec.images.items()}
    measured = _exact_ups(dome_scene, registered)
    surface = [i for i in sorted(rec.points3D) if i % 4]  # three points in four
    sigma = {i: np.full(im.num_points2D(), np.nan) for i, im in rec.images.items()}
    for point_id in surface:
        for e in rec.point3D(point_id).track.elements:
            sigma[e.image_id][e.point2D_idx] = 10.0
    people = PeopleNoise(sigma_px=sigma, robust_px=sigma)
    without = pycolmap.Reconstruction(rec)
    for point_id in surface:
        without.delete_point3D(point_id)
    everything = absorbed_noise_px(rec, registered, measured, 1e3)
    weighted = absorbed_noise_px(rec, registered, measured, 1e3, people)
    expected = absorbed_noise_px(without, registered, measured, 1e3)
    assert weighted == pytest.approx(expected, rel=1e-6)
    assert everything / weighted > 1.5  # 4x the points: about sqrt(4)


_LARGE_UP_PROBLEM = """
import sys
import numpy as np
import pycolmap
from colmap_vc.gba.ceres import bundle_adjust_inplace
from colmap_vc.gba.up import UpPriors

rec = pycolmap.Reconstruction(sys.argv[1])
for point_id in list(rec.point3D_ids()):
    rec.delete_point3D(point_id)
ids = np.array(sorted(rec.reg_image_ids()), dtype=np.int64)
rng = np.random.default_rng(0)
centre = np.mean([rec.image(int(i)).projection_center() for i in ids], axis=0)
n = 30000 // len(ids) + 1  # 60000 residuals: COLMAP evaluates them on all threads
X = centre + rng.normal(0, 0.5, (n, 3))
for i in ids.tolist():
    image = rec.image(i)
    T = image.cam_from_world().matrix()
    uv = np.asarray(rec.camera(image.camera_id).img_from_cam(X @ T[:, :3].T + T[:, 3]))
    uv += rng.normal(0, 1.0, uv.shape)
    image.points2D = pycolmap.Point2DList([pycolmap.Point2D(p) for p in uv])
for k in range(n):
    track = pycolmap.Track()
    for i in ids.tolist():
        track.add_element(i, k)
    rec.add_point3D(X[k], track)
up = UpPriors(
    image_id=ids,
    up_cam=np.array(
        [rec.image(int(i)).cam_from_world().rotation.matrix() @ [0, 0, 1.0]
         for i in ids]
    ),
    sigma_rad=np.full(len(ids), np.radians(1.0)),
    pixel_noise_px=1.0,
)
summary = bundle_adjust_inplace(rec, 2.0, None, up)
print("threads", summary.num_threads_used)
"""


def test_a_large_problem_with_ups_solves_on_several_threads(dome_scene) -> None:
    """The ups are Python cost functions. A problem large enough for COLMAP to
    use several threads once hung in pycolmap's solve, which keeps Python's lock
    while a worker thread waits for it (`map --gba --static-cameras` on
    pose2sim_multi). Run in a child process so that a hang fails the test."""
    run = subprocess.run(
        [sys.executable, "-c", _LARGE_UP_PROBLEM, str(dome_scene / "gt" / "sparse")],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert run.returncode == 0, run.stderr[-2000:]
    threads = int(run.stdout.split("threads")[-1])
    assert threads > 1 or os.cpu_count() == 1  # else the test proves nothing


def _segments_towards(
    vp: np.ndarray, rng, count: int, length_px: float, f: float = 700.0
) -> tuple[np.ndarray, np.ndarray]:
    """``count`` segments of ``length_px`` at random places of a 640 x 960 image
    at focal ``f``, each on the line from its midpoint to the vanishing
    direction ``vp`` (camera frame): (ray1, ray2), z = 1."""
    mid = np.c_[rng.uniform(-300, 300, count), rng.uniform(-450, 450, count)] / f
    towards = vp[:2] / vp[2] - mid  # image direction to the vanishing point
    towards /= np.linalg.norm(towards, axis=1, keepdims=True)
    half = towards * length_px / 2.0 / f
    one = np.ones((count, 1))
    return np.c_[mid - half, one], np.c_[mid + half, one]


def _as_segments(*parts: tuple[np.ndarray, np.ndarray]) -> Segments:
    ray1 = np.concatenate([p[0] for p in parts])
    ray2 = np.concatenate([p[1] for p in parts])
    normal = np.cross(ray1, ray2)
    return Segments(
        ray1=ray1, ray2=ray2, normal=normal / np.linalg.norm(normal, axis=1)[:, None]
    )


def _two_directions(
    seed: int, apart_deg: float, length_px: float, between: int
) -> tuple[Segments, np.ndarray]:
    """Edges leaning to two directions ``apart_deg`` apart about the truth, 20
    each, and ``between`` more towards the truth itself, which support both
    (each accepts asin(2 / length) about its own) -> segments, the truth."""
    rng = np.random.default_rng(seed)
    truth = _cam_from_world(20.0, 0.0) @ WORLD_UP
    tilt = Rotation.from_rotvec(np.radians(apart_deg / 2) * np.array([0.0, 0, 1]))
    segments = _as_segments(
        _segments_towards(tilt.apply(truth), rng, 20, length_px),
        _segments_towards(tilt.inv().apply(truth), rng, 20, length_px),
        _segments_towards(truth, rng, between, length_px),
    )
    return segments, truth


@pytest.mark.parametrize("seed", [0, 2])
def test_two_close_vanishing_points_of_the_same_lines_keep_the_up(seed) -> None:
    # 1.8 deg apart, 150-px edges (these seeds: RANSAC finds the two, most
    # lines on both). Whichever is the vertical, the best is within 1.8 deg of
    # it: the up is kept, its error widened to reach the other.
    segments, truth = _two_directions(seed, 1.8, 150.0, 30)
    found = vertical_direction(segments, truth, 700.0, GravityOptions())
    assert found is not None
    up, sigma, _ = found
    error = np.degrees(np.arccos(np.clip(up @ truth, -1, 1)))
    assert np.degrees(sigma) > 1.0  # about the separation, not the fit's 0.23
    assert error < np.degrees(sigma), (error, np.degrees(sigma))


@pytest.mark.parametrize("seed", [6, 7])
def test_two_vanishing_points_farther_than_the_bound_give_no_up(seed) -> None:
    # 4 deg apart, 60-px edges, most lines on both: the image cannot tell the
    # vertical to the 2 deg an up must hold (max_rival_deg); no up.
    segments, truth = _two_directions(seed, 4.0, 60.0, 30)
    assert vertical_direction(segments, truth, 700.0, GravityOptions()) is None
    wider = GravityOptions(max_rival_deg=5.0)  # the same rival, within the bound
    found = vertical_direction(segments, truth, 700.0, wider)
    assert found is not None and np.degrees(found[1]) > 2.0


def test_two_vanishing_points_of_different_lines_give_no_up(rng) -> None:
    # Two bundles of long edges, 6 deg apart, 40 lines each, none of them on
    # both: the image does not say which is the vertical.
    R = _cam_from_world(20.0, 0.0)
    truth = R @ WORLD_UP
    tilt = Rotation.from_rotvec(np.radians(3.0) * np.array([0.0, 0.0, 1.0]))
    segments = _as_segments(
        _segments_towards(tilt.apply(truth), rng, 40, 150.0),
        _segments_towards(tilt.inv().apply(truth), rng, 40, 150.0),
    )
    assert vertical_direction(segments, truth, 700.0, GravityOptions()) is None
    alone = _as_segments(_segments_towards(tilt.apply(truth), rng, 40, 150.0))
    assert vertical_direction(alone, truth, 700.0, GravityOptions()) is not None


def _tilted(R: np.ndarray, deg: float, rng) -> np.ndarray:
    """``R`` (cam_from_world) with the camera turned by ``deg`` about a random
    axis across its up (world +Z)."""
    up = R @ WORLD_UP
    axis = np.cross(up, rng.normal(size=3))
    turn = Rotation.from_rotvec(np.radians(deg) * axis / np.linalg.norm(axis))
    return turn.as_matrix() @ R


def _ring(n: int, rng) -> dict[str, np.ndarray]:
    """``n`` level cameras around the origin, looking in, by name."""
    return {
        f"cam{i:02d}": _cam_from_world(0.0, 0.0)
        @ Rotation.from_euler("z", yaw, degrees=True).as_matrix()
        for i, yaw in enumerate(rng.uniform(0, 360, n))
    }


def _people_of(truth: dict[str, np.ndarray], deg: float, rng) -> dict:
    """Per camera one person's up (1, 3): the true up in its frame, off by a 2D
    normal error of ``deg`` per axis."""
    return {
        n: (_tilted(R, float(np.hypot(*rng.normal(0, deg, 2))), rng) @ WORLD_UP)[None]
        for n, R in truth.items()
    }


def test_the_people_score_a_right_turn_as_noise_and_a_wrong_one_far_off() -> None:
    """The score of :func:`people_verdict` on known turns: the people's ups (5
    deg of noise per axis) of 12 cameras. A step that removes tilt errors scores
    as a standard normal, whatever their size (0.5 or 3 deg: the larger ones
    widen the noise read from the spread, so the score only narrows); one that
    adds 10 deg errors to seven cameras scores about D / sigma, above the bound.
    With two cameras the score is a Student's t of two degrees of freedom."""
    rng = np.random.default_rng(0)
    right_small, right, wrong = [], [], []
    for _ in range(400):  # loop over random scenes
        truth = _ring(12, rng)
        people = _people_of(truth, 5.0, rng)
        for out, error_deg in ((right_small, 0.5), (right, 3.0)):
            before = {n: _tilted(R, error_deg, rng) for n, R in truth.items()}
            verdict = people_verdict(before, truth, people)
            assert verdict is not None
            out.append(verdict.z)
        after = {
            n: _tilted(R, 10.0, rng) if k < 7 else R
            for k, (n, R) in enumerate(sorted(truth.items()))
        }
        verdict = people_verdict(truth, after, people)
        assert verdict is not None and verdict.num_cameras == 12
        assert verdict.dof == 22
        wrong.append((verdict.t, verdict.z))
    assert abs(np.mean(right_small)) < 0.2 and 0.8 < np.std(right_small) < 1.2
    assert abs(np.mean(right)) < 0.2 and np.std(right) < np.std(right_small)
    for z in (right_small, right):
        assert np.mean(np.array(z) > MAX_PEOPLE_Z) < 0.01
    # t about D / sigma = sqrt(7) * 10 / 5 = 5.3.
    assert np.median([t for t, _ in wrong]) == pytest.approx(5.3, rel=0.15)
    assert np.mean([z > MAX_PEOPLE_Z for _, z in wrong]) > 0.9
    # Two cameras: the noise rests on two degrees of freedom, so a right step's
    # t is often above 3 (about 5 %), its z is not (0.13 %).
    pair = []
    for _ in range(1000):  # loop over random pairs
        truth = _ring(2, rng)
        people = _people_of(truth, 5.0, rng)
        before = {n: _tilted(R, 3.0, rng) for n, R in truth.items()}
        verdict = people_verdict(before, truth, people)
        assert verdict is not None and verdict.dof == 2
        pair.append((verdict.t, verdict.z))
    assert np.mean([t > 3.0 for t, _ in pair]) > 0.02
    assert np.mean([z > MAX_PEOPLE_Z for _, z in pair]) < 0.005
    # No turn, or fewer than two cameras with people: nothing to say.
    truth = _ring(3, rng)
    assert people_verdict(truth, truth, people_ups({}, {n: [n] for n in truth})) is None
    up = {n: (R @ WORLD_UP)[None] for n, R in truth.items()}
    assert people_verdict(truth, truth, up) is None
