"""Mapping: augmented databases register where classic ones fail; bad input is clear."""

from __future__ import annotations

import collections
import dataclasses
import hashlib
import json
import shutil
import sqlite3

import cv2
import numpy as np
import pyceres
import pycolmap
import pytest
from scipy.spatial.transform import Rotation

from colmap_vc import augment, database, mapping
from colmap_vc.baselines import colmap_incremental
from colmap_vc.evaluation import (
    camera_distance_ratio,
    evaluate_poses,
    evaluate_reconstruction,
    poses_by_name,
)
from colmap_vc.keypoint_ba import KeypointBaOptions
from colmap_vc.meshalign import mesh_alignment_poses
from colmap_vc.metric_scale import PERSON_SIZE_SD
from colmap_vc.outputs import marker_name
from colmap_vc.priors import read_priors


@pytest.fixture(scope="module")
def augmented(dome_scene, tmp_path_factory):
    db = tmp_path_factory.mktemp("map") / "database.db"
    shutil.copyfile(dome_scene / "database.db", db)
    augment.run(
        db, dome_scene / "gt" / "priors", augment.AugmentOptions(show_progress=False)
    )
    return db


def test_augmented_dome_registers_every_image_accurately(
    dome_scene, augmented, tmp_path
):
    rec, summary = mapping.run(
        augmented,
        dome_scene / "images",
        tmp_path / "sparse",
        mapping.MappingOptions(num_threads=2),
    )
    assert summary.num_registered == 6 and not summary.unregistered
    metrics = evaluate_reconstruction(
        rec, pycolmap.Reconstruction(dome_scene / "gt" / "sparse")
    )
    assert metrics.auc["15"] > 90  # clean priors
    assert (summary.model_dir / "images.bin").exists()
    # In metres, from the people (the synthetic world is metric).
    gt = pycolmap.Reconstruction(dome_scene / "gt" / "sparse")
    ratio = camera_distance_ratio(poses_by_name(rec), poses_by_name(gt))
    assert summary.metric_scale is not None and abs(ratio - 1.0) < 0.03, ratio
    # Clean priors: every view of both people gives the same scale. The priors
    # carry the people's ids, which are not their indices in the priors.
    assert summary.metric_scale.spread < 0.02, summary.metric_scale
    # Its uncertainty is the people's shared size error (two people), not the
    # views' agreement: it covers the truth without claiming the views' 2%.
    scale = json.loads((summary.model_dir / "metric_scale.json").read_text())
    assert scale["num_people"] == 2 and scale["relative_pose"] == 0.0
    assert scale["uncertainty"] >= PERSON_SIZE_SD / np.sqrt(2) > scale["spread"]
    assert abs(ratio - 1.0) < 2 * scale["uncertainty"]
    assert summary.model_dir == tmp_path / "sparse" / "0"
    ran = json.loads((summary.model_dir / mapping.OPTIONS_FILE).read_text())
    assert ran["options"]["num_threads"] == 2 and ran["registered"] == 6
    assert ran["database"] == str(augmented.resolve())
    # Clean priors: the camera check moves no camera (none turned, none off).
    assert summary.re_posed == {} and ran["re_posed"] == {}
    # The written points: none behind its camera, errors as stored.
    written = pycolmap.Reconstruction(summary.model_dir)
    errors = np.array([p.error for p in written.points3D.values()])
    written.update_point_3d_errors()
    again = np.array([p.error for p in written.points3D.values()])
    assert written.num_points3D() > 100 and np.allclose(errors, again)
    assert errors.max() < 1000.0  # a point behind a camera errs by 1e150 px


READERS = (
    "read_views",
    "read_keypoints",
    "read_matches",
    "read_two_view_geometries",
    "read_virtual_correspondences",
    "read_person_associations",
    "read_run_info",
)


@pytest.mark.parametrize("gba", [False, True], ids=["keypoint BA", "GBA"])
def test_map_reads_each_input_from_the_database_once(
    dome_scene, augmented, tmp_path, monkeypatch, gba
):
    """The images, what augment wrote, the two-view geometries and the priors are
    read once; the refinement, the checks, the metric scale and the reasons for
    unregistered images get them in memory (pycolmap's mapper reads its matches
    from the database itself)."""
    calls: collections.Counter[str] = collections.Counter()

    def counted(name, read):
        def wrapper(*args, **kwargs):
            calls[name] += 1
            return read(*args, **kwargs)

        return wrapper

    for name in READERS:
        monkeypatch.setattr(database, name, counted(name, getattr(database, name)))
    monkeypatch.setattr(
        "colmap_vc.mapping.priors.read_priors", counted("read_priors", read_priors)
    )
    options = mapping.MappingOptions(
        keypoint_ba_options=KeypointBaOptions(surface_tracks=gba)
    )
    _, summary = mapping.run(
        augmented,
        dome_scene / "images",
        tmp_path / "sparse",
        options,
        priors_path=dome_scene / "gt" / "priors",
    )
    assert summary.num_registered == 6 and summary.metric_scale is not None
    once = {
        "read_views",
        "read_two_view_geometries",
        "read_virtual_correspondences",
        "read_person_associations",
        "read_run_info",
        "read_priors",
    }
    assert dict(calls) == dict.fromkeys(once, 1), calls


