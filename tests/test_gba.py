"""gba: camera model, residuals at ground truth, Jacobian, convergence, metric scale."""

from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path

import numpy as np
import pycolmap
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from colmap_vc import augment, database
from colmap_vc.evaluation import evaluate_poses, poses_by_name
from colmap_vc.gba import (
    GbaOptions,
    GbaProblem,
    LossType,
    Parametrization,
    Solver,
    build_problem,
    export_ply,
    jacobian,
    model,
    pack,
    refine_reconstruction,
    residuals,
    solve,
    vc_tuples_from_db,
)
from colmap_vc.gba.camera import opencv_params, project
from colmap_vc.gba.problem import rays_world
from colmap_vc.priors import read_priors

CAMERAS = {
    "SIMPLE_PINHOLE": [500.0, 320.0, 240.0],
    "PINHOLE": [500.0, 510.0, 320.0, 240.0],
    "SIMPLE_RADIAL": [500.0, 320.0, 240.0, -0.08],
    "RADIAL": [500.0, 320.0, 240.0, -0.08, 0.02],
    "OPENCV": [500.0, 510.0, 320.0, 240.0, -0.08, 0.02, 0.001, -0.002],
}


def _camera(model_name: str, camera_id: int = 1) -> pycolmap.Camera:
    return pycolmap.Camera(
        camera_id=camera_id,
        model=model_name,
        width=640,
        height=480,
        params=np.array(CAMERAS[model_name]),
    )


def _look_at(centre: np.ndarray, target: np.ndarray) -> np.ndarray:
    z = target - centre
    z /= np.linalg.norm(z)
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    return np.column_stack([R, -R @ centre])


def _project(cameras, poses, X, idx):
    if len(idx) == 0:
        return np.zeros((0, 2))
    Xc = np.einsum("mij,mj->mi", poses[idx, :, :3], X) + poses[idx, :, 3]
    return np.stack(
        [
            cameras[i].img_from_cam(x, check_cheirality=False)
            for i, x in zip(idx, Xc, strict=True)
        ]
    )


def _random_problem(
    rng: np.random.Generator, num_points: int = 8, num_vcs: int = 10
) -> GbaProblem:
    """Three cameras around the origin (OPENCV, SIMPLE_RADIAL, RADIAL), noisy data."""
    cameras = tuple(
        _camera(m, k + 1) for k, m in enumerate(["OPENCV", "SIMPLE_RADIAL", "RADIAL"])
    )
    poses = np.stack(
        [
            _look_at(
                np.array([4 * np.sin(a), 0.3 * rng.normal(), -4 * np.cos(a)]),
                np.zeros(3),
            )
            for a in (0.0, 2.1, 4.2)
        ]
    )
    points = rng.normal(size=(num_points, 3)) * 0.5
    obs_img = np.tile(np.arange(3), num_points)
    obs_pt = np.repeat(np.arange(num_points), 3)
    i1 = rng.integers(0, 3, num_vcs)
    i2 = (i1 + rng.integers(1, 3, num_vcs)) % 3
    x1 = rng.normal(size=(num_vcs, 3)) * 0.5
    x2 = x1 + rng.normal(size=(num_vcs, 3)) * 0.1
    return GbaProblem(
        image_ids=np.arange(1, 4),
        image_names=("a.jpg", "b.jpg", "c.jpg"),
        cameras=cameras,
        cam_from_world=poses,
        point3D_ids=np.arange(num_points),
        points_world=points,
        obs_image_idx=obs_img,
        obs_point_idx=obs_pt,
        obs_xy=_project(cameras, poses, points[obs_pt], obs_img)
        + rng.normal(size=(len(obs_img), 2)),
        vc_image_idx1=i1,
        vc_image_idx2=i2,
        vc_xy1=_project(cameras, poses, x1, i1) + rng.normal(size=(num_vcs, 2)),
        vc_xy2=_project(cameras, poses, x2, i2) + rng.normal(size=(num_vcs, 2)),
        vc_x1_world=x1,
        vc_x2_world=x2,
        vc_prior_depth1=rng.uniform(3, 5, num_vcs),
        vc_prior_depth2=rng.uniform(3, 5, num_vcs),
        vc_prior_a=0.05 * rng.normal(size=num_vcs),
        vc_prior_b=0.05 * rng.normal(size=num_vcs),
        vc_kind=np.zeros(num_vcs, np.int64),
        vc_point3D_id1=np.full(num_vcs, -1),
        vc_point3D_id2=np.full(num_vcs, -1),
    )


