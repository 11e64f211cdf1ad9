"""augment: VC geometry against ground truth, database contract, bad input."""

from __future__ import annotations

import dataclasses
import itertools
import shutil
import sqlite3
from pathlib import Path

import numpy as np
import pycolmap
import pytest

from colmap_vc import augment, database
from colmap_vc.evaluation import relative_pose, rotation_angle_deg
from colmap_vc.priors import PriorsError, read_priors, write_priors
from colmap_vc.structs import HitKind, ImagePrior, ScenePriors
from colmap_vc.verification import epipolar_errors_px


def _gt_poses(scene: Path) -> dict[str, np.ndarray]:
    rec = pycolmap.Reconstruction(scene / "gt" / "sparse")
    return {im.name: im.cam_from_world().matrix() for im in rec.images.values()}


@pytest.fixture(scope="module")
def clean_vcs(dome_scene):
    views = database.read_views(dome_scene / "database.db")
    priors = read_priors(dome_scene / "gt" / "priors")
    opts = augment.AugmentOptions(use_classic_matches=False, show_progress=False)
    return views, augment.compute_virtual_correspondences(views, priors, opts)


def test_clean_vcs_meet_under_the_ground_truth_poses(dome_scene, clean_vcs):
    views, vcs = clean_vcs
    gt = _gt_poses(dome_scene)
    name_of = dict(zip(views.image_ids.tolist(), views.image_names, strict=True))
    cam_of = {
        int(i): views.cameras[int(c)]
        for i, c in zip(views.image_ids, views.camera_ids, strict=True)
    }
    kp = {k.image_id: k for k in vcs.keypoints}
    kinds = np.zeros(3, int)
    for pair in vcs.pairs:
        rel = relative_pose(gt[name_of[pair.image_id1]], gt[name_of[pair.image_id2]])
        xy1 = kp[pair.image_id1].xy_img[pair.idx1]
        xy2 = kp[pair.image_id2].xy_img[pair.idx2]
        err = epipolar_errors_px(
            cam_of[pair.image_id1], cam_of[pair.image_id2], rel, xy1, xy2
        )
        assert err.max() < 0.01, (
            f"pair {pair.image_id1}-{pair.image_id2}: {err.max():.4f} px"
        )
        kinds += np.bincount(pair.kind, minlength=3)
        # No duplicate VC within a pair.
        assert len(np.unique(pair.idx1 * 100_000 + pair.idx2)) == len(pair)
    assert (
        kinds[HitKind.COVISIBLE] > 100
        and kinds[HitKind.VIRTUAL] > 100
        and kinds[HitKind.KEYPOINT] > 10
    )


def test_every_pair_sharing_a_person_is_verified(dome_scene, clean_vcs):
    views, vcs = clean_vcs
    gt = _gt_poses(dome_scene)
    seen = {
        name: set(
            np.unique(
                np.load(dome_scene / "gt" / "surface" / (Path(name).stem + ".npz"))[
                    "person_id"
                ]
            ).tolist()
        )
        for name in views.image_names
    }
    id_of = dict(zip(views.image_names, views.image_ids.tolist(), strict=True))
    for n1, n2 in itertools.combinations(views.image_names, 2):
        if not seen[n1] & seen[n2]:
            continue
        key = tuple(sorted((id_of[n1], id_of[n2])))
        assert key in vcs.geometries, f"{n1}-{n2} not verified"
        a, b = (n1, n2) if id_of[n1] < id_of[n2] else (n2, n1)
        rel = relative_pose(gt[a], gt[b])
        R = vcs.geometries[key].cam2_from_cam1[:, :3]
        assert rotation_angle_deg(R @ rel[:, :3].T) < 1.0


def test_tracks_span_several_images(clean_vcs):
    _, vcs = clean_vcs
    images_per_track: dict[tuple[int, int], int] = {}
    for k in vcs.keypoints:
        for key in set(zip(k.person_id.tolist(), k.track_id.tolist(), strict=True)):
            images_per_track[key] = images_per_track.get(key, 0) + 1
    counts = np.array(list(images_per_track.values()))
    assert (counts >= 3).sum() > 200