def test_the_written_points_lose_the_refinements_outliers(dome_scene, rng):
    """An observation behind its camera, or more than ten Cauchy scales from its
    point, leaves the model; a point left with one view leaves too; the rest and
    their errors stay."""
    rec = pycolmap.Reconstruction(dome_scene / "gt" / "sparse")
    for point_id in list(rec.point3D_ids()):
        rec.delete_point3D(point_id)
    ids = sorted(rec.reg_image_ids())[:3]
    X = rng.normal(0, 0.3, (20, 3)) + np.array([0.0, -0.9, 0.0])
    behind = (
        rec.image(ids[0]).projection_center()
        - 0.5 * rec.image(ids[0]).viewing_direction()
    )
    X = np.vstack([X, behind])
    uv = {}
    for i in ids:  # loop over three images: every point's pixel
        image = rec.image(i)
        T = image.cam_from_world().matrix()
        Xc = X @ T[:, :3].T + T[:, 3]
        Xc[:, 2] = np.abs(Xc[:, 2])  # the point behind image ids[0]: some pixel
        uv[i] = np.asarray(rec.camera(image.camera_id).img_from_cam(Xc))
    uv[ids[0]][0] += [300.0, 0.0]  # point 1: one view far off (three views)
    uv[ids[1]][1] += [0.0, 300.0]  # point 2: far off in one view ...
    for i in ids:
        rec.image(i).points2D = pycolmap.Point2DList(
            [pycolmap.Point2D(p) for p in uv[i]]
        )
    for k in range(len(X)):  # loop over the points
        track = pycolmap.Track()
        for i in ids if k != 1 else ids[1:]:  # ... with two views
            track.add_element(i, k)
        rec.add_point3D(X[k], track)
    dropped = mapping.outputs.drop_outlier_observations_inplace(rec, 5.0)
    assert dropped == 1 + 2 + 1  # point 1's bad view, point 2, the one behind
    assert rec.point3D(1).track.length() == 2 and not rec.exists_point3D(2)
    assert rec.point3D(21).track.length() == 2
    assert rec.num_points3D() == 20
    assert max(p.error for p in rec.points3D.values()) < 1e-6
    unseen = [rec.image(i).name for i in sorted(rec.reg_image_ids())[3:]]
    left = mapping.outputs.leave_out_unobserved_inplace(rec)  # nothing places them
    assert sorted(left) == sorted(unseen) and "nothing places it" in left[unseen[0]]
    assert sorted(rec.reg_image_ids()) == ids


def test_a_plain_database_maps_as_plain_colmap_and_says_why(dome_scene, tmp_path):
    db = tmp_path / "plain.db"
    shutil.copyfile(dome_scene / "database.db", db)
    try:
        _rec, summary = mapping.run(db, dome_scene / "images", tmp_path / "sparse")
    except RuntimeError as exc:  # classic matching fails on the dome: say why
        assert "no model" in str(exc) and "cam0" in str(exc)
    else:
        assert summary.num_registered + len(summary.unregistered) == 6
        assert all(isinstance(r, str) and r for r in summary.unregistered.values())


def test_existing_output_is_kept_without_overwrite(dome_scene, augmented, tmp_path):
    out = tmp_path / "sparse"
    out.mkdir()
    (out / "mine.txt").write_text("keep")
    with pytest.raises(FileExistsError, match="overwrite"):
        mapping.run(augmented, dome_scene / "images", out)
    assert (out / "mine.txt").read_text() == "keep"


def test_no_model_raises_with_the_reason(dome_scene, tmp_path):
    db = tmp_path / "nomatch.db"
    shutil.copyfile(dome_scene / "database.db", db)
    with sqlite3.connect(db) as conn:
        conn.execute("DELETE FROM two_view_geometries")
    with pytest.raises(RuntimeError, match="no verified image pair"):
        mapping.run(db, dome_scene / "images", tmp_path / "sparse")


def test_verified_pairs_without_any_model_are_not_called_a_separate_component(
    augmented,
):
    """No model at all (the mapper found no initial pair): each image's reason
    says so, not that it lies in a component apart from registered images."""
    from colmap_vc.mapping.outputs import why_unregistered

    views = database.read_views(augmented)
    geometries = database.read_two_view_geometries(augmented, include_vc=True)
    reasons = why_unregistered(views, geometries, None)
    assert len(reasons) == 6
    for why in reasons.values():
        assert "no model could be started" in why and "component" not in why, why


def test_the_mesh_mapper_without_priors_says_so(dome_scene, tmp_path):
    """`--mapper mesh` on a database `augment` never saw: a clear error, and the
    user's database is only read."""
    db = tmp_path / "plain.db"
    shutil.copyfile(dome_scene / "database.db", db)
    before = hashlib.sha256(db.read_bytes()).hexdigest()
    with pytest.raises(ValueError, match="needs the priors"):
        mapping.run(
            db,
            dome_scene / "images",
            tmp_path / "sparse",
            mapping.MappingOptions(mapper=mapping.Mapper.MESH),
        )
    assert hashlib.sha256(db.read_bytes()).hexdigest() == before


def test_missing_inputs(dome_scene, tmp_path):
    with pytest.raises(FileNotFoundError, match="database"):
        mapping.run(tmp_path / "none.db", dome_scene / "images", tmp_path / "o")
    with pytest.raises(FileNotFoundError, match="image folder"):
        mapping.run(dome_scene / "database.db", tmp_path / "noimages", tmp_path / "o")


