"""Keypoint BA: identity tracks are right, and the pass pulls perturbed poses back."""

from __future__ import annotations

import shutil

import numpy as np
import pycolmap
import pytest

from colmap_vc import augment, database, mapping
from colmap_vc.evaluation import evaluate_reconstruction
from colmap_vc.keypoint_ba import (
    KeypointBaOptions,
    keypoint_bundle_adjustment,
    keypoint_tracks,
    person_identities,
    triangulate_tracks,
)


@pytest.fixture(scope="module")
def mapped(dome_scene, tmp_path_factory):
    """The clean-prior dome, augmented and mapped without the keypoint pass."""
    work = tmp_path_factory.mktemp("kba")
    db = work / "database.db"
    shutil.copyfile(dome_scene / "database.db", db)
    augment.run(
        db, dome_scene / "gt" / "priors", augment.AugmentOptions(show_progress=False)
    )
    rec, _ = mapping.run(
        db,
        dome_scene / "images",
        work / "sparse",
        mapping.MappingOptions(num_threads=2, keypoint_ba=False, show_progress=False),
    )
    return db, rec


def test_person_identities_follow_association_chains():
    A = database.AssociationMethod("geometric")
    assoc = [
        database.PersonAssociation(
            image_id1=1, image_id2=2, person_id1=0, person_id2=1, method=A, score=1.0
        ),
        database.PersonAssociation(
            image_id1=2, image_id2=3, person_id1=1, person_id2=0, method=A, score=1.0
        ),
        database.PersonAssociation(
            image_id1=1, image_id2=2, person_id1=1, person_id2=0, method=A, score=1.0
        ),
    ]
    ident = person_identities(assoc)
    assert ident[(1, 0)] == ident[(2, 1)] == ident[(3, 0)]
    assert ident[(1, 1)] == ident[(2, 0)] != ident[(1, 0)]


def test_identity_tracks_triangulate_consistently(mapped):
    db, rec = mapped
    registered = np.array(list(rec.reg_image_ids()), dtype=np.int64)
    tracks = keypoint_tracks(db, registered)
    assert tracks.num_tracks > 0
    # One observation per image and track.
    pairs = np.stack([tracks.track, tracks.image_id], axis=1)
    assert len(np.unique(pairs, axis=0)) == len(pairs)
    # Clean priors: every track's rays meet (reprojection of its DLT point, px).
    X, counts = triangulate_tracks(rec, tracks)
    err = []
    for image_id in np.unique(tracks.image_id):
        sel = tracks.image_id == image_id
        image = rec.image(int(image_id))
        T = image.cam_from_world().matrix()
        pc = X[tracks.track[sel]] @ T[:, :3].T + T[:, 3]
        xy = np.asarray(rec.camera(image.camera_id).img_from_cam(pc))
        err.append(np.linalg.norm(xy - tracks.xy_img[sel], axis=1))
    assert (counts >= 2).all() and np.median(np.concatenate(err)) < 2.0


def test_keypoint_ba_pulls_perturbed_poses_back(dome_scene, mapped, rng):
    db, rec = mapped
    gt = pycolmap.Reconstruction(dome_scene / "gt" / "sparse")
    before = evaluate_reconstruction(rec, gt).median_error_deg
    perturbed = pycolmap.Reconstruction(rec)
    for image in perturbed.images.values():
        w = rng.normal(size=3)
        dR = pycolmap.Rotation3d(w / np.linalg.norm(w) * np.deg2rad(5.0)).matrix()
        T = image.cam_from_world().matrix()
        new = pycolmap.Rigid3d(pycolmap.Rotation3d(dR @ T[:, :3]), T[:, 3])
        perturbed.frame(image.frame_id).rig_from_world = new
    assert evaluate_reconstruction(perturbed, gt).median_error_deg > 3.0
    snapshot = {i: im.cam_from_world().matrix() for i, im in perturbed.images.items()}
    out, summary = keypoint_bundle_adjustment(
        db, perturbed, KeypointBaOptions(surface_per_image=0.0)
    )
    assert summary.num_tracks > 0 and summary.num_surface_observations == 0
    assert evaluate_reconstruction(out, gt).median_error_deg < max(1.0, 2 * before)
    for i, im in perturbed.images.items():  # the input is not modified
        assert np.array_equal(im.cam_from_world().matrix(), snapshot[i])
