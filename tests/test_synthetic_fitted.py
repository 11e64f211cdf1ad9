"""The synthetic `fitted` level: the bundled estimator's fit to noisy landmarks."""

from __future__ import annotations

import numpy as np
import pycolmap
import pytest

from colmap_vc import raycast
from colmap_vc.estimators.body import (
    NUM_LANDMARKS,
    landmark_index,
    landmarks_from_mesh,
    load_template,
)
from colmap_vc.estimators.prior import render_silhouette
from colmap_vc.priors import read_priors
from colmap_vc.synthetic import SynthOptions, generate, noise
from colmap_vc.synthetic.bodies import joints, load_bodies, pose_body
from colmap_vc.synthetic.fitted import (
    CORRELATION_2D_3D,
    LANDMARK_SIGMA,
    LANDMARK_SIGMA_3D,
    SHARED_SIGMA,
    fitted_person,
    noisy_landmarks,
)

CAMERA = pycolmap.Camera(
    model="PINHOLE", width=640, height=480, params=[500.0, 500.0, 320.0, 240.0]
)
# Body frame (left -X, forward +Y, up +Z) -> camera (x right, y down, z ahead).
FACING_CAMERA = np.array([[-1.0, 0, 0], [0, 0, -1.0], [0, -1.0, 0]])


@pytest.fixture(scope="module")
def person():
    """A person 4 m ahead facing the camera: its view and its true vertices."""
    bodies = load_bodies()
    body = pose_body(bodies, 0, 0)
    cam_from_body = np.c_[FACING_CAMERA, [0.0, 0.2, 4.0]]
    verts = body @ FACING_CAMERA.T + cam_from_body[:, 3]
    view = noise.PersonView(
        person_id=0,
        phenotype=0,
        pose=0,
        body_vertices=body,
        cam_from_body=cam_from_body,
        xy_img=np.zeros((0, 2)),
        face_idx=np.zeros(0, np.int64),
        bary=np.zeros((0, 3)),
        mask=render_silhouette(CAMERA, verts, bodies.faces),
    )
    return bodies, view, verts


def _facing(bodies, verts) -> np.ndarray:
    j = joints(bodies, verts)
    names = bodies.joint_names
    left_right = j[names.index("left_shoulder")] - j[names.index("right_shoulder")]
    return np.cross(left_right, FACING_CAMERA @ [0.0, 0.0, 1.0])


def _prior(person, rng, **kw):
    bodies, view, _ = person
    args = dict(noise_scale=0.0, turn_prob=0.0, confidence=0.9)
    args.update(kw)
    return fitted_person(bodies, view, CAMERA, mask=view.mask, rng=rng, **args)


def test_without_noise_the_fit_finds_the_body_and_maps_its_pixels(person, rng):
    bodies, view, verts = person
    p = _prior(person, rng)
    assert p is not None and p.template == "anny"
    true = joints(bodies, verts)
    fitted = np.asarray(p.keypoints_cam)[: len(true)]
    err = np.linalg.norm(fitted - true, axis=1)
    assert np.median(err) < 0.05  # joint centres within a few cm
    assert _facing(bodies, verts) @ _facing(bodies, p.vertices_cam) > 0
    # Valid keypoints are the landmarks' pixels, exactly (no noise).
    exact = landmarks_from_mesh(
        load_template(bodies), view.body_vertices, view.cam_from_body, CAMERA
    )
    valid = np.asarray(p.keypoints_valid)
    assert valid.sum() >= 17
    names = bodies.joint_names
    for k in np.flatnonzero(valid[: len(names)]):
        assert np.allclose(p.keypoints_xy[k], exact.xy_img[landmark_index(names[k])])
    # The dense map: mask pixels ray-cast on the fitted mesh, its points project
    # back onto their pixels, and cover most of the person.
    smap = p.surface_map
    assert smap is not None and len(smap.xy_img) > 0.8 * view.mask.sum()
    tri = np.asarray(p.vertices_cam)[np.asarray(p.faces)[smap.face_idx]]
    points = np.einsum("nk,nkd->nd", smap.bary, tri)
    assert np.allclose(CAMERA.img_from_cam(points), smap.xy_img, atol=1e-3)
    hits = raycast.first_hits(
        raycast.build_scene([(verts, bodies.faces)]),
        np.zeros((len(points), 3)),
        raycast.rays_cam(CAMERA, smap.xy_img),
    )
    assert (hits[1] >= 0).mean() > 0.95  # the true body is under those pixels