def test_without_verified_pairs_meshes_and_keypoint_tracks_still_register(
    dome_scene, tmp_path, caplog
):
    """No two-view geometry at all (every RANSAC failed): the auto mapper places the
    cameras by mesh alignment and the keypoint BA refines them from identity tracks."""
    db = tmp_path / "noverify.db"
    shutil.copyfile(dome_scene / "database.db", db)
    augment.run(db, dome_scene / "priors", augment.AugmentOptions(show_progress=False))
    with sqlite3.connect(db) as conn:
        conn.execute("DELETE FROM two_view_geometries")
    caplog.set_level("INFO", logger="colmap_vc.mapping.choice")
    rec, summary = mapping.run(
        db,
        dome_scene / "images",
        tmp_path / "sparse",
        mapping.MappingOptions(num_threads=2, show_progress=False),
    )
    assert summary.num_registered == 6
    # It says why: there was no incremental model to judge (it read "contradicts
    # the mesh prior (median 180 deg)").
    assert "the incremental mapper found no model: mesh-initialised" in caplog.text
    models = sorted(p.name for p in (tmp_path / "sparse").iterdir())
    # The mesh-initialised model replaced the incremental one: one answer, at 0/
    # as COLMAP names it, no superseded model beside it.
    assert models == [mapping.OUTPUT_MARKER, "0"] and summary.model_dir.name == "0"
    ran = json.loads((summary.model_dir / mapping.OPTIONS_FILE).read_text())
    assert ran["options"]["mapper"] == "auto" and ran["registered"] == 6
    gt = pycolmap.Reconstruction(dome_scene / "gt" / "sparse")
    mesh_only = evaluate_poses(
        mesh_alignment_poses(read_priors(dome_scene / "priors")), poses_by_name(gt)
    )
    refined = evaluate_reconstruction(rec, gt)
    assert rec.num_points3D() > 0  # keypoint tracks, triangulated
    # Realistic priors: the meshes are off by many degrees, the keypoint tracks fix it.
    assert refined.median_error_deg < 0.5 * mesh_only.median_error_deg
    # Without the keypoint BA there is nothing to build on: no model, with the reason.
    with pytest.raises(RuntimeError, match="no model"):
        mapping.run(
            db,
            dome_scene / "images",
            tmp_path / "sparse2",
            mapping.MappingOptions(num_threads=2, keypoint_ba=False),
        )


def test_a_camera_that_contradicts_the_meshes_is_left_out(dome_scene):
    """Flip one camera of the ground truth: only it leaves, with the reason."""
    import numpy as np
    from scipy.spatial.transform import Rotation

    rec = pycolmap.Reconstruction(dome_scene / "gt" / "sparse")
    priors = read_priors(dome_scene / "priors")  # realistic meshes
    assert mapping.leave_out_prior_outliers_inplace(rec, priors, 90.0) == {}
    image = sorted(rec.images.values(), key=lambda im: im.name)[2]
    T = image.cam_from_world().matrix()
    flip = Rotation.from_euler("y", 150, degrees=True).as_matrix()
    rec.frame(image.frame_id).rig_from_world = pycolmap.Rigid3d(
        pycolmap.Rotation3d(flip @ T[:, :3]), flip @ T[:, 3]
    )
    left = mapping.leave_out_prior_outliers_inplace(rec, priors, 90.0)
    assert (
        list(left) == [image.name] and "contradicts the body meshes" in left[image.name]
    )
    assert not rec.image(image.image_id).has_pose
    assert rec.num_reg_images() == len(rec.images) - 1
    assert np.isfinite(T).all()


def _ring_of_cameras(turn):
    """Six right cameras on a circle 4 m out around three upright people (point
    clouds, y their long axis), cam00's middle person turned by ``turn`` about its
    centre, cam03 seeing only that person: the model and its priors."""
    from scipy.spatial.transform import Rotation

    from colmap_vc.structs import ImagePrior, PersonPrior, ScenePriors

    rng = np.random.default_rng(0)
    centres = ([-0.8, 0.0, 0.0], [0.0, 0.0, 0.5], [0.8, 0.0, 0.0])
    people = [rng.normal(scale=[0.2, 0.5, 0.1], size=(60, 3)) + c for c in centres]
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(
        pycolmap.Camera(
            camera_id=1,
            model="PINHOLE",
            width=640,
            height=480,
            params=[500, 500, 320, 240],
        )
    )
    images = {}
    for i in range(6):  # cameras on a circle, 4 m out, looking at the people
        a = 2 * np.pi * i / 6
        R = Rotation.from_euler("y", -a).as_matrix()
        t = -R @ (4.0 * np.array([np.sin(a), 0.0, -np.cos(a)]))
        name = f"cam{i:02d}.jpg"
        rec.add_image_with_trivial_frame(
            pycolmap.Image(name=name, camera_id=1, image_id=i + 1),
            pycolmap.Rigid3d(pycolmap.Rotation3d(R), t),
        )
        persons = []
        for k, X in enumerate(people):
            if i == 3 and k != 1:
                continue  # cam03 sees the middle person only
            if i == 0 and k == 1:  # cam00 (three people: the reference) turned it
                X = (X - X.mean(axis=0)) @ turn.T + X.mean(axis=0)
            persons.append(
                PersonPrior(
                    vertices_cam=X @ R.T + t,
                    faces=np.zeros((0, 3), dtype=np.int64),
                    person_id=k,
                )
            )
        images[name] = ImagePrior(image_name=name, persons=tuple(persons))
    return rec, ScenePriors(images=images)


def _turn_pose_inplace(rec, image_id, turn):
    """Turn an image's camera by ``turn`` (camera frame), its priors as they are."""
    image = rec.image(image_id)
    T = image.cam_from_world().matrix()
    rec.frame(image.frame_id).rig_from_world = pycolmap.Rigid3d(
        pycolmap.Rotation3d(turn @ T[:, :3]), turn @ T[:, 3]
    )


def test_one_turned_mesh_of_the_most_crowded_image_leaves_no_right_camera_out():
    """Each pair of images is judged by its own meshes, not through one reference
    image: six right cameras around three people, the most crowded image's
    middle person turned front to back, and one image seeing only that person.
    Through the reference that image's every pair was 180 deg off (it left);
    by its own pairs only one pair is, and no camera leaves."""
    from scipy.spatial.transform import Rotation

    turn = Rotation.from_euler("y", 180, degrees=True).as_matrix()
    rec, priors = _ring_of_cameras(turn)
    assert mapping.leave_out_prior_outliers_inplace(rec, priors, 90.0) == {}
    assert rec.num_reg_images() == 6
    # The same check still leaves out cam03 posed on the mirror side.
    _turn_pose_inplace(rec, 4, turn)
    assert list(mapping.leave_out_prior_outliers_inplace(rec, priors, 90.0)) == [
        "cam03.jpg"
    ]