def _perturbed(
    rec: pycolmap.Reconstruction,
    rng: np.random.Generator,
    deg: float,
    frac: float,
    scale: float = 1.0,
) -> pycolmap.Reconstruction:
    out = pycolmap.Reconstruction(rec)
    for image_id in sorted(out.images):
        image = out.images[image_id]
        P = image.cam_from_world().matrix()
        axis = rng.normal(size=3)
        dR = Rotation.from_rotvec(
            np.radians(deg) * axis / np.linalg.norm(axis)
        ).as_matrix()
        step = rng.normal(size=3)
        t = P[:, 3] + frac * np.linalg.norm(P[:, 3]) * step / np.linalg.norm(step)
        image.frame.set_cam_from_world(
            image.camera_id,
            pycolmap.Rigid3d(pycolmap.Rotation3d(dR @ P[:, :3]), scale * t),
        )
    return out


def _max_pair_error(result, gt: pycolmap.Reconstruction) -> float:
    pred = dict(zip(result.image_names, result.cam_from_world, strict=True))
    return max(p.error_deg for p in evaluate_poses(pred, poses_by_name(gt)).pairs)


@pytest.fixture(scope="module")
def gt_rec(dome_scene) -> pycolmap.Reconstruction:
    return pycolmap.Reconstruction(dome_scene / "gt" / "sparse")


def _vcs(scene: Path, priors_dir: Path):
    views = database.read_views(scene / "database.db")
    opts = augment.AugmentOptions(use_classic_matches=False, show_progress=False)
    return augment.compute_virtual_correspondences(views, read_priors(priors_dir), opts)


@pytest.fixture(scope="module")
def clean_vcs(dome_scene):
    return _vcs(dome_scene, dome_scene / "gt" / "priors")


@pytest.fixture(scope="module")
def noisy_vcs(dome_scene):
    return _vcs(dome_scene, dome_scene / "priors")


# ---------------------------------------------------------------- camera model


@pytest.mark.parametrize("model_name", list(CAMERAS))
def test_projection_matches_pycolmap(model_name, rng):
    camera = _camera(model_name)
    points = rng.normal(size=(500, 3)) * [1.0, 0.8, 0.5] + [0.0, 0.0, 3.0]
    xy, _ = project(points, np.tile(opencv_params(camera), (len(points), 1)))
    assert np.abs(xy - camera.img_from_cam(points)).max() < 1e-9


def test_unsupported_camera_model_is_refused():
    camera = pycolmap.Camera(
        model="SIMPLE_RADIAL_FISHEYE",
        width=64,
        height=48,
        params=np.array([50.0, 32.0, 24.0, 0.1]),
    )
    with pytest.raises(NotImplementedError, match="SIMPLE_RADIAL_FISHEYE"):
        opencv_params(camera)


# ---------------------------------------------------------------- residuals, Jacobian


@pytest.mark.parametrize("parametrization", list(Parametrization))
def test_jacobian_matches_finite_differences(parametrization, rng):
    problem = _random_problem(rng)
    options = GbaOptions(parametrization=parametrization, metric_prior_weight=3.0)
    x = pack(problem, options) + 0.05 * rng.normal(
        size=model.layout(problem, options).num_params
    )
    J = jacobian(x, problem, options).toarray()
    step = 1e-6
    J_fd = np.stack(
        [
            (
                residuals(x + step * e, problem, options)
                - residuals(x - step * e, problem, options)
            )
            / (2 * step)
            for e in np.eye(len(x))
        ],
        axis=1,
    )
    assert J.shape == J_fd.shape
    assert np.abs(J - J_fd).max() <= 1e-5 * max(1.0, np.abs(J_fd).max())
    assert (np.abs(J - J_fd) / np.maximum(1.0, np.abs(J_fd))).max() < 1e-5


def test_segments_give_the_same_linearization(rng):
    problem = _random_problem(rng, num_vcs=400)
    order = np.argsort(problem.vc_image_idx1 * 3 + problem.vc_image_idx2, kind="stable")
    problem = dataclasses.replace(
        problem,
        **{
            f.name: getattr(problem, f.name)[order]
            for f in dataclasses.fields(problem)
            if f.name.startswith("vc_")
        },
    )
    options = GbaOptions(metric_prior_weight=1.0)
    x = pack(problem, options) + 0.01 * rng.normal(
        size=model.layout(problem, options).num_params
    )
    segments = (
        model.image_segments(problem.vc_image_idx1),
        model.image_segments(problem.vc_image_idx2),
    )
    plain = model.linearize(x, problem, options)
    fast = model.linearize(x, problem, options, segments=segments)
    for name in ("vc_r", "vc_jpose", "vc_jvar"):
        np.testing.assert_allclose(
            getattr(fast, name), getattr(plain, name), rtol=1e-12, atol=1e-9
        )


