"""Same input, same output: the order COLMAP wrote the images in changes nothing.

COLMAP's threaded feature extraction writes images in whatever order its threads
finish, so image ids are arbitrary. The database is rebuilt here with the images
extracted in two orders (ids permuted), then augmented with anonymous priors and
mapped; the VCs and the poses must agree image by image.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from conftest import extract_database

from colmap_vc import augment, database, mapping
from colmap_vc.evaluation import relative_pose, relative_pose_error
from colmap_vc.priors import read_priors, write_priors
from colmap_vc.structs import ImagePrior, ScenePriors


def _extract(scene: Path, order: list[str], db_path: Path) -> Path:
    views = database.read_views(scene / "database.db")
    camera_of = {
        n: views.cameras[int(c)]
        for n, c in zip(views.image_names, views.camera_ids, strict=True)
    }
    return extract_database(scene / "images", order, camera_of, db_path)


@pytest.fixture(scope="module")
def anonymous_priors(
    dome_scene: Path, tmp_path_factory: pytest.TempPathFactory
) -> Path:
    priors = read_priors(dome_scene / "priors")
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
    out = tmp_path_factory.mktemp("anonymous") / "priors"
    write_priors(anonymous, out)
    return out


def test_image_order_changes_neither_vcs_nor_poses(
    dome_scene: Path, anonymous_priors: Path, tmp_path: Path
) -> None:
    names = sorted(database.read_views(dome_scene / "database.db").image_names)
    orders = {"forward": names, "shuffled": [names[i] for i in (3, 0, 5, 1, 4, 2)]}
    reports, poses = {}, {}
    for label, order in orders.items():
        db = _extract(dome_scene, order, tmp_path / f"{label}.db")
        ids = database.read_views(db)
        assert [
            n for _, n in sorted(zip(ids.image_ids, ids.image_names, strict=False))
        ] == order
        summary = augment.run(
            db, anonymous_priors, augment.AugmentOptions(show_progress=False)
        )
        reports[label] = {
            tuple(sorted((p.image_name1, p.image_name2))): (
                p.num_vcs,
                p.num_inliers,
                p.verified,
            )
            for p in summary.pairs
        }
        rec, _ = mapping.run(
            db,
            dome_scene / "images",
            tmp_path / f"{label}_sparse",
            mapping.MappingOptions(show_progress=False),
        )
        poses[label] = {
            im.name: im.cam_from_world().matrix()
            for im in rec.images.values()
            if im.has_pose
        }
    assert reports["forward"] == reports["shuffled"]
    assert sum(v[2] for v in reports["forward"].values()) >= 5
    a, b = poses["forward"], poses["shuffled"]
    assert sorted(a) == sorted(b) and len(a) >= 5
    for i, n1 in enumerate(sorted(a)):
        for n2 in sorted(a)[i + 1 :]:
            rot, trans = relative_pose_error(
                relative_pose(a[n1], a[n2]), relative_pose(b[n1], b[n2])
            )
            assert max(rot, trans) < 1.0, (n1, n2, rot, trans)
    assert np.isfinite(list(reports["forward"].values())).all()