def test_a_camera_that_tilts_its_people_leaves_a_turned_mesh_does_not():
    """The people's up check: a mesh turned front to back keeps its long axis,
    so no right camera leaves; a camera rolled 40 deg about its axis tilts its
    people 40 deg from the up the other images give them and leaves, with the
    reason; rolled 20 deg (under the 30 deg a wrong camera needs) it stays, and
    so does one rolled 40 deg among meshes whose own tilts err by 15 deg
    (within 4.5 times the scene's median)."""
    from scipy.spatial.transform import Rotation

    options = mapping.MappingOptions()
    bound = (options.max_people_up_deg, options.people_up_ratio)
    rec, priors = _ring_of_cameras(
        Rotation.from_euler("y", 180, degrees=True).as_matrix()
    )
    names = [f"cam{i:02d}.jpg" for i in range(6)]
    dev = mapping.priors.people_up_deviations_deg(rec, priors, names)
    assert max(max(d.values()) for d in dev.values()) < 1.0
    assert mapping.leave_out_tilted_inplace(rec, priors, *bound) == {}
    _turn_pose_inplace(rec, 3, Rotation.from_euler("z", 20, degrees=True).as_matrix())
    assert mapping.leave_out_tilted_inplace(rec, priors, *bound) == {}
    _turn_pose_inplace(rec, 3, Rotation.from_euler("z", 20, degrees=True).as_matrix())
    left = mapping.leave_out_tilted_inplace(rec, priors, *bound)
    assert (
        list(left) == ["cam02.jpg"] and "tilts its people 40 deg" in left["cam02.jpg"]
    )
    assert rec.num_reg_images() == 5 and not rec.image(3).has_pose
    # Meshes tilted 15 deg each, about random horizontal axes: 40 deg is noise.
    rec, priors = _ring_of_cameras(np.eye(3))
    rng = np.random.default_rng(1)
    noisy = {}
    for name, ip in priors.images.items():
        persons = []
        for p in ip.persons:
            axis = np.r_[rng.normal(size=1), 0.0, rng.normal(size=1)]
            tilt = Rotation.from_rotvec(np.radians(15) * axis / np.linalg.norm(axis))
            c = p.vertices_cam.mean(axis=0)
            moved = (p.vertices_cam - c) @ tilt.as_matrix().T + c
            persons.append(dataclasses.replace(p, vertices_cam=moved))
        noisy[name] = dataclasses.replace(ip, persons=tuple(persons))
    priors = dataclasses.replace(priors, images=noisy)
    _turn_pose_inplace(rec, 3, Rotation.from_euler("z", 40, degrees=True).as_matrix())
    assert mapping.leave_out_tilted_inplace(rec, priors, *bound) == {}
    # Judged by the 30 deg alone, that camera would leave.
    alone = mapping.leave_out_tilted_inplace(
        pycolmap.Reconstruction(rec), priors, bound[0], 0.0
    )
    assert list(alone) == ["cam02.jpg"]
    # With the check off (0) nothing is judged.
    rec, priors = _ring_of_cameras(np.eye(3))
    _turn_pose_inplace(rec, 3, Rotation.from_euler("z", 40, degrees=True).as_matrix())
    assert mapping.leave_out_tilted_inplace(rec, priors, 0.0, bound[1]) == {}
    assert list(mapping.leave_out_tilted_inplace(rec, priors, *bound)) == ["cam02.jpg"]


def test_two_images_the_mesh_check_leaves_are_mapped_again(
    dome_scene, augmented, tmp_path, caplog
):
    """When the mesh check leaves out all but two images, the two are mapped again
    on their own (their verified two-view geometry, as two images mapped from the
    start) and adjusted, not adjusted from the larger model's poses: from those,
    pose2sim_single t070's cam01-cam03 ended 27 deg off once cam02 left (5.8 deg
    mapped on their own)."""
    caplog.set_level("INFO", logger="colmap_vc")
    rec, summary = mapping.run(
        augmented,
        dome_scene / "images",
        tmp_path / "sparse",
        # Any deviation contradicts: the check leaves images out until two remain.
        mapping.MappingOptions(num_threads=2, max_image_prior_deviation_deg=1e-12),
    )
    assert summary.num_registered == 2 and len(summary.unregistered) == 4
    assert all(
        "contradicts the body meshes" in r for r in summary.unregistered.values()
    )
    # The reasons are kept beside the model, not only in the log.
    ran = json.loads((summary.model_dir / mapping.OPTIONS_FILE).read_text())
    assert ran["unregistered"] == summary.unregistered
    again = [r.getMessage() for r in caplog.records if "mapped again" in r.getMessage()]
    assert len(again) == 1
    assert all(name in again[0] for name in summary.registered), again
    adjusted = [
        r.getMessage()
        for r in caplog.records
        if "surface-VC observations" in r.getMessage()
    ]
    # The larger model's adjustment, then the two images' own.
    assert len(adjusted) == 2 and all("weighing 6 per image" in m for m in adjusted)
    assert {im.name for im in rec.images.values() if im.has_pose} == set(
        summary.registered
    )
    metrics = evaluate_reconstruction(
        rec, pycolmap.Reconstruction(dome_scene / "gt" / "sparse")
    )
    (pair,) = [p for p in metrics.pairs if p.registered]
    assert pair.rotation_deg < 1.0  # clean priors


