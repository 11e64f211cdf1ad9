"""The synthetic world: ground truth is self-consistent, deterministic, as specified."""

from __future__ import annotations

import hashlib
import itertools
import json
from pathlib import Path

import numpy as np
import pycolmap
import pytest

from colmap_vc import raycast
from colmap_vc.evaluation import rotation_angle_deg
from colmap_vc.priors import read_priors
from colmap_vc.synthetic import SynthOptions, generate
from colmap_vc.synthetic.layout import (
    LayoutOptions,
    Preset,
    make_layout,
    pair_angle_deg,
)


def _gt(scene: Path) -> pycolmap.Reconstruction:
    return pycolmap.Reconstruction(scene / "gt" / "sparse")


def test_gt_model_loads_and_matches_the_scene_spec(dome_scene):
    rec = _gt(dome_scene)
    spec = json.loads((dome_scene / "scene.json").read_text())
    assert rec.num_reg_images() == len(spec["cameras"]) == 6
    by_name = {im.name: im for im in rec.images.values()}
    for cam in spec["cameras"]:
        image = by_name[cam["name"]]
        np.testing.assert_allclose(
            image.cam_from_world().matrix(), cam["cam_from_world"], atol=1e-12
        )
        np.testing.assert_allclose(image.camera.params, cam["params"])
        assert (dome_scene / "images" / cam["name"]).is_file()
    # The text model says the same as the binary one.
    text = pycolmap.Reconstruction()
    text.read_text(str(dome_scene / "gt" / "sparse"))
    assert {im.name for im in text.images.values()} == set(by_name)


def test_gt_surface_maps_reproject_to_their_surface_points(dome_scene):
    rec = _gt(dome_scene)
    priors = read_priors(dome_scene / "gt" / "priors")
    checked = 0
    for image in rec.images.values():
        data = np.load(dome_scene / "gt" / "surface" / (Path(image.name).stem + ".npz"))
        by_id = {p.person_id: p for p in priors.images[image.name].persons}
        for pid in np.unique(data["person_id"]):
            sel = data["person_id"] == pid
            person = by_id[int(pid)]
            points = raycast.surface_points(
                person.vertices_cam,
                person.faces,
                data["face"][sel].astype(np.int64),
                data["bary"][sel].astype(np.float64),
            )
            xy = image.camera.img_from_cam(points)
            err = np.linalg.norm(xy - data["xy"][sel], axis=1)
            assert err.max() < 0.5, f"{image.name} person {pid}: {err.max():.3f} px"
            checked += int(sel.sum())
    assert checked > 10_000


def test_gt_priors_agree_across_cameras_through_the_gt_poses(dome_scene):
    """The same person's GT mesh, moved from camera i to camera j by the GT poses."""
    rec = _gt(dome_scene)
    priors = read_priors(dome_scene / "gt" / "priors")
    images = sorted(rec.images.values(), key=lambda im: im.name)
    for a, b in itertools.combinations(images, 2):
        pa = {p.person_id: p for p in priors.images[a.name].persons}
        pb = {p.person_id: p for p in priors.images[b.name].persons}
        for pid in set(pa) & set(pb):
            T_a = a.cam_from_world().matrix()
            T_b = b.cam_from_world().matrix()
            world = (pa[pid].vertices_cam - T_a[:, 3]) @ T_a[:, :3]
            in_b = world @ T_b[:, :3].T + T_b[:, 3]
            # float32 storage of the priors: ~1e-6 m at a few metres.
            assert np.abs(in_b - pb[pid].vertices_cam).max() < 1e-4


def test_predicted_priors_follow_the_noise_model(dome_scene):
    gt = read_priors(dome_scene / "gt" / "priors")
    pred = read_priors(dome_scene / "priors")
    rotations, joint_px = [], []
    rec = _gt(dome_scene)
    cams = {im.name: im.camera for im in rec.images.values()}
    for name, image_prior in pred.images.items():
        truth = {p.person_id: p for p in gt.images[name].persons}
        for p in image_prior.persons:
            t = truth[p.person_id]
            # Kabsch rotation between the centred meshes: the global orientation error
            # (plus some articulation and shape error).
            A = p.vertices_cam - p.vertices_cam.mean(0)
            B = t.vertices_cam - t.vertices_cam.mean(0)
            U, _, Vt = np.linalg.svd(A.T @ B)
            R = U @ np.diag([1, 1, np.sign(np.linalg.det(U @ Vt))]) @ Vt
            rotations.append(rotation_angle_deg(R))
            # The refit keeps the predicted joints near the person in 2D.
            xy = cams[name].img_from_cam(p.keypoints_cam)
            true_xy = cams[name].img_from_cam(t.keypoints_cam)
            joint_px.append(np.median(np.linalg.norm(xy - true_xy, axis=1)))
            assert p.surface_map is not None and 0 < len(p.surface_map) < 1.05 * len(
                t.surface_map
            )
            assert 0.7 <= p.confidence <= 0.95
    assert 3.0 < np.median(rotations) < 20.0
    assert np.median(joint_px) < 15.0


