"""Prior estimators: the Anny fit on synthetic landmarks; MediaPipe on real photos."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest
from scipy.spatial.transform import Rotation

from colmap_vc import raycast
from colmap_vc.estimators import EstimatorOptions, body, fit, prior
from colmap_vc.priors import read_priors, write_priors
from colmap_vc.structs import ImagePrior, ScenePriors
from colmap_vc.synthetic import bodies as body_lib

POSE2SIM = Path(__file__).resolve().parents[2] / "shared" / "data" / "pose2sim_single"
# Body frame (+Y forward, +Z up) -> camera (x right, y down, z forward), facing it.
PEOPLE = Path(__file__).resolve().parent / "data" / "pose2sim_people.json"
FACING_CAMERA = np.array([[-1.0, 0, 0], [0, 0, -1], [0, -1, 0]])


@pytest.fixture(scope="module")
def template() -> body.FitTemplate:
    return body.load_template()


@pytest.fixture(scope="module")
def camera() -> pycolmap.Camera:
    return pycolmap.Camera(
        model="OPENCV",
        width=1088,
        height=1920,
        params=[1680.0, 1680.0, 540.0, 960.0, -0.001, 0.002, 0.0, 0.0],
    )


def _scene(
    template: body.FitTemplate,
    camera: pycolmap.Camera,
    phenotype: int,
    pose: int,
    yaw_deg: float,
    rng: np.random.Generator,
    noise_px: float = 1.5,
    noise_m: float = 0.01,
) -> tuple[body.BodyLandmarks, np.ndarray, np.ndarray]:
    """Noisy landmarks of a body 4 m in front of the camera, true joints, vertices."""
    model = template.model
    rot = FACING_CAMERA @ Rotation.from_euler("z", yaw_deg, degrees=True).as_matrix()
    verts = body_lib.pose_body(model, phenotype, pose)
    t = np.array([0.1, 0.0, 4.0]) - rot @ np.array([0.0, 0.0, 0.9])
    cam_from_body = np.column_stack([rot, t])
    lm = body.landmarks_from_mesh(template, verts, cam_from_body, camera)
    noisy = body.BodyLandmarks(
        xy_img=lm.xy_img + rng.normal(0, noise_px, lm.xy_img.shape),
        points_3d=lm.points_3d + rng.normal(0, noise_m, lm.points_3d.shape),
        visibility=lm.visibility,
    )
    verts_cam = verts @ rot.T + t
    return noisy, body_lib.joints(model, verts_cam), verts_cam


@pytest.mark.parametrize(
    ("phenotype", "pose", "yaw_deg"),
    [(2, 0, 20.0), (0, 1, -60.0), (3, 2, 150.0), (5, 5, 90.0), (1, 7, -150.0)],
)
def test_fit_recovers_joints_and_reprojects(
    template, camera, rng, phenotype, pose, yaw_deg
):
    lm, true_joints, _ = _scene(template, camera, phenotype, pose, yaw_deg, rng)
    fitted = fit.fit_body(lm, camera, template)
    err = fitted.joints_cam - true_joints
    depth = true_joints[:, 2].mean()
    # Shape is up to a depth shift along the viewing direction (size <-> distance):
    # centred joints within a few cm, depth within a few percent.
    centred = np.linalg.norm(err - err.mean(axis=0), axis=1)
    assert np.median(centred) < 0.025 and centred.max() < 0.06
    assert abs(err.mean(axis=0)[2]) < 0.04 * depth
    assert np.median(fitted.reprojection_error_px[fitted.used_2d]) < 2.5
    assert not fitted.relabelled


def test_fit_with_known_phenotype_is_within_a_few_cm(template, camera, rng):
    lm, true_joints, _ = _scene(template, camera, 2, 1, 30.0, rng)
    fitted = fit.fit_body(lm, camera, template, fit.FitOptions(phenotype=2))
    assert fitted.shape == (2, 2, 0.0)
    assert np.linalg.norm(fitted.joints_cam - true_joints, axis=1).max() < 0.05


@pytest.mark.parametrize("yaw_deg", [0.0, 180.0])
def test_left_right_swap_is_fixed(template, camera, rng, yaw_deg):
    lm, true_joints, _ = _scene(template, camera, 2, 0, yaw_deg, rng)
    assert fit.facing_cosine(lm) > 0.9
    swapped = lm.relabelled()
    assert fit.facing_cosine(swapped) < -0.9
    fitted = fit.fit_body(swapped, camera, template)
    assert fitted.relabelled
    err = np.linalg.norm(fitted.joints_cam - true_joints, axis=1)
    assert np.median(err) < 0.08  # left joints on the left: not mirrored
    unfixed = fit.fit_body(
        swapped, camera, template, fit.FitOptions(fix_left_right=False)
    )
    assert not unfixed.relabelled


def test_fit_rejects_too_few_landmarks(template, camera, rng):
    lm, _, _ = _scene(template, camera, 2, 0, 0.0, rng)
    vis = lm.visibility.copy()
    vis[
        [body.BLAZEPOSE_NAMES.index(n) for n in ("left_shoulder", "right_shoulder")]
    ] = 0.0  # no shoulders
    with pytest.raises(ValueError, match="too few usable 2D landmarks"):
        fit.fit_body(
            body.BodyLandmarks(
                xy_img=lm.xy_img, points_3d=lm.points_3d, visibility=vis
            ),
            camera,
            template,
        )


def test_silhouette_matches_raycasting(template, camera, rng):
    _, _, verts_cam = _scene(template, camera, 0, 2, 40.0, rng)
    faces = template.model.faces
    sil = prior.render_silhouette(camera, verts_cam, faces)
    xy = raycast.pixel_grid(camera.width, camera.height)
    dirs = raycast.rays_cam(camera, xy)
    scene = raycast.build_scene([(verts_cam, faces)])
    hit = raycast.first_hits(scene, np.zeros_like(dirs), dirs)[1] >= 0
    assert prior.mask_iou(sil, hit.reshape(camera.height, camera.width)) > 0.95


def test_prior_from_fit_is_valid_and_consistent(template, camera, rng, tmp_path):
    lm, _, true_verts = _scene(template, camera, 4, 3, -30.0, rng)
    true_mask = prior.render_silhouette(camera, true_verts, template.model.faces)
    fitted = fit.fit_body(lm, camera, template)
    person, iou = prior.prior_from_fit(fitted, camera, true_mask, surface_stride_px=2)
    assert iou > 0.7
    sm = person.surface_map
    assert sm is not None and len(sm) > 1000
    # The map's surface points lie on the rays of their pixels (ray-cast hits).
    pts = raycast.surface_points(
        person.vertices_cam, person.faces, sm.face_idx, sm.bary
    )
    xy = camera.img_from_cam(pts)
    assert np.abs(xy - sm.xy_img).max() < 1e-4
    px = np.floor(sm.xy_img).astype(int)
    assert person.mask is not None and person.mask[px[:, 1], px[:, 0]].all()
    # 17 joints (12 are BlazePose landmarks) + 7 surface landmarks, all valid here.
    assert person.keypoints_valid is not None and person.keypoints_valid.shape == (24,)
    assert person.keypoints_valid.sum() == 12 + len(body.SURFACE_LANDMARKS)
    # The surface keypoints are vertices of the fitted mesh.
    kp_cam = person.keypoints_cam
    assert kp_cam is not None
    gap = np.linalg.norm(kp_cam[17:, None] - person.vertices_cam[None], axis=2).min(1)
    assert gap.max() < 1e-9
    # The priors format accepts it.
    write_priors(
        ScenePriors(
            images={"a.jpg": ImagePrior(image_name="a.jpg", persons=(person,))}
        ),
        tmp_path / "priors",
        templates={body.TEMPLATE_NAME: template.model.faces},
        image_sizes={"a.jpg": (camera.width, camera.height)},
    )
    back = read_priors(tmp_path / "priors")
    assert back.images["a.jpg"].persons[0].template == body.TEMPLATE_NAME


# --- MediaPipe on real photos (pose2sim_single) ------------------------------------


def _pose2sim_cameras() -> dict[str, pycolmap.Camera]:
    doc = json.loads((POSE2SIM / "cameras.json").read_text())
    cameras = {}
    for cam in doc["cameras"]:
        k = np.array(cam["K"])
        w, h = cam["image_size_wh"]
        camera = pycolmap.Camera(
            model="OPENCV",
            width=w,
            height=h,
            params=[k[0, 0], k[1, 1], k[0, 2], k[1, 2], *cam["dist_k1k2p1p2"]],
        )
        for rel in cam["images"].values():
            cameras[Path(rel).name] = camera
    return cameras


@pytest.fixture(scope="module")
def mediapipe_run(tmp_path_factory: pytest.TempPathFactory):
    pytest.importorskip("ai_edge_litert")
    if not POSE2SIM.is_dir():
        pytest.skip(f"{POSE2SIM} not available")
    from colmap_vc.estimators import run_estimator

    cameras = _pose2sim_cameras()
    image_dir = tmp_path_factory.mktemp("photos")
    real = ["cam01_t010.jpg", "cam03_t050.jpg"]
    for name in real:
        shutil.copy(POSE2SIM / "images" / name, image_dir / name)
    photo = cv2.imread(str(POSE2SIM / "images" / real[0]))
    h, w = photo.shape[:2]
    # Nobody: a flat grey image.
    cv2.imwrite(str(image_dir / "empty.png"), np.full((h, w, 3), 128, np.uint8))
    # A tiny person: the whole photo shrunk 12x, pasted on grey.
    tiny = np.full_like(photo, 128)
    small = cv2.resize(photo, (w // 12, h // 12), interpolation=cv2.INTER_AREA)
    tiny[900 : 900 + small.shape[0], 500 : 500 + small.shape[1]] = small
    cv2.imwrite(str(image_dir / "tiny.png"), tiny)
    # A person cut by the frame: the photo shifted down by 60 %.
    cut = np.full_like(photo, 128)
    cut[int(0.6 * h) :] = photo[: h - int(0.6 * h)]
    cv2.imwrite(str(image_dir / "cut.png"), cut)
    for name in ("empty.png", "tiny.png", "cut.png"):
        cameras[name] = cameras[real[0]]
    cameras = {n: cameras[n] for n in [*real, "empty.png", "tiny.png", "cut.png"]}
    out = tmp_path_factory.mktemp("priors")
    summary = run_estimator(
        image_dir, out, cameras=cameras, options=EstimatorOptions(show_progress=False)
    )
    return summary, cameras, real


def test_mediapipe_finds_the_person(mediapipe_run):
    summary, cameras, real = mediapipe_run
    priors = read_priors(summary.priors_path)
    labels = json.loads(PEOPLE.read_text())["pose2sim_single"]
    for name in real:
        persons = priors.images[name].persons
        # The man; the bystander in the background of cam01 and cam02 may be found
        # too (EstimatorOptions.detector_levels = 3), nobody else.
        assert 1 <= len(persons) <= len(labels[name]), summary.skipped.get(name)
        camera = cameras[name]
        reports = [r for r in summary.report.persons if r.image_name == name]
        assert all(r.kept and r.mask_iou > 0.5 for r in reports)
        for person in persons:
            depth = np.median(person.vertices_cam[:, 2])
            assert 1.5 < depth < 12.0  # the man 2-6 m from the cameras, bystander ~9
            sil = prior.render_silhouette(camera, person.vertices_cam, person.faces)
            assert person.mask is not None and prior.mask_iou(sil, person.mask) > 0.5
            valid = person.keypoints_valid
            assert valid is not None and valid.sum() >= 8
            xy = person.keypoints_xy[valid]
            assert np.all((xy >= 0) & (xy <= [camera.width, camera.height]))
            assert person.surface_map is not None and len(person.surface_map) > 500
            assert person.person_id is None and 0 < person.confidence <= 1


def test_mediapipe_skips_bad_images_with_a_reason(mediapipe_run):
    summary, _, _ = mediapipe_run
    priors = read_priors(summary.priors_path)
    assert priors.images["empty.png"].persons == ()
    assert summary.skipped["empty.png"] == "no person detected"
    for name in ("tiny.png", "cut.png"):  # skipped with a reason, or found: no crash
        assert (name in summary.skipped) != bool(priors.images[name].persons)
        assert summary.skipped.get(name, "x")
    assert summary.num_images == 5


def test_priors_refuse_when_no_image_can_be_used(tmp_path):
    # Database names that are not in the folder, or images of another size than
    # their cameras: nothing was looked for, so no priors (augment would take
    # empty ones for images without people).
    pytest.importorskip("ai_edge_litert")
    from colmap_vc.estimators import run_estimator

    images = tmp_path / "images"
    images.mkdir()
    cv2.imwrite(str(images / "small.png"), np.full((48, 64, 3), 128, np.uint8))
    camera = pycolmap.Camera(
        model="PINHOLE", width=128, height=96, params=[100.0, 100.0, 64.0, 48.0]
    )
    cameras = {"small.png": camera, "missing.png": camera}
    with pytest.raises(ValueError, match="none of the 2 images could be used"):
        run_estimator(
            images,
            tmp_path / "priors",
            cameras=cameras,
            options=EstimatorOptions(show_progress=False),
        )
    assert not (tmp_path / "priors" / "priors.json").exists()


def test_pose2sim_one_instant_end_to_end(tmp_path):
    """priors -> augment -> map on the 4 photos of one instant: every camera registers
    and the relative poses are near the calibration (classic COLMAP registers none)."""
    pytest.importorskip("ai_edge_litert")
    if not POSE2SIM.is_dir():
        pytest.skip(f"{POSE2SIM} not available")
    from colmap_vc import augment, mapping
    from colmap_vc.estimators import run_estimator
    from colmap_vc.evaluation import evaluate_poses

    doc = json.loads((POSE2SIM / "cameras.json").read_text())
    names = [f"{c['name']}_t030.jpg" for c in doc["cameras"]]
    gt = {
        f"{c['name']}_t030.jpg": np.c_[np.array(c["R"]), np.array(c["t"])]
        for c in doc["cameras"]
    }
    cameras = {n: c for n, c in _pose2sim_cameras().items() if n in names}
    images = tmp_path / "images"
    images.mkdir()
    for name in names:
        shutil.copy(POSE2SIM / "images" / name, images / name)
    run_estimator(
        images,
        tmp_path / "priors",
        cameras=cameras,
        options=EstimatorOptions(show_progress=False),
    )
    db = tmp_path / "database.db"
    for name in names:  # SIFT with the known intrinsics, as a user would
        pycolmap.extract_features(
            db,
            images,
            image_names=[name],
            camera_mode=pycolmap.CameraMode.PER_IMAGE,
            reader_options=pycolmap.ImageReaderOptions(
                camera_model="OPENCV",
                camera_params=",".join(f"{p:.17g}" for p in cameras[name].params),
            ),
            extraction_options=pycolmap.FeatureExtractionOptions(num_threads=2),
            device=pycolmap.Device.cpu,
        )
    pycolmap.match_exhaustive(db, device=pycolmap.Device.cpu)
    augment.run(db, tmp_path / "priors", augment.AugmentOptions(show_progress=False))
    rec, summary = mapping.run(
        db,
        images,
        tmp_path / "sparse",
        mapping.MappingOptions(num_threads=2, show_progress=False),
    )
    assert summary.num_registered == 4, summary.unregistered
    pred = {im.name: im.cam_from_world().matrix() for im in rec.images.values()}
    metrics = evaluate_poses(pred, gt)
    # Measured (bench/pose2sim.py): median 4.7 deg at this instant; cameras 48-151
    # degrees apart, so a mirrored or failed solution is far above this bound.
    assert metrics.median_error_deg < 12.0


def test_priors_warn_when_the_database_guessed_the_focal_length(tmp_path, caplog):
    """A database whose camera has no known focal length (COLMAP's guess, as
    for frames without EXIF): the meshes' depth follows the guess, and `priors`
    says so."""
    pytest.importorskip("ai_edge_litert")
    from colmap_vc.estimators import run_estimator

    images = tmp_path / "images"
    images.mkdir()
    grey = np.random.default_rng(0).integers(0, 255, (96, 128, 3), dtype=np.uint8)
    cv2.imwrite(str(images / "frame.png"), grey)
    db = tmp_path / "database.db"
    pycolmap.extract_features(db, images, device=pycolmap.Device.cpu)
    caplog.set_level("WARNING", logger="colmap_vc.estimators")
    summary = run_estimator(
        images,
        tmp_path / "priors",
        database_path=db,
        options=EstimatorOptions(show_progress=False),
    )
    assert summary.num_images == 1
    assert "1 of 1 images" in caplog.text and "no known focal length" in caplog.text