def test_the_meshes_do_not_judge_two_cameras_classic_matches_place(dome_scene):
    """The `auto` mapper's check of a model against the meshes skips the pairs of
    two images that classic matches place (their relative pose is SIFT's, and a
    mesh turned front to back is 180 deg off), and still judges every other pair."""
    from scipy.spatial.transform import Rotation

    from colmap_vc.mapping.priors import prior_deviation_deg

    rec = pycolmap.Reconstruction(dome_scene / "gt" / "sparse")
    priors = read_priors(dome_scene / "priors")  # realistic meshes
    names = sorted(im.name for im in rec.images.values())
    assert prior_deviation_deg(rec, priors) < 35.0
    flip = Rotation.from_euler("y", 150, degrees=True).as_matrix()
    turned = set(names[:3])
    for image in rec.images.values():
        if image.name in turned:
            T = image.cam_from_world().matrix()
            rec.frame(image.frame_id).rig_from_world = pycolmap.Rigid3d(
                pycolmap.Rotation3d(flip @ T[:, :3]), flip @ T[:, 3]
            )
    assert prior_deviation_deg(rec, priors) > 35.0
    assert prior_deviation_deg(rec, priors, frozenset(names)) == 0.0
    # Pinned turned cameras are still judged against the cameras people place.
    assert prior_deviation_deg(rec, priors, frozenset(turned)) > 35.0


def test_a_model_sift_places_is_kept_though_the_meshes_contradict_it(tmp_path, caplog):
    """A dense scene that SIFT solves, priors with the people's ids (`augment`
    links every pair that shares a person, also those it leaves to SIFT), and for
    `map` every other mesh turned front to back: the incremental model stays."""
    import dataclasses
    import logging

    from colmap_vc.priors import write_priors
    from colmap_vc.synthetic import SynthOptions, generate

    scene = tmp_path / "scene"
    generate(
        "dense",
        scene,
        SynthOptions(
            seed=0,
            num_cameras=8,
            num_people=1,
            noise="realistic",
            num_threads=2,
            with_ids=True,
        ),
    )
    db = tmp_path / "database.db"
    shutil.copyfile(scene / "database.db", db)
    summary = augment.run(
        db, scene / "gt" / "priors", augment.AugmentOptions(show_progress=False)
    )
    assert len(summary.pairs) < 8 * 7 // 2  # SIFT solved the others: no VCs
    priors = read_priors(scene / "gt" / "priors")
    turn = np.diag([-1.0, 1.0, -1.0])  # 180 deg about the camera's vertical

    def turned(v: np.ndarray) -> np.ndarray:
        return (v - v.mean(axis=0)) @ turn.T + v.mean(axis=0)

    images = {
        name: dataclasses.replace(
            image,
            persons=[
                dataclasses.replace(p, vertices_cam=turned(p.vertices_cam))
                for p in image.persons
            ],
        )
        if k % 2
        else image
        for k, (name, image) in enumerate(sorted(priors.images.items()))
    }
    write_priors(dataclasses.replace(priors, images=images), tmp_path / "turned")
    caplog.set_level(logging.INFO, logger="colmap_vc.mapping.choice")
    rec, _ = mapping.run(
        db,
        scene / "images",
        tmp_path / "sparse",
        mapping.MappingOptions(num_threads=2, show_progress=False),
        priors_path=tmp_path / "turned",
    )
    assert "classic matches place every image" in caplog.text
    gt = pycolmap.Reconstruction(scene / "gt" / "sparse")
    assert evaluate_reconstruction(rec, gt).auc["15"] > 95


@pytest.mark.parametrize("where", ["project", "foreign"])
def test_overwrite_never_removes_what_colmap_vc_did_not_write(
    dome_scene, augmented, tmp_path, where
):
    """`map --overwrite` into the folder holding the database, or into a folder
    colmap-vc did not write, is refused and removes nothing."""
    project = tmp_path / "project"
    shutil.copytree(dome_scene / "images", project / "images")
    shutil.copyfile(augmented, project / "database.db")
    out = project if where == "project" else tmp_path / "mine"
    out.mkdir(exist_ok=True)
    (out / "notes.txt").write_text("keep me")
    before = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*"))
    with pytest.raises(FileExistsError, match="--overwrite refused"):
        mapping.run(
            project / "database.db",
            project / "images",
            out,
            mapping.MappingOptions(show_progress=False),
            overwrite=True,
        )
    assert sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*")) == before


def test_overwrite_replaces_a_folder_map_wrote(dome_scene, augmented, tmp_path):
    out = tmp_path / "sparse"
    options = mapping.MappingOptions(show_progress=False)
    mapping.run(augmented, dome_scene / "images", out, options)
    assert (out / mapping.OUTPUT_MARKER).is_file()
    _, summary = mapping.run(
        augmented, dome_scene / "images", out, options, overwrite=True
    )
    assert summary.num_registered >= 5


def test_a_two_view_geometry_stored_without_its_pose_gets_one() -> None:
    """COLMAP's matchers store E (or F) and the inliers but no relative pose: a
    two-image database whose one pair classic matching solved still maps."""
    import numpy as np
    from scipy.spatial.transform import Rotation

    from colmap_vc.database import TwoViewGeometryRow
    from colmap_vc.evaluation import relative_pose_error
    from colmap_vc.mapping.strategies import _pose_from_geometry

    rng = np.random.default_rng(0)
    camera = pycolmap.Camera(
        model="SIMPLE_PINHOLE", width=640, height=480, params=[500.0, 320.0, 240.0]
    )
    X = rng.uniform([-2, -2, 5], [2, 2, 9], (200, 3))
    R = Rotation.from_euler("y", 20, degrees=True).as_matrix()
    t = np.array([-1.0, 0.1, 0.2])
    kp1 = np.asarray(camera.img_from_cam(X))
    kp2 = np.asarray(camera.img_from_cam(X @ R.T + t))
    E = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]]) @ R
    row = TwoViewGeometryRow(
        image_id1=1,
        image_id2=2,
        inlier_matches=np.c_[np.arange(200), np.arange(200)],
        config=int(pycolmap.TwoViewGeometryConfiguration.CALIBRATED),
        F=None,
        E=E,
        H=None,
        qvec_wxyz=np.zeros(4),  # as COLMAP 3.8 writes it: no pose
        tvec=np.zeros(3),
    )
    assert row.cam2_from_cam1 is None
    pose = _pose_from_geometry(row, camera, camera, kp1, kp2)
    assert pose is not None
    rot_err, t_err = relative_pose_error(pose, np.c_[R, t / np.linalg.norm(t)])
    assert rot_err < 0.1 and t_err < 0.1