def test_clean_priors_are_the_ground_truth(dome_scene):
    gt = read_priors(dome_scene / "gt" / "priors")
    for prior in gt.images.values():
        for p in prior.persons:
            assert p.confidence == 1.0
            assert p.keypoints_valid is not None and p.keypoints_valid.any()


def test_database_has_the_true_intrinsics_and_features(dome_scene):
    from colmap_vc import database

    views = database.read_views(dome_scene / "database.db")
    rec = _gt(dome_scene)
    by_name = {im.name: im for im in rec.images.values()}
    assert set(views.image_names) == set(by_name)
    for name, cam_id, n in zip(
        views.image_names, views.camera_ids, views.num_keypoints, strict=True
    ):
        np.testing.assert_allclose(
            views.cameras[int(cam_id)].params, by_name[name].camera.params
        )
        assert views.cameras[int(cam_id)].model == by_name[name].camera.model
        assert 50 < n <= 2048 * 2  # SIFT cap (COLMAP may add a second orientation)
    assert len(database.read_matches(dome_scene / "database.db")) > 0


def _digest(folder: Path) -> dict[str, str]:
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


def test_same_seed_gives_the_same_files(tmp_path):
    opts = dict(num_cameras=2, width=160, height=120, make_database=False, num_people=1)
    a = generate("dome", tmp_path / "a", SynthOptions(seed=3, **opts)).out_dir
    b = generate("dome", tmp_path / "b", SynthOptions(seed=3, **opts)).out_dir
    c = generate("dome", tmp_path / "c", SynthOptions(seed=4, **opts)).out_dir
    assert _digest(a) == _digest(b)
    assert _digest(a)["images/cam00.jpg"] != _digest(c)["images/cam00.jpg"]


def test_existing_output_is_not_overwritten(tmp_path):
    out = tmp_path / "scene"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    with pytest.raises(FileExistsError, match="overwrite"):
        generate(
            "dome",
            out,
            SynthOptions(num_cameras=2, width=80, height=60, make_database=False),
        )
    assert (out / "keep.txt").read_text() == "mine"


def _angles(layout) -> list[float]:
    return [
        pair_angle_deg(a, b, np.array([0.0, 0.0, 1.0]))
        for a, b in itertools.combinations(layout.cameras, 2)
    ]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_dome_layout_is_all_around(seed):
    layout = make_layout(
        Preset.DOME, np.random.default_rng(seed), num_phenotypes=6, num_poses=8
    )
    assert 8 <= len(layout.cameras) <= 16
    angles = np.array(_angles(layout))
    assert (angles >= 90).mean() > 0.25 and angles.max() > 120
    for cam in layout.cameras:
        r = np.linalg.norm(cam.centre - np.r_[0.0, 0.0, 1.0])
        assert 2.5 < r < 5.5
        assert cam.centre[2] > 0.5


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_dense_layout_overlaps(seed):
    layout = make_layout(
        Preset.DENSE, np.random.default_rng(seed), num_phenotypes=6, num_poses=8
    )
    steps = [
        pair_angle_deg(a, b, np.array([0.0, 0.0, 1.0]))
        for a, b in zip(layout.cameras[:-1], layout.cameras[1:], strict=True)
    ]
    assert min(steps) >= 3 and max(steps) <= 25


@pytest.mark.parametrize("angle", [0.0, 60.0, 150.0])
def test_pair_layout_has_the_requested_angle(angle):
    layout = make_layout(
        Preset.PAIR,
        np.random.default_rng(0),
        num_phenotypes=6,
        num_poses=8,
        options=LayoutOptions(pair_angle_deg=angle),
    )
    assert len(layout.cameras) == 2
    target = np.r_[layout.people[0].position_xy, 1.0]
    assert pair_angle_deg(*layout.cameras, target) == pytest.approx(angle, abs=1e-6)


def test_bad_options_are_rejected():
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError, match="num_people"):
        make_layout(
            Preset.DOME,
            rng,
            num_phenotypes=6,
            num_poses=8,
            options=LayoutOptions(num_people=4),
        )
    with pytest.raises(ValueError, match="camera_model"):
        make_layout(
            Preset.DOME,
            rng,
            num_phenotypes=6,
            num_poses=8,
            options=LayoutOptions(camera_model="FISHEYE_X"),
        )
    with pytest.raises(ValueError):
        Preset("cathedral")