def test_geometric_person_association_recovers_identities(dome_scene):
    views = database.read_views(dome_scene / "database.db")
    priors = read_priors(dome_scene / "gt" / "priors")
    anonymous = ScenePriors(
        images={
            n: ImagePrior(
                image_name=n,
                persons=tuple(
                    dataclasses.replace(p, person_id=None) for p in ip.persons
                ),
            )
            for n, ip in priors.images.items()
        }
    )
    opts = augment.AugmentOptions(use_classic_matches=False, show_progress=False)
    vcs = augment.compute_virtual_correspondences(views, anonymous, opts)
    true_ids = {n: [p.person_id for p in ip.persons] for n, ip in priors.images.items()}
    checked = 0
    for report in vcs.reports:
        assert report.association_method == "joint"
        for k1, k2 in report.association:
            assert true_ids[report.image_name1][k1] == true_ids[report.image_name2][k2]
            checked += 1
    assert checked >= 5


def _checksums(db: Path) -> dict[str, str]:
    return database.table_checksums(db)


def test_augment_strip_round_trip_and_dry_run(dome_scene, tmp_path):
    db = tmp_path / "database.db"
    shutil.copyfile(dome_scene / "database.db", db)
    before = _checksums(db)
    opts = augment.AugmentOptions(show_progress=False)
    dry = augment.run(
        db, dome_scene / "priors", dataclasses.replace(opts, dry_run=True)
    )
    assert dry.write is None and _checksums(db) == before and dry.pairs
    first = augment.run(db, dome_scene / "priors", opts)
    assert first.write is not None and first.num_verified_pairs > 0
    once = _checksums(db)
    for table in ("cameras", "images"):
        assert once[table] == before[table]
    # Classic keypoints are a byte-identical prefix; classic matches rows survive.
    views = database.read_views(db)
    for image_id in views.image_ids:
        assert np.array_equal(
            database.read_keypoints(db, int(image_id)),
            database.read_keypoints(dome_scene / "database.db", int(image_id)),
        )
    augment.run(db, dome_scene / "priors", opts)
    assert _checksums(db) == once  # augment twice == augment once
    database.strip(db)
    assert _checksums(db) == before


def test_augmented_database_maps_with_pycolmap(dome_scene, tmp_path):
    db = tmp_path / "database.db"
    shutil.copyfile(dome_scene / "database.db", db)
    augment.run(
        db, dome_scene / "gt" / "priors", augment.AugmentOptions(show_progress=False)
    )
    opts = pycolmap.IncrementalPipelineOptions(
        num_threads=2, ba_refine_focal_length=False, ba_refine_extra_params=False
    )
    pycolmap.set_random_seed(0)
    models = pycolmap.incremental_mapping(
        db, dome_scene / "images", tmp_path / "sparse", opts
    )
    assert max(m.num_reg_images() for m in models.values()) == 6


def test_priors_of_no_database_image_fail_and_leave_the_database(dome_scene, tmp_path):
    """Priors whose images are all unknown (another folder, renamed images) are
    refused before anything is written; priors of more images than the database
    holds are fine (tests/test_priors.py)."""
    db = tmp_path / "database.db"
    shutil.copyfile(dome_scene / "database.db", db)
    before = _checksums(db)
    priors = read_priors(dome_scene / "priors")
    bad = ScenePriors(
        images={
            f"ghost/{n}": dataclasses.replace(p, image_name=f"ghost/{n}")
            for n, p in priors.images.items()
        }
    )
    write_priors(
        bad,
        tmp_path / "priors",
        templates={"anny": next(iter(priors.images.values())).persons[0].faces},
    )
    with pytest.raises(PriorsError, match=r"ghost/"):
        augment.run(
            db, tmp_path / "priors", augment.AugmentOptions(show_progress=False)
        )
    assert _checksums(db) == before