def test_the_classic_baseline_is_colmap_itself(dome_scene, tmp_path):
    """`colmap_incremental` is COLMAP's mapper at its defaults, intrinsics known:
    no colmap-vc step, the scene's database untouched, the same model pycolmap
    gives by itself."""
    db = dome_scene / "database.db"
    before = hashlib.sha256(db.read_bytes()).hexdigest()
    rec = colmap_incremental(db, dome_scene / "images", tmp_path / "classic")
    assert hashlib.sha256(db.read_bytes()).hexdigest() == before
    assert sorted(p.name for p in (tmp_path / "classic").iterdir()) == sorted(
        str(k) for k in range(len(list((tmp_path / "classic").iterdir())))
    )  # COLMAP's numbered models only: no colmap-vc marker, options or copy
    copy = tmp_path / "copy.db"
    shutil.copyfile(db, copy)
    pycolmap.set_random_seed(0)
    models = pycolmap.incremental_mapping(
        copy,
        dome_scene / "images",
        tmp_path / "direct",
        options=pycolmap.IncrementalPipelineOptions(
            num_threads=1,
            random_seed=0,
            ba_refine_focal_length=False,
            ba_refine_extra_params=False,
        ),
    )
    own = max((m.num_reg_images() for m in models.values()), default=0)
    assert (0 if rec is None else rec.num_reg_images()) == own


def _with_pillars(scene, out):
    """A copy of the scene's images with vertical pillars (world Z up) on a ring
    around the people, drawn through each image's true camera."""
    gt = pycolmap.Reconstruction(scene / "gt" / "sparse")
    out.mkdir()
    angles = np.linspace(0, 2 * np.pi, 48, endpoint=False)
    feet = np.c_[7 * np.cos(angles), 7 * np.sin(angles), np.zeros(len(angles))]
    heads = feet + np.array([0.0, 0.0, 3.0])
    for image in gt.images.values():
        picture = cv2.imread(str(scene / "images" / image.name))
        T = image.cam_from_world().matrix()
        camera = gt.camera(image.camera_id)
        for a, b in zip(feet, heads, strict=True):  # loop over pillars
            for dx in (-0.15, 0.15):  # its two edges
                ends = np.stack([a, b]) + np.array([dx, 0.0, 0.0])
                cam = ends @ T[:, :3].T + T[:, 3]
                if (cam[:, 2] < 0.5).any():
                    continue
                uv = np.asarray(camera.img_from_cam(cam))
                p, q = (tuple(np.round(x * 16).astype(int)) for x in uv)
                cv2.line(picture, p, q, (40, 40, 40), 2, cv2.LINE_AA, 4)
        cv2.imwrite(str(out / image.name), picture)
    return gt


@pytest.fixture(scope="module")
def augmented_realistic(dome_scene, tmp_path_factory):
    """The dome's database augmented with its realistic priors (noisy meshes)."""
    db = tmp_path_factory.mktemp("map_realistic") / "database.db"
    shutil.copyfile(dome_scene / "database.db", db)
    augment.run(db, dome_scene / "priors", augment.AugmentOptions(show_progress=False))
    return db


def test_gravity_from_vertical_lines_is_measured_and_kept(
    dome_scene, augmented_realistic, tmp_path
):
    """Pillars in the images and realistic people: every camera's up is
    measured, the people's ups agree with the turn it makes, the cameras agree
    on it after the adjustment (written beside the model), and the model is
    better than without it."""
    gt = _with_pillars(dome_scene, tmp_path / "images")
    runs = {
        gravity: mapping.run(
            augmented_realistic,
            tmp_path / "images",
            tmp_path / f"sparse_{gravity}",
            mapping.MappingOptions(num_threads=2, gravity=gravity),
            priors_path=dome_scene / "priors",
        )
        for gravity in (False, True)
    }
    summary = runs[True][1]
    assert summary.num_registered == runs[False][1].num_registered == 6
    auc = {g: evaluate_reconstruction(r, gt).auc["15"] for g, (r, _) in runs.items()}
    assert auc[True] > auc[False] + 2.0, auc
    found = json.loads((summary.model_dir / "gravity.json").read_text())
    assert found["used"] and len(found["cameras"]) >= 4 and found["rejected"] is None
    assert found["people"]["z"] < 3.0 and found["people"]["turn_deg"] > 0.5
    for name, camera in found["cameras"].items():
        truth = gt.find_image_with_name(name).cam_from_world().rotation.matrix()[:, 2]
        assert float(np.dot(camera["up_cam"], truth)) > 0.999
        assert camera["residual_deg"] < 1.0


def test_exact_people_overrule_vertical_lines_a_degree_off(
    dome_scene, augmented, tmp_path
):
    """The same pillars with exact people (the scene's true meshes and
    keypoints): the model is exact without the lines, whose ups (each within
    2.6 deg) would turn the cameras by about a degree. The people's ups agree
    exactly before and not after: the step is undone, the model stays exact."""
    gt = _with_pillars(dome_scene, tmp_path / "images")
    rec, summary = mapping.run(
        augmented,
        tmp_path / "images",
        tmp_path / "sparse",
        mapping.MappingOptions(num_threads=2, gravity=True),
    )
    assert summary.num_registered == 6
    assert evaluate_reconstruction(rec, gt).median_error_deg < 0.01
    found = json.loads((summary.model_dir / "gravity.json").read_text())
    assert len(found["cameras"]) >= 4 and not found["used"]
    assert found["people"]["z"] > 3.0 and found["people"]["spread_before_deg"] < 0.01


