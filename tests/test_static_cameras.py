"""Static cameras: images grouped by physical camera, one view per camera."""

from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path

import numpy as np
import pytest
from conftest import extract_database

from colmap_vc import cli, database
from colmap_vc.evaluation import camera_distance_ratio
from colmap_vc.gba.repeats import repeat_design
from colmap_vc.keypoint_ba import KeypointBaOptions, surface_noise, with_loss_scale
from colmap_vc.keypoint_tracks import keypoint_tracks, surface_tracks
from colmap_vc.mapping.inputs import read_inputs
from colmap_vc.mapping.options import MappingOptions
from colmap_vc.mapping.outputs import static_members_left_out
from colmap_vc.metric_scale import read_metric_scale
from colmap_vc.priors import read_priors, write_priors
from colmap_vc.static_cameras import (
    merge_priors,
    parse_static_cameras,
    same_view_pairs,
    warn_if_static_cameras,
)
from colmap_vc.structs import ImagePrior, ScenePriors

NAMES = [f"cam{c:02d}_t{t:03d}.jpg" for c in (1, 2, 3) for t in (10, 30)] + ["x.jpg"]


def test_cameras_instants_and_unmatched_images() -> None:
    static = parse_static_cameras(r"(cam\d+)_", NAMES)
    assert static.representative == {
        "cam01": "cam01_t010.jpg",
        "cam02": "cam02_t010.jpg",
        "cam03": "cam03_t010.jpg",
    }
    assert static.instant_of["cam02_t030.jpg"] == "_t030.jpg"
    assert static.instant_of["cam01_t030.jpg"] == static.instant_of["cam03_t030.jpg"]
    assert static.unmatched == ("x.jpg",)
    assert static.members("cam02_t010.jpg") == ["cam02_t010.jpg", "cam02_t030.jpg"]
    assert static.representative_of("cam03_t030.jpg") == "cam03_t010.jpg"
    assert static.representative_of("x.jpg") == "x.jpg"


def test_a_left_out_static_camera_gives_its_reason_to_every_image() -> None:
    static = parse_static_cameras(r"(cam\d+)_", NAMES)
    why = "left out: its pose contradicts the body meshes"
    reasons = static_members_left_out({"cam02_t010.jpg": why, "x.jpg": "?"}, static)
    assert reasons == {
        "cam02_t030.jpg": f"as cam02_t010.jpg (the same static camera): {why}"
    }