def test_landmark_noise_has_the_measured_spread_and_shared_offset(person):
    bodies, view, _ = person
    template = load_template(bodies)
    exact = landmarks_from_mesh(
        template, view.body_vertices, view.cam_from_body, CAMERA
    )
    height = np.ptp(exact.xy_img[template.landmark_idx, 1])
    rng = np.random.default_rng(1)
    draws = (
        np.stack(
            [
                noisy_landmarks(
                    exact,
                    fitted_idx=template.landmark_idx,
                    noise_scale=1.0,
                    rng=rng,
                ).xy_img
                - exact.xy_img
                for _ in range(4000)
            ]
        )
        / height
    )  # (draws, 33, 2)
    nose, toe = landmark_index("nose"), landmark_index("left_foot_index")
    for k, name in ((nose, "nose"), (toe, "left_foot_index")):
        want = np.hypot(LANDMARK_SIGMA[name], SHARED_SIGMA)
        assert draws[:, k].std(axis=0) == pytest.approx([want, want], rel=0.06)
    # Two landmarks share the offset, and only it.
    cov = np.mean(draws[:, nose, 0] * draws[:, toe, 0])
    assert cov == pytest.approx(SHARED_SIGMA**2, rel=0.25)
    unfitted = np.setdiff1d(np.arange(NUM_LANDMARKS), template.landmark_idx)
    offset = draws[:, unfitted]  # landmarks the fit ignores: the offset only
    assert np.abs(offset - offset[:, :1]).max() < 1e-12
    assert offset[:, 0].std(axis=0) == pytest.approx(
        [SHARED_SIGMA, SHARED_SIGMA], rel=0.06
    )


def test_the_fitted_mesh_follows_the_landmarks_errors(person):
    """Why the level exists: the fit goes where the noisy landmarks are, so its
    joints (and the dense map read off its mesh) repeat their errors."""
    bodies, _, verts = person
    true_xy = CAMERA.img_from_cam(joints(bodies, verts))
    rng = np.random.default_rng(3)
    follow = []
    for _ in range(3):
        p = _prior(person, rng, noise_scale=2.0)
        assert p is not None
        valid = np.asarray(p.keypoints_valid)[: len(true_xy)]
        fitted_xy = CAMERA.img_from_cam(np.asarray(p.keypoints_cam)[: len(true_xy)])
        noisy = np.asarray(p.keypoints_xy)[: len(true_xy)]
        a = (fitted_xy - true_xy)[valid].ravel()
        b = (noisy - true_xy)[valid].ravel()
        follow.append(np.corrcoef(a, b)[0, 1])
    assert np.median(follow) > 0.5


def test_a_turned_person_is_fitted_facing_away_with_left_and_right_exchanged(
    person, rng
):
    bodies, _, verts = person
    p = _prior(person, rng, turn_prob=1.0)
    assert p is not None
    assert _facing(bodies, verts) @ _facing(bodies, p.vertices_cam) < 0
    names = bodies.joint_names
    true_xy = CAMERA.img_from_cam(joints(bodies, verts))
    left, right = names.index("left_wrist"), names.index("right_wrist")
    assert np.allclose(p.keypoints_xy[left], true_xy[right], atol=5.0)