@pytest.mark.parametrize("parametrization", list(Parametrization))
def test_residuals_vanish_at_ground_truth(parametrization, gt_rec, clean_vcs):
    problem = build_problem(
        gt_rec, clean_vcs.keypoints, clean_vcs.pairs, max_vcs_per_pair=200
    )
    # X1, X2: on the ground-truth rays at the ground-truth first-hit depths.
    cam = problem.cam_from_world
    o1, d1 = rays_world(problem.cameras, cam, problem.vc_image_idx1, problem.vc_xy1)
    o2, d2 = rays_world(problem.cameras, cam, problem.vc_image_idx2, problem.vc_xy2)
    z1 = np.einsum("ti,ti->t", cam[problem.vc_image_idx1, 2, :3], d1)
    z2 = np.einsum("ti,ti->t", cam[problem.vc_image_idx2, 2, :3], d2)
    x1 = o1 + (problem.vc_prior_depth1 / z1)[:, None] * d1
    x2 = o2 + (problem.vc_prior_depth2 / z2)[:, None] * d2
    gt = dataclasses.replace(problem, vc_x1_world=x1, vc_x2_world=x2)
    options = GbaOptions(parametrization=parametrization)
    r = residuals(pack(gt, options), gt, options).reshape(problem.num_vcs, -1)
    # The synthetic VC pixels themselves meet to ~1e-4 px (float32 surface samples).
    assert np.abs(r).max() < 1e-3
    # With X2 moved into the plane (o1, X1, o2) and its pixel re-rendered, exactly 0.
    n = np.cross(x1 - o1, o2 - o1)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    x2 = x2 - np.einsum("ti,ti->t", x2 - o1, n)[:, None] * n
    xy2 = _project(problem.cameras, cam, x2, problem.vc_image_idx2)
    exact = dataclasses.replace(gt, vc_x2_world=x2, vc_xy2=xy2)
    r = residuals(pack(exact, options), exact, options)
    assert np.abs(r).max() < 1e-6


# ---------------------------------------------------------------- solving


def test_converges_from_perturbed_poses(gt_rec, clean_vcs):
    start = _perturbed(gt_rec, np.random.default_rng(1), deg=10.0, frac=0.1)
    problem = build_problem(
        start, clean_vcs.keypoints, clean_vcs.pairs, max_vcs_per_pair=300
    )
    result = solve(problem, GbaOptions(max_iterations=100))
    assert result.summary.final_cost < 0.01 * result.summary.initial_cost
    assert _max_pair_error(result, gt_rec) < 0.1


def test_metric_prior_recovers_the_scale(gt_rec, noisy_vcs):
    # Realistic priors, a reconstruction at an arbitrary scale (0.37) and 2 degrees off.
    start = _perturbed(gt_rec, np.random.default_rng(2), deg=2.0, frac=0.05, scale=0.37)
    problem = build_problem(
        start, noisy_vcs.keypoints, noisy_vcs.pairs, max_vcs_per_pair=300
    )
    result = solve(problem, GbaOptions(metric_prior_weight=10.0, max_iterations=60))
    gt = poses_by_name(gt_rec)
    centres = np.array([-P[:, :3].T @ P[:, 3] for P in result.cam_from_world])
    gt_centres = np.array([-gt[n][:, :3].T @ gt[n][:, 3] for n in result.image_names])
    iu = np.triu_indices(len(centres), 1)
    ratio = (
        np.linalg.norm(centres[:, None] - centres[None], axis=2)[iu]
        / np.linalg.norm(gt_centres[:, None] - gt_centres[None], axis=2)[iu]
    )
    assert abs(np.median(ratio) - 1.0) < 0.05
    assert result.summary.fixed_image_idx == 0 and result.summary.scale_fix is None


