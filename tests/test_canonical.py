"""Same input, same output: `map` does not depend on the order COLMAP wrote images."""

from __future__ import annotations

import shutil

import numpy as np
import pycolmap
import pytest

from colmap_vc import augment, canonical, database, mapping


@pytest.fixture(scope="module")
def databases(dome_scene, tmp_path_factory):
    """The augmented dome, and the same database numbered in reverse name order."""
    root = tmp_path_factory.mktemp("canonical")
    db = root / "database.db"
    shutil.copyfile(dome_scene / "database.db", db)
    augment.run(db, dome_scene / "priors", augment.AugmentOptions(show_progress=False))
    work = root / "work.db"
    shutil.copyfile(db, work)
    reverse = root / "reverse.db"
    ids = canonical.canonical_copy(work, reverse, reverse=True)
    assert ids is not None
    return db, reverse


def _by_names(db) -> tuple[dict, dict, dict]:
    """Matches, geometries and VCs keyed by image names, oriented by name."""
    views = database.read_views(db)
    name = dict(zip(views.image_ids.tolist(), views.image_names, strict=True))
    matches, geometries, vcs = {}, {}, {}
    for (a, b), m in database.read_matches(db, include_vc=True).items():
        (n1, n2), m = (
            ((name[a], name[b]), m)
            if name[a] < name[b]
            else (
                (name[b], name[a]),
                m[:, ::-1],
            )
        )
        matches[(n1, n2)] = {tuple(r) for r in m.tolist()}
    for (a, b), g in database.read_two_view_geometries(db, include_vc=True).items():
        if not len(g.inlier_matches):
            continue  # a rejected pair: pycolmap reads (and copies) none of it
        T = g.cam2_from_cam1
        if name[a] > name[b]:
            a, b = b, a
            if T is not None:
                T = np.c_[T[:, :3].T, -T[:, :3].T @ T[:, 3]]
        geometries[(name[a], name[b])] = (g.config, T)
    for p in database.read_virtual_correspondences(db)[1]:
        rows = np.c_[p.idx1, p.idx2, p.points1_cam, p.points2_cam, p.a, p.b]
        flip = name[p.image_id1] > name[p.image_id2]
        key = tuple(sorted((name[p.image_id1], name[p.image_id2])))
        vcs[key] = (flip, rows)
    return matches, geometries, vcs


def test_reversed_numbering_keeps_every_correspondence(databases):
    """Matches, two-view geometries (inverted where the pair turned) and VCs (X1
    and X2 exchanged, the thickness (a, b) re-expressed) are those of the source."""
    db, reverse = databases
    m0, g0, v0 = _by_names(db)
    m1, g1, v1 = _by_names(reverse)
    assert m0 == m1
    assert g0.keys() == g1.keys()
    for key, (config, T) in g0.items():
        assert g1[key][0] == config
        if T is not None:
            assert np.allclose(g1[key][1], T, atol=1e-9), key
    assert v0.keys() == v1.keys()
    turned = 0
    for key, (flip0, rows0) in v0.items():
        flip1, rows1 = v1[key]
        assert flip0 != flip1  # reverse numbering turns every pair
        fwd, rev = (rows0, rows1) if not flip0 else (rows1, rows0)
        # rows of `fwd` run image 1 -> 2 by name; `rev` the other way
        assert np.array_equal(fwd[:, 0], rev[:, 1])
        assert np.array_equal(fwd[:, 2:5], rev[:, 5:8])
        a, b = fwd[:, 8], fwd[:, 9]
        ok = np.abs(1 + a) > 1e-3
        assert np.allclose(rev[ok, 8], -a[ok] / (1 + a[ok]))
        assert np.allclose(rev[ok, 9], (a[ok] + b[ok]) / (1 + a[ok]))
        turned += 1
    assert turned > 5


def test_reversed_thickness_describes_the_same_points(rng):
    """X2 = X1 + a (X1 - o1) + b (o2 - o1)  <=>  X1 = X2 + a' (X2 - o2) + b' (o1 - o2)
    with a' = -a / (1 + a), b' = (a + b) / (1 + a): the formula canonical.py uses."""
    o1, o2, x1 = rng.normal(size=(3, 100, 3))
    a, b = rng.uniform(-0.5, 0.5, (2, 100, 1))
    x2 = x1 + a * (x1 - o1) + b * (o2 - o1)
    a2, b2 = -a / (1 + a), (a + b) / (1 + a)
    assert np.allclose(x1, x2 + a2 * (x2 - o2) + b2 * (o1 - o2))


def test_map_does_not_depend_on_the_image_order(databases, dome_scene, tmp_path):
    """The same database numbered two ways gives the same cameras, each model with
    its own database's ids."""
    poses = []
    for k, db in enumerate(databases):
        rec, _ = mapping.run(
            db,
            dome_scene / "images",
            tmp_path / f"sparse{k}",
            mapping.MappingOptions(num_threads=1),
        )
        views = database.read_views(db)
        ids = dict(zip(views.image_names, views.image_ids.tolist(), strict=True))
        on_disk = pycolmap.Reconstruction(next((tmp_path / f"sparse{k}").glob("*/")))
        for model in (rec, on_disk):
            assert {im.name: i for i, im in model.images.items()} == {
                n: ids[n] for n in (im.name for im in model.images.values())
            }
        poses.append(
            {
                im.name: im.cam_from_world().matrix()
                for im in rec.images.values()
                if im.has_pose
            }
        )
    assert poses[0].keys() == poses[1].keys() and len(poses[0]) >= 5
    for name, T in poses[0].items():
        assert np.allclose(poses[1][name], T, atol=1e-6), name


def test_relabel_keeps_an_unregistered_image_unregistered(capfd):
    """An image the model left out comes back with the user's id and no pose,
    without COLMAP warning that a frame was de-registered twice."""
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(
        pycolmap.Camera(
            camera_id=1, model="PINHOLE", width=64, height=48, params=[50, 50, 32, 24]
        )
    )
    posed = pycolmap.Rigid3d(pycolmap.Rotation3d(), np.array([0.0, 0.0, 1.0]))
    rec.add_image_with_trivial_frame(
        pycolmap.Image(name="a.jpg", camera_id=1, image_id=1), posed
    )
    rec.add_image_with_trivial_frame(
        pycolmap.Image(name="b.jpg", camera_id=1, image_id=2)
    )
    out = canonical.relabel(rec, {1: 7, 2: 3}, {1: 5})
    assert out.image(7).name == "a.jpg" and out.image(7).has_pose
    assert out.image(3).name == "b.jpg" and not out.image(3).has_pose
    assert sorted(out.reg_image_ids()) == [7]
    assert "de-registration" not in capfd.readouterr().err