def test_a_fitted_scene_writes_the_estimators_priors(tmp_path):
    out = tmp_path / "scene"
    generate(
        "dome",
        out,
        SynthOptions(
            seed=2,
            num_cameras=3,
            width=320,
            height=240,
            noise="fitted",
            sift=False,
            num_threads=1,
        ),
    )
    priors = read_priors(out / "priors")
    persons = [p for ip in priors.images.values() for p in ip.persons]
    assert persons
    for p in persons:
        assert p.template == "anny" and len(p.keypoints_xy) == 24
        assert p.surface_map is not None and len(p.surface_map) > 0
        assert 0.7 <= p.confidence <= 0.95


def test_world_landmarks_have_the_measured_spread_per_axis(person):
    """The 3D landmarks the fit reads err per camera axis as measured on pose2sim
    (a fraction of the landmarks' 3D extent), most in depth, across the image
    with the landmark's own 2D error as measured there; landmarks the fit
    ignores keep their exact position."""
    bodies, view, _ = person
    template = load_template(bodies)
    exact = landmarks_from_mesh(
        template, view.body_vertices, view.cam_from_body, CAMERA
    )
    extent = np.ptp(exact.points_3d[template.landmark_idx], axis=0).max()
    assert 1.3 < extent < 2.0  # a standing adult's landmarks, metres
    rng = np.random.default_rng(2)
    noisy = [
        noisy_landmarks(
            exact, fitted_idx=template.landmark_idx, noise_scale=1.0, rng=rng
        )
        for _ in range(4000)
    ]
    draws = np.stack([n.points_3d - exact.points_3d for n in noisy]) / extent
    flat = np.stack([n.xy_img - exact.xy_img for n in noisy])  # (draws, 33, 2)
    for name in ("nose", "left_wrist", "right_hip"):
        k = landmark_index(name)
        assert draws[:, k].std(axis=0) == pytest.approx(
            LANDMARK_SIGMA_3D[name], rel=0.06
        )
    wrist = draws[:, landmark_index("left_wrist")]
    assert wrist[:, 2].std() > 2 * wrist[:, 0].std()  # depth errs most
    # Across the image it follows the landmark's own 2D error (not the offset
    # all landmarks share), in depth it does not.
    k = landmark_index("left_wrist")
    own = LANDMARK_SIGMA["left_wrist"] / np.hypot(
        LANDMARK_SIGMA["left_wrist"], SHARED_SIGMA
    )
    for axis in (0, 1):
        r = np.corrcoef(flat[:, k, axis], draws[:, k, axis])[0, 1]
        assert r == pytest.approx(CORRELATION_2D_3D[axis] * own, abs=0.05)
    assert abs(np.corrcoef(flat[:, k, 0], draws[:, k, 2])[0, 1]) < 0.05
    unfitted = np.setdiff1d(np.arange(NUM_LANDMARKS), template.landmark_idx)
    assert np.abs(draws[:, unfitted]).max() == 0.0


def test_the_persons_size_error_scales_the_fitted_body_and_its_depth(person):
    exact = _prior(person, np.random.default_rng(0))
    larger = _prior(person, np.random.default_rng(0), size_error=0.1)
    assert exact is not None and larger is not None

    def size(v: np.ndarray) -> float:
        return float(np.sqrt(((v - v.mean(0)) ** 2).sum(1).mean()))

    ratio = size(np.asarray(larger.vertices_cam)) / size(np.asarray(exact.vertices_cam))
    assert ratio == pytest.approx(1.1, abs=0.02)
    # Depth scales alike, so the larger body still lies on the person's pixels.
    pelvis = np.asarray(larger.keypoints_cam)[0], np.asarray(exact.keypoints_cam)[0]
    assert pelvis[0][2] / pelvis[1][2] == pytest.approx(1.1, abs=0.03)
    valid = np.asarray(exact.keypoints_valid)
    assert valid.sum() >= 17
    assert np.array_equal(valid, np.asarray(larger.keypoints_valid))
    assert np.allclose(larger.keypoints_xy[valid], exact.keypoints_xy[valid])