@pytest.mark.parametrize("refine_points", [True, False])
def test_without_vcs_it_is_plain_bundle_adjustment(refine_points, gt_rec, rng):
    gt = poses_by_name(gt_rec)
    names = sorted(gt)
    cameras = tuple(
        gt_rec.cameras[gt_rec.find_image_with_name(n).camera_id] for n in names
    )
    poses = np.stack([gt[n] for n in names])
    points = rng.normal(size=(300, 3)) * [0.8, 0.8, 0.8] + [0.0, 0.9, 0.0]
    obs_img = np.tile(np.arange(len(names)), len(points))
    obs_pt = np.repeat(np.arange(len(points)), len(names))
    xy = _project(cameras, poses, points[obs_pt], obs_img)
    noisy = poses.copy()
    for k in range(1, len(names)):  # the gauge image stays: the frame is comparable
        noisy[k, :, :3] = (
            Rotation.from_rotvec(np.radians(2.0) * rng.normal(size=3) / 1.7).as_matrix()
            @ poses[k, :, :3]
        )
        noisy[k, :, 3] += 0.02 * rng.normal(size=3)
    problem = GbaProblem(
        image_ids=np.arange(1, len(names) + 1),
        image_names=tuple(names),
        cameras=cameras,
        cam_from_world=noisy,
        point3D_ids=np.arange(len(points)),
        points_world=points
        + (0.01 * rng.normal(size=points.shape) if refine_points else 0.0),
        obs_image_idx=obs_img,
        obs_point_idx=obs_pt,
        obs_xy=xy,
    )
    result = solve(
        problem, GbaOptions(refine_classic_points=refine_points, loss=LossType.LINEAR)
    )
    assert result.summary.final_rms_px < 1e-6
    assert _max_pair_error(result, gt_rec) < 1e-4
    if not refine_points:  # constant points define the frame: absolute poses come back
        np.testing.assert_allclose(result.cam_from_world, poses, atol=1e-6)


def test_scipy_solver_reaches_the_same_plain_ba_optimum(rng):
    problem = _random_problem(rng, num_points=30, num_vcs=0)
    options = GbaOptions(loss=LossType.LINEAR, max_iterations=200)
    lm = solve(problem, options)
    ref = solve(problem, dataclasses.replace(options, solver=Solver.SCIPY))
    assert lm.summary.final_cost == pytest.approx(ref.summary.final_cost, rel=1e-4)


def test_bad_inputs_raise_value_error(rng):
    problem = _random_problem(rng)
    with pytest.raises(ValueError, match="obs_xy"):
        dataclasses.replace(problem, obs_xy=problem.obs_xy[:, :1])
    with pytest.raises(ValueError, match="vc_image_idx2"):
        dataclasses.replace(problem, vc_image_idx2=problem.vc_image_idx2[:-1])
    with pytest.raises(ValueError, match="obs_point_idx"):
        dataclasses.replace(problem, obs_point_idx=problem.obs_point_idx + 100)
    with pytest.raises(ValueError, match="itself"):
        dataclasses.replace(problem, vc_image_idx2=problem.vc_image_idx1)
    with pytest.raises(ValueError, match="cam_from_world"):
        dataclasses.replace(problem, cam_from_world=problem.cam_from_world[:, :, :3])
    with pytest.raises(ValueError, match="x has shape"):
        residuals(np.zeros(3), problem)
    with pytest.raises(ValueError, match="gauge_image_idx"):
        solve(problem, GbaOptions(gauge_image_idx=7))


def test_refine_reconstruction_from_the_database(
    dome_scene, gt_rec, clean_vcs, tmp_path
):
    db = tmp_path / "database.db"
    shutil.copyfile(dome_scene / "database.db", db)
    # The VCs as augment writes them (computed once by the clean_vcs fixture).
    database.write_virtual_correspondences(
        db, clean_vcs.keypoints, clean_vcs.pairs, clean_vcs.geometries
    )
    keypoints, pairs, num_classic = vc_tuples_from_db(db)
    start = _perturbed(gt_rec, np.random.default_rng(3), deg=1.0, frac=0.02)
    before = {i: im.cam_from_world().matrix() for i, im in start.images.items()}
    refined, result = refine_reconstruction(
        start,
        keypoints,
        pairs,
        image_id_to_num_classic=num_classic,
        max_vcs_per_pair=200,
    )
    for image_id, P in before.items():  # the input is not modified
        np.testing.assert_array_equal(
            start.images[image_id].cam_from_world().matrix(), P
        )
    assert _max_pair_error(result, gt_rec) < 0.1
    for image_id, P in zip(result.image_ids, result.cam_from_world, strict=True):
        np.testing.assert_allclose(
            refined.images[int(image_id)].cam_from_world().matrix(), P, atol=1e-9
        )
    export_ply(result, tmp_path / "vc.ply", tmp_path / "points.ply")
    cloud = trimesh.load(tmp_path / "vc.ply")
    assert len(cloud.vertices) == 2 * result.summary.num_vcs
    np.testing.assert_allclose(
        np.asarray(cloud.vertices)[: result.summary.num_vcs], result.x1_world
    )
    assert len(trimesh.load(tmp_path / "points.ply").vertices) == len(result.image_ids)