def test_priors_of_another_focal_length_are_pointed_out(dome_scene, tmp_path, caplog):
    # Priors made with COLMAP's guessed intrinsics, mapped with a calibration:
    # the meshes' depth is off by the focal lengths' ratio; augment says so.
    db = tmp_path / "database.db"
    shutil.copyfile(dome_scene / "database.db", db)
    views = database.read_views(db)
    focal = {
        n: views.cameras[int(c)].mean_focal_length()
        for n, c in zip(views.image_names, views.camera_ids, strict=True)
    }
    priors = read_priors(dome_scene / "priors")
    guessed = ScenePriors(
        images={
            n: dataclasses.replace(p, focal_px=1.3 * focal[n])
            for n, p in priors.images.items()
        }
    )
    faces = next(iter(priors.images.values())).persons[0].faces
    write_priors(guessed, tmp_path / "priors", templates={"anny": faces})
    caplog.set_level("WARNING", logger="colmap_vc.augment")
    augment.run(
        db,
        tmp_path / "priors",
        augment.AugmentOptions(show_progress=False, dry_run=True),
    )
    assert f"the priors of {len(priors.images)} image(s) were made with" in caplog.text


def test_images_without_priors_are_skipped_with_a_reason(dome_scene, tmp_path, caplog):
    db = tmp_path / "database.db"
    shutil.copyfile(dome_scene / "database.db", db)
    priors = read_priors(dome_scene / "priors")
    dropped = sorted(priors.images)[0]
    partial = ScenePriors(
        images={n: p for n, p in priors.images.items() if n != dropped}
    )
    write_priors(
        partial,
        tmp_path / "priors",
        templates={"anny": priors.images[dropped].persons[0].faces},
    )
    summary = augment.run(
        db, tmp_path / "priors", augment.AugmentOptions(show_progress=False)
    )
    assert dropped in summary.skipped_images
    assert dropped in caplog.text
    assert all(dropped not in (p.image_name1, p.image_name2) for p in summary.pairs)


def test_not_a_database_and_no_keypoints(tmp_path, dome_scene):
    junk = tmp_path / "junk.db"
    junk.write_bytes(b"not sqlite at all" * 100)
    with pytest.raises(ValueError, match=r"junk.db"):
        augment.run(junk, dome_scene / "priors")
    assert junk.read_bytes() == b"not sqlite at all" * 100
    empty = tmp_path / "empty.db"
    shutil.copyfile(dome_scene / "database.db", empty)
    with sqlite3.connect(empty) as conn:
        conn.execute("DELETE FROM keypoints")
    with pytest.raises(ValueError, match="feature extraction"):
        augment.run(empty, dome_scene / "priors")


def test_ransac_threshold_scales_with_image_size(rng):
    from colmap_vc.verification import VerificationOptions, max_error_px, verify_pair

    small = pycolmap.Camera(
        model="PINHOLE", width=640, height=480, params=[500, 500, 320, 240]
    )
    big = pycolmap.Camera(
        model="PINHOLE", width=1080, height=1920, params=[1500, 1500, 540, 960]
    )
    opts = VerificationOptions()
    assert max_error_px(opts, small, small) == 4.0
    assert max_error_px(opts, small, big) == pytest.approx(12.0)
    off = dataclasses.replace(opts, reference_image_size_px=0)
    assert max_error_px(off, big, big) == 4.0
    # Two big views of a random cloud; matches perturbed by ~8 px: the scaled
    # threshold verifies them, the unscaled 4 px keeps few.
    points = rng.uniform([-1, -1, 4], [1, 1, 6], size=(200, 3))
    R = pycolmap.Rotation3d(np.array([0.0, 0.5, 0.0])).matrix()
    t = np.array([-2.0, 0.0, 0.5])
    xy1 = np.asarray(big.img_from_cam(points))
    xy2 = np.asarray(big.img_from_cam(points @ R.T + t))
    xy2 = xy2 + rng.normal(scale=5.0, size=xy2.shape)
    scaled = verify_pair(big, big, xy1, xy2, options=opts)
    unscaled = verify_pair(big, big, xy1, xy2, options=off)
    assert scaled.geometry is not None
    assert scaled.vc_is_inlier.mean() > 0.9
    assert unscaled.vc_is_inlier.mean() < scaled.vc_is_inlier.mean() - 0.1