def test_ups_of_lines_that_are_not_vertical_are_undone_by_the_people(
    dome_scene, augmented_realistic, tmp_path, monkeypatch
):
    """Every camera's "vertical" lines meet 18 deg off its up, each in its own
    direction (a geodesic dome's edges do that), with a confident 0.5 deg error:
    the ups agree with each other within the up check's cone, and the adjustment
    turns the cameras to them. Their people's ups (realistic meshes) say the
    turn is wrong, so the model is put back as the people made it, and
    gravity.json says why. Six cameras and meshes whose ups scatter by 7 deg
    are near the test's reach: z = 3.3 here; at 22 deg one camera leaves the up
    check, the others turn less, z = 2.8 and the step stays (docs/real-data.md,
    "The people judge the step")."""
    from colmap_vc.gravity import Gravity
    from colmap_vc.mapping import up as up_step

    gt = pycolmap.Reconstruction(dome_scene / "gt" / "sparse")
    rng = np.random.default_rng(0)

    def slanted(image_dir, groups, cameras, persons, options=None):
        out = {}
        for name in sorted(groups):  # loop over cameras
            true = gt.find_image_with_name(name).cam_from_world().rotation.matrix()
            up = true[:, 2]  # world Z in the camera
            axis = np.cross(up, rng.normal(size=3))
            turn = Rotation.from_rotvec(np.radians(18) * axis / np.linalg.norm(axis))
            out[name] = Gravity(
                up_cam=turn.apply(up),
                sigma_rad=float(np.radians(0.5)),
                num_segments=40,
                num_images=1,
                lines_px=np.zeros((0, 4)),
                people_up_cam=up,
            )
        return out

    def run(out: str) -> tuple[pycolmap.Reconstruction, mapping.MappingSummary]:
        # One thread: two runs compared to 1e-9 must be the same run (with two,
        # COLMAP's mapper could take another path on a loaded machine).
        return mapping.run(
            augmented_realistic,
            dome_scene / "images",
            tmp_path / out,
            mapping.MappingOptions(num_threads=1),
            priors_path=dome_scene / "priors",
        )

    monkeypatch.setattr(up_step, "measure_gravity", lambda *a, **k: {})
    without, _ = run("without")  # no lines measured: the people's model
    monkeypatch.setattr(up_step, "measure_gravity", slanted)
    rec, summary = run("sparse")
    found = json.loads((summary.model_dir / "gravity.json").read_text())
    assert len(found["cameras"]) == 6 and not found["left_out_deg"]
    assert not found["used"] and found["people"]["z"] > 3.0
    assert "the turn is wrong" in found["rejected"]
    assert found["people"]["turn_deg"] > 5.0
    assert summary.num_registered == without.num_reg_images() == 6
    for name in found["cameras"]:  # the poses put back exactly
        a = rec.find_image_with_name(name).cam_from_world().matrix()
        b = without.find_image_with_name(name).cam_from_world().matrix()
        assert np.allclose(a, b, atol=1e-9)


def test_when_the_checks_leave_fewer_than_two_images_there_is_no_model(
    dome_scene, augmented, tmp_path, monkeypatch
):
    """A check that leaves all but one image out (here the gravity step, made
    to): the run fails with the reasons, and the output folder holds no model
    (a failed run leaves only its marker), not the mapper's, which the checks
    contradicted."""
    from colmap_vc.mapping import pipeline

    real = pipeline.refine_with_gravity_inplace

    def all_but_one_out(rec, *args, **kwargs):
        result = real(rec, *args, **kwargs)
        names = sorted(rec.image(i).name for i in rec.reg_image_ids())
        why = {n: "left out: contradicted (test)" for n in names[1:]}
        for name in names[1:]:
            rec.deregister_frame(rec.find_image_with_name(name).frame_id)
        return dataclasses.replace(result, cameras_left_out=why)

    monkeypatch.setattr(pipeline, "refine_with_gravity_inplace", all_but_one_out)
    out = tmp_path / "sparse"
    with pytest.raises(RuntimeError, match="no model left") as err:
        mapping.run(
            augmented,
            dome_scene / "images",
            out,
            mapping.MappingOptions(num_threads=2, gravity=True),
        )
    assert "5 image(s)" in str(err.value) and "1 remain" in str(err.value)
    assert "contradicted (test)" in str(err.value)
    assert sorted(p.name for p in out.iterdir()) == [marker_name("map")]


def test_two_images_placed_by_people_alone_come_with_a_warning(
    dome_scene, tmp_path, caplog
):
    """Two views of people make a weak pair (pose2sim: 5-11 deg median): map
    registers them and says so."""
    from conftest import extract_database

    views = database.read_views(dome_scene / "database.db")
    camera = dict(zip(views.image_names, views.camera_ids.tolist(), strict=True))
    names = sorted(views.image_names)[:2]
    db = extract_database(
        dome_scene / "images",
        names,
        {n: views.cameras[camera[n]] for n in names},
        tmp_path / "pair.db",
    )
    augment.run(db, dome_scene / "priors", augment.AugmentOptions(show_progress=False))
    caplog.set_level("WARNING", logger="colmap_vc.mapping.pipeline")
    _, summary = mapping.run(
        db,
        dome_scene / "images",
        tmp_path / "sparse",
        mapping.MappingOptions(num_threads=2, show_progress=False),
    )
    assert summary.num_registered == 2
    assert "two images placed by their people alone" in caplog.text
    # The scale's uncertainty holds the relative pose's part, written beside it.
    scale = summary.metric_scale
    assert scale is not None and 0.0 < scale.relative_pose < scale.uncertainty
    people_part = scale.uncertainty**2 - scale.relative_pose**2
    assert people_part >= PERSON_SIZE_SD**2 / scale.num_people - 1e-12
    written = json.loads((summary.model_dir / "metric_scale.json").read_text())
    assert written["relative_pose"] == pytest.approx(scale.relative_pose)