@pytest.mark.parametrize(
    ("pattern", "message"),
    [
        ("(cam\\d+", "not a valid regular expression"),
        ("cam\\d+_", "no capturing group"),
        ("(view\\d+)_", "matches none of the 7 images"),
    ],
)
def test_bad_expressions_are_refused_clearly(pattern: str, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        parse_static_cameras(pattern, NAMES)


def test_merged_views_hold_every_instant_tagged(dome_scene: Path) -> None:
    priors = read_priors(dome_scene / "priors")
    names = sorted(priors.images)[:4]
    # Pretend the first four images are 2 cameras x 2 instants.
    renamed = {n: f"cam{k // 2:02d}_t{k % 2:03d}.jpg" for k, n in enumerate(names)}
    scene = ScenePriors(
        images={
            renamed[n]: ImagePrior(
                image_name=renamed[n], persons=priors.images[n].persons
            )
            for n in names
        }
    )
    static = parse_static_cameras(r"(cam\d+)_", list(scene.images))
    merged, groups = merge_priors(scene, static)
    assert sorted(merged.images) == ["cam00_t000.jpg", "cam01_t000.jpg"]
    for rep, ip in merged.images.items():
        members = static.members(rep)
        assert len(ip.persons) == sum(len(scene.images[m].persons) for m in members)
        tags = [groups[(rep, k)] for k in range(len(ip.persons))]
        assert tags == sorted(tags) and len(set(tags)) == 2
        ids = [p.person_id for p in ip.persons]
        assert len(set(ids)) == len(ids)  # ids are made unique per instant


def test_cli_refuses_a_bad_expression_and_leaves_the_database(
    dome_scene: Path, tmp_path: Path
) -> None:
    db = tmp_path / "database.db"
    shutil.copyfile(dome_scene / "database.db", db)
    before = database.table_checksums(db)
    code = cli.main(
        [
            "augment",
            str(db),
            "--priors",
            str(dome_scene / "priors"),
            "--static-cameras",
            "(nothing\\d+)_",
            "--no-show-progress",
        ]
    )
    assert code == 1
    assert database.table_checksums(db) == before


def _static_copies(
    dome_scene: Path,
    tmp_path: Path,
    names: list[str],
    background: bool = False,
    drop: tuple[str, ...] = (),
    instants: tuple[str, ...] = ("_t2",),
    anonymous: bool = True,
) -> tuple[Path, Path, list[str]]:
    """The dome images ``names`` as instants of static cameras: each picture
    again under each name suffix of ``instants`` (the people did not move), a
    database of all with the known intrinsics, anonymous priors, ``augment
    --static-cameras``.
    ``background``: a textured band along each camera's top edge, the same at
    both instants (a static camera's room: many SIFT matches between its own
    instants, none with the other cameras). ``drop``: images left out of the
    database (a camera that missed an instant). ``anonymous``: the people without
    their ids (else each keeps its own at every instant).
    -> (database, image folder, every image name)."""
    import cv2

    images = tmp_path / "images"
    images.mkdir()
    priors = read_priors(dome_scene / "priors")
    views = database.read_views(dome_scene / "database.db")
    rng = np.random.default_rng(0)
    for n in names:
        shutil.copyfile(dome_scene / "images" / n, images / n)
        if background:
            img = cv2.imread(str(images / n))
            band = img.shape[0] // 8
            blocks = rng.integers(0, 256, (band // 4, img.shape[1] // 4, 3))
            img[:band] = np.kron(blocks, np.ones((4, 4, 1)))[:band, : img.shape[1]]
            cv2.imwrite(str(images / n), img)
        for t in instants:
            shutil.copyfile(images / n, images / n.replace(".jpg", f"{t}.jpg"))
    db = tmp_path / "database.db"
    camera_of = {
        n: views.cameras[int(c)]
        for n, c in zip(views.image_names, views.camera_ids, strict=True)
    }
    source = {  # image name -> the dome image it copies
        n.replace(".jpg", f"{t}.jpg"): n for n in names for t in ("", *instants)
    }
    all_names = sorted(set(source) - set(drop))
    cameras = {n: camera_of[source[n]] for n in all_names}
    extract_database(images, all_names, cameras, db)
    anonymous = {
        n: ImagePrior(
            image_name=n,
            persons=tuple(
                dataclasses.replace(p, person_id=None) if anonymous else p
                for p in priors.images[source[n]].persons
            ),
        )
        for n in all_names
    }
    write_priors(ScenePriors(images=anonymous), tmp_path / "priors")
    augment = ["augment", str(db), "--priors", str(tmp_path / "priors")]
    static = ["--static-cameras", r"^(cam\d+)", "--no-show-progress"]
    assert cli.main([*augment, *static]) == 0
    return db, images, all_names


def _map_poses(db: Path, images: Path, out: Path) -> dict[str, np.ndarray]:
    """``colmap-vc map`` (static cameras as augment recorded) -> pose per image."""
    import pycolmap

    args = ["map", str(db), "--image-path", str(images), "--output-path", str(out)]
    assert cli.main([*args, "--no-show-progress"]) == 0
    rec = pycolmap.Reconstruction(out / "0")
    return {
        im.name: im.cam_from_world().matrix()
        for im in rec.images.values()
        if im.has_pose
    }


def test_one_pose_per_static_camera_end_to_end(
    dome_scene: Path, tmp_path: Path
) -> None:
    """A 6-view dome seen as 2 instants of the same cameras: copies of each image
    under a second instant name give the same pose as the first."""
    names = sorted(database.read_views(dome_scene / "database.db").image_names)
    db, images, all_names = _static_copies(dome_scene, tmp_path, names)
    poses = _map_poses(db, images, tmp_path / "sparse")
    assert sorted(poses) == all_names  # every input image is in the model
    for n in names:
        assert np.allclose(poses[n], poses[n.replace(".jpg", "_t2.jpg")])


def test_two_static_cameras_are_mapped_from_their_own_pair(
    dome_scene: Path, tmp_path: Path, capfd
) -> None:
    """Two static cameras over two instants: the two-view start takes the pair of
    the two cameras, not the two instants of one camera (the same background, the
    most SIFT inliers, no baseline: it took that pair and found no model)."""
    import pycolmap

    gt = pycolmap.Reconstruction(dome_scene / "gt" / "sparse")
    truth = {im.name: im.cam_from_world().matrix() for im in gt.images.values()}
    a, b = sorted(truth)[:2]
    db, images, all_names = _static_copies(dome_scene, tmp_path, [a, b], True)
    capfd.readouterr()
    poses = _map_poses(db, images, tmp_path / "sparse")
    assert sorted(poses) == all_names
    # Two cameras over two instants are not the weak two-image case.
    assert "two images placed by their people alone" not in "".join(capfd.readouterr())
    rel = poses[b][:, :3] @ poses[a][:, :3].T
    rel_gt = truth[b][:, :3] @ truth[a][:, :3].T
    cos = np.clip((np.trace(rel @ rel_gt.T) - 1) / 2, -1.0, 1.0)
    assert np.degrees(np.arccos(cos)) < 20.0  # two views of one instant: ~11


def test_uneven_instants_are_scaled_to_metres(dome_scene: Path, tmp_path: Path) -> None:
    """Three static cameras, each instant seen by two of them (a and b, then b
    and c, then a and c): every keypoint track has two views, and the model is
    still scaled from the people (it was left unscaled: no track of three)."""
    import pycolmap

    gt = pycolmap.Reconstruction(dome_scene / "gt" / "sparse")
    truth = {im.name: im.cam_from_world().matrix() for im in gt.images.values()}
    a, b, c = sorted(truth)[:3]
    drop = (c, a.replace(".jpg", "_t2.jpg"), b.replace(".jpg", "_t3.jpg"))
    db, images, all_names = _static_copies(
        dome_scene, tmp_path, [a, b, c], drop=drop, instants=("_t2", "_t3")
    )
    poses = _map_poses(db, images, tmp_path / "sparse")
    assert sorted(poses) == all_names
    scale = read_metric_scale(tmp_path / "sparse" / "0")
    # The people of different instants may be one person: the scale says how
    # many identities it read and how many people it takes them for. Each
    # instant is a copy of the same pictures, so a camera's view holds each
    # person three times at the same keypoints: each identity's instant is the
    # one the database names, not the first with those keypoints (it read "6
    # identities over 2 instants, taken as 4 people").
    assert scale is not None
    assert "6 identities over 3 instants, taken as 2 people" in scale.describe()
    for t in ("_t2", "_t3"):  # the same camera at every instant
        truth.update({n.replace(".jpg", f"{t}.jpg"): truth[n] for n in (a, b, c)})
    assert camera_distance_ratio(poses, truth) == pytest.approx(1.0, abs=0.15)


def test_frames_of_one_camera_without_static_cameras_are_pointed_out(
    dome_scene: Path, tmp_path: Path, capfd
) -> None:
    """Frames of static cameras at two instants match at the same pixels: augment
    without --static-cameras says so, with the groups, and is quiet with it."""
    names = sorted(database.read_views(dome_scene / "database.db").image_names)[:3]
    db, _, _ = _static_copies(dome_scene, tmp_path, names, background=True)
    assert "same pixels" not in "".join(capfd.readouterr())  # it was given
    groups = warn_if_static_cameras(
        database.read_two_view_geometries(db), database.read_views(db)
    )
    assert groups == [[n, n.replace(".jpg", "_t2.jpg")] for n in names]
    augment = ["augment", str(db), "--priors", str(tmp_path / "priors")]
    assert cli.main([*augment, "--no-show-progress"]) == 0
    output = "".join(capfd.readouterr())
    assert "3 image pair(s) match at the same pixels, in 3 group(s)" in output


def test_same_pixels_need_many_inliers_and_no_shift() -> None:
    def row(H: np.ndarray, inliers: int) -> database.TwoViewGeometryRow:
        return database.TwoViewGeometryRow(
            image_id1=1,
            image_id2=2,
            inlier_matches=np.zeros((inliers, 2), np.int64),
            config=5,
            F=None,
            E=None,
            H=H,
            qvec_wxyz=None,
            tvec=None,
        )

    sizes = {1: (640, 480)}
    shifted = np.eye(3)
    shifted[0, 2] = 3.0  # three pixels to the right
    turned = np.array([[1.0, -0.01, 0], [0.01, 1.0, 0], [0, 0, 1]])  # 0.6 deg
    for H, inliers, found in (
        (np.eye(3), 100, True),
        (np.eye(3) * 2.0, 100, True),  # a homography's scale is free
        (np.eye(3), 10, False),
        (shifted, 100, False),
        (turned, 100, False),
    ):
        got = same_view_pairs({(1, 2): row(H, inliers)}, sizes, 30, 2.0)
        assert bool(got) is found, (H, inliers)


@pytest.mark.parametrize("anonymous", [True, False])
def test_a_scene_that_did_not_move_repeats_every_keypoint_error(
    dome_scene: Path, tmp_path: Path, anonymous: bool
) -> None:
    """Two instants of the same pictures (nobody moved): `map` knows the instant
    of every static-camera person, anonymous or with ids, and each keypoint
    repeats the other instant's error exactly (design effect 2: the two instants
    count as one)."""
    names = sorted(database.read_views(dome_scene / "database.db").image_names)
    db, _, _ = _static_copies(dome_scene, tmp_path, names[:4], anonymous=anonymous)
    inputs = read_inputs(db, MappingOptions(), None)
    assert inputs.instant_of is not None
    assert sorted(set(inputs.instant_of.values())) == [".jpg", "_t2.jpg"]
    ids = inputs.records.views.image_ids
    tracks = keypoint_tracks(inputs.records, np.asarray(ids, dtype=np.int64))
    assert tracks.keys is not None and tracks.num_tracks > 0
    assert set(np.unique(tracks.keys[:, 0]).tolist()) <= set(inputs.instant_of)
    m = repeat_design(tracks, inputs.instant_of, sigma_px=5.0)
    assert np.allclose(m, 2.0)


def test_a_still_scene_doubles_the_noise_of_every_surface_sample(
    dome_scene: Path, tmp_path: Path
) -> None:
    """The GBA's surface samples of two identical instants repeat each other: each
    one's noise variance doubles (the instants count as one), on top of its
    correlation with its neighbours."""
    import pycolmap

    names = sorted(database.read_views(dome_scene / "database.db").image_names)
    db, images, _ = _static_copies(dome_scene, tmp_path, names[:4])
    _map_poses(db, images, tmp_path / "sparse")
    rec = pycolmap.Reconstruction(tmp_path / "sparse" / "0")
    inputs = read_inputs(db, MappingOptions(), None)
    posed = np.array(sorted(rec.reg_image_ids()), dtype=np.int64)
    kp = keypoint_tracks(inputs.records, posed)
    surface = surface_tracks(inputs.records, posed)
    options = with_loss_scale(KeypointBaOptions(), rec)
    alone = surface_noise(rec, kp, surface, options)
    repeated = surface_noise(rec, kp, surface, options, inputs.instant_of)
    ratios = np.concatenate(
        [repeated.sigma_px[i] / alone.sigma_px[i] for i in alone.sigma_px]
    )
    ratios = ratios[np.isfinite(ratios)]
    assert len(ratios) > 100
    assert np.allclose(ratios, np.sqrt(2.0), rtol=0.03)