def test_a_guessed_focal_length_leaves_the_scale_arbitrary_and_says_so(
    dome_scene, augmented, tmp_path, caplog
):
    """Without a known focal length (COLMAP's guess, as for frames without EXIF)
    the people's depth is as wrong as the guess: `map` warns, and leaves the
    model at COLMAP's scale rather than claim metres."""
    db = tmp_path / "guessed.db"
    shutil.copyfile(augmented, db)
    with sqlite3.connect(db) as con:
        con.execute("UPDATE cameras SET prior_focal_length = 0")
    caplog.set_level("INFO", logger="colmap_vc.mapping.pipeline")
    _, summary = mapping.run(
        db,
        dome_scene / "images",
        tmp_path / "sparse",
        mapping.MappingOptions(num_threads=2, show_progress=False),
    )
    assert summary.num_registered == 6
    assert summary.metric_scale is None
    assert "without a known focal length" in summary.no_scale
    assert not (summary.model_dir / "metric_scale.json").exists()
    assert "6 of 6 images have no known focal length" in caplog.text


def test_colmaps_own_log_lines_only_with_debug_logging(
    dome_scene, tmp_path, capfd, caplog
):
    """COLMAP's mapper writes its own lines (glog, to stderr): on a database it
    can start no model from, an error line. Without --verbose `map` reports that
    in its own words, so COLMAP's lines stay off; with it they are shown."""
    import logging

    from colmap_vc.mapping import strategies
    from colmap_vc.mapping.options import MappingOptions

    db = tmp_path / "nomatch.db"
    shutil.copyfile(dome_scene / "database.db", db)
    with sqlite3.connect(db) as conn:
        conn.execute("DELETE FROM two_view_geometries")
    names = sorted(p.name for p in (dome_scene / "images").iterdir())
    before = pycolmap.logging.minloglevel
    for verbose in (False, True):
        caplog.set_level(logging.DEBUG if verbose else logging.INFO)
        out = tmp_path / f"sparse_{verbose}"
        out.mkdir()
        models = strategies.incremental(
            db, dome_scene / "images", out, MappingOptions(), names
        )
        assert not models
        glog = [
            line for line in capfd.readouterr().err.splitlines() if line[:1] in "IWE"
        ]
        assert bool(glog) == verbose, glog
        assert pycolmap.logging.minloglevel == before


def test_colmap_quiet_silences_glog_inside_its_block_only(capfd, tmp_path, monkeypatch):
    """The same switch is around colmap-vc's own Ceres solves (gba/ceres.py).
    pyceres links its own glog (its solves' "Linear solver failure" lines):
    both are quiet inside the block, and pyceres's writes no log file into the
    working folder (left as it is, it does after COLMAP's first line)."""
    import logging

    from colmap_vc.colmap_log import colmap_quiet

    monkeypatch.chdir(tmp_path)
    quiet, verbose = logging.getLogger("quiet.test"), logging.getLogger("verbose.test")
    quiet.setLevel(logging.INFO)
    verbose.setLevel(logging.DEBUG)
    before = (
        pycolmap.logging.minloglevel,
        pyceres.logging.minloglevel,
        pyceres.logging.logtostderr,
    )
    with colmap_quiet(quiet):
        pycolmap.logging.warning("inside the quiet block")
        pyceres.logging.warning("pyceres inside the quiet block")
    with colmap_quiet(verbose):
        pycolmap.logging.warning("inside the verbose block")
        pyceres.logging.warning("pyceres inside the verbose block")
    pycolmap.logging.warning("after the blocks")
    err = capfd.readouterr().err
    assert "inside the quiet block" not in err
    assert "inside the verbose block" in err and "after the blocks" in err
    assert "pyceres inside the verbose block" in err
    after = (
        pycolmap.logging.minloglevel,
        pyceres.logging.minloglevel,
        pyceres.logging.logtostderr,
    )
    assert after == before
    assert not [p.name for p in tmp_path.iterdir() if ".log." in p.name]


def test_anonymous_people_take_the_identity_their_association_gave_them():
    from colmap_vc.database_schema import AssociationMethod
    from colmap_vc.structs import ImagePrior, PersonPrior, ScenePriors

    def person(person_id):
        return PersonPrior(
            vertices_cam=np.zeros((3, 3)),
            faces=np.zeros((0, 3), dtype=np.int64),
            person_id=person_id,
        )

    priors = ScenePriors(
        images={
            n: ImagePrior(image_name=n, persons=tuple(map(person, ids)))
            for n, ids in (
                ("a.jpg", (None, None)),
                ("b.jpg", (None, 4)),
                ("c.jpg", (None,)),
            )
        }
    )
    link = dict(method=AssociationMethod.JOINT, score=1.0)
    associations = [  # a#1 = b#0 = c#0 (a chain), a#0 with nobody
        database.PersonAssociation(
            image_id1=1, image_id2=2, person_id1=1, person_id2=0, **link
        ),
        database.PersonAssociation(
            image_id1=2, image_id2=3, person_id1=0, person_id2=0, **link
        ),
    ]
    out = mapping.apply_associations(
        priors, associations, {"a.jpg": 1, "b.jpg": 2, "c.jpg": 3}
    )
    ids = {n: [p.person_id for p in ip.persons] for n, ip in out.images.items()}
    # one new identity for the chain, above the ids the priors already use
    assert ids["a.jpg"][1] == ids["b.jpg"][0] == ids["c.jpg"][0] >= 5
    assert ids["a.jpg"][0] is None  # associated with nobody: stays anonymous
    assert ids["b.jpg"][1] == 4  # a given id is kept
    assert mapping.apply_associations(priors, [], {}) is priors
