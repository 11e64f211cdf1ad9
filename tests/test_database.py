"""colmap_vc.database on real COLMAP 3.8 and pycolmap 4.x databases.

The databases come from feature extraction and matching on a small rendered scene (two
textured planes, five cameras); the VCs are exact projections of 3D points of the same
scene, so the mappers can use them.
"""

from __future__ import annotations

import os
import pickle
import re
import shutil
import sqlite3
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest

from colmap_vc import database, database_schema, database_write
from colmap_vc.structs import HitKind, PairGeometry, PairVcMatches, VcKeypoints

WIDTH, HEIGHT, FOCAL = 320, 240, 280.0
K = np.array([[FOCAL, 0, WIDTH / 2], [0, FOCAL, HEIGHT / 2], [0, 0, 1.0]])
NUM_IMAGES = 5
HAS_COLMAP = shutil.which("colmap") is not None
needs_colmap = pytest.mark.skipif(not HAS_COLMAP, reason="no `colmap` binary (3.8)")
SCHEMAS = [
    "pycolmap4",
    pytest.param("colmap38", marks=[pytest.mark.colmap38, needs_colmap]),
]


# ------------------------------------------------------------------ scene + databases


def _cameras() -> list[tuple[np.ndarray, np.ndarray]]:
    """cam_from_world (R, t) of cameras on a line, looking at (0, 0, 5)."""
    poses = []
    for i, x in enumerate(np.linspace(-1.2, 1.2, NUM_IMAGES)):
        center = np.array([x, 0.2 * np.sin(i), 0.0])
        z = np.array([0.0, 0.0, 5.0]) - center
        z /= np.linalg.norm(z)
        x_axis = np.cross([0.0, 1.0, 0.0], z)
        x_axis /= np.linalg.norm(x_axis)
        rotation = np.stack([x_axis, np.cross(z, x_axis), z])
        poses.append((rotation, -rotation @ center))
    return poses


def _render(image_dir: Path, rng: np.random.Generator) -> None:
    """Two textured planes (a wall and a tilted board in front) seen by _cameras()."""
    image_dir.mkdir(parents=True)
    planes = [  # corner, side vectors of the texture square, in world metres
        (np.array([-7.0, -5.0, 7.0]), np.array([14.0, 0, 0]), np.array([0, 10.0, 0])),
        (np.array([-1.5, -1.2, 3.8]), np.array([2.4, 0, 0.8]), np.array([0, 2.4, 0])),
    ]
    size = 512
    textures = []
    for _ in planes:
        noise = sum(
            cv2.resize(rng.random((size // s, size // s)), (size, size)) / s**0.5
            for s in (2, 6, 18)
        )
        noise = (noise - noise.min()) / np.ptp(noise)
        textures.append((255 * noise).astype(np.uint8))
    # OpenCV puts pixel centres at integers, COLMAP at +0.5: shift by -0.5 at warp.
    to_opencv = np.array([[1, 0, -0.5], [0, 1, -0.5], [0, 0, 1]])
    for index, (rotation, translation) in enumerate(_cameras()):
        image = np.zeros((HEIGHT, WIDTH), np.uint8)
        for (corner, side_u, side_v), texture in zip(planes, textures, strict=True):
            origin = corner + 0.5 * (side_u + side_v) / size  # texel centre (0, 0)
            columns = [rotation @ side_u / size, rotation @ side_v / size]
            plane_to_cam = np.column_stack([*columns, rotation @ origin + translation])
            homography = to_opencv @ K @ plane_to_cam
            warped = cv2.warpPerspective(texture, homography, (WIDTH, HEIGHT))
            mask = cv2.warpPerspective(
                np.full_like(texture, 255),
                homography,
                (WIDTH, HEIGHT),
                flags=cv2.INTER_NEAREST,
            )
            image[mask > 0] = warped[mask > 0]
        cv2.imwrite(str(image_dir / f"img{index:02d}.png"), image)


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("scene")
    _render(root / "images", np.random.default_rng(0))
    return root


def _build_pycolmap4(scene: Path, db_path: Path) -> None:
    pycolmap.extract_features(
        db_path,
        scene / "images",
        camera_mode=pycolmap.CameraMode.SINGLE,
        reader_options=pycolmap.ImageReaderOptions(
            camera_model="PINHOLE", camera_params=f"{FOCAL},{FOCAL},160,120"
        ),
        extraction_options=pycolmap.FeatureExtractionOptions(num_threads=1),
        device=pycolmap.Device.cpu,
    )
    _match_pycolmap4(db_path)


def _match_pycolmap4(db_path: Path, guided: bool = False) -> None:
    pycolmap.match_exhaustive(
        db_path,
        matching_options=pycolmap.FeatureMatchingOptions(
            num_threads=1, guided_matching=guided
        ),
        device=pycolmap.Device.cpu,
    )


def _colmap(*args: str) -> None:
    env = {**os.environ, "QT_QPA_PLATFORM": "offscreen"}
    result = subprocess.run(["colmap", *args], capture_output=True, text=True, env=env)
    assert result.returncode == 0, result.stderr[-2000:]


def _build_colmap38(scene: Path, db_path: Path) -> None:
    _colmap(
        "feature_extractor",
        "--database_path",
        str(db_path),
        "--image_path",
        str(scene / "images"),
        "--ImageReader.single_camera",
        "1",
        "--ImageReader.camera_model",
        "PINHOLE",
        "--ImageReader.camera_params",
        f"{FOCAL},{FOCAL},160,120",
        "--SiftExtraction.use_gpu",
        "0",
        "--SiftExtraction.num_threads",
        "1",
    )
    _match_colmap38(db_path)


def _match_colmap38(db_path: Path, guided: bool = False) -> None:
    _colmap(
        "exhaustive_matcher",
        "--database_path",
        str(db_path),
        "--SiftMatching.use_gpu",
        "0",
        "--SiftMatching.num_threads",
        "1",
        "--SiftMatching.guided_matching",
        str(int(guided)),
    )


@pytest.fixture(scope="module")
def templates(scene_dir: Path) -> dict[str, Path]:
    """One matched database per schema, built lazily and copied by each test."""
    return {}


@pytest.fixture(params=SCHEMAS)
def db(
    request: pytest.FixtureRequest,
    templates: dict[str, Path],
    scene_dir: Path,
    tmp_path: Path,
) -> Path:
    kind = request.param
    if kind not in templates:
        templates[kind] = scene_dir / f"{kind}.db"
        build = _build_pycolmap4 if kind == "pycolmap4" else _build_colmap38
        build(scene_dir, templates[kind])
    path = tmp_path / "database.db"
    shutil.copy(templates[kind], path)
    return path


def _sql(db_path: Path, *statements: str) -> None:
    conn = sqlite3.connect(db_path)
    for statement in statements:
        conn.execute(statement)
    conn.commit()
    conn.close()


def _make_vcs(
    db_path: Path, rng: np.random.Generator, num_points: int = 60
) -> tuple[list[VcKeypoints], list[PairVcMatches], dict[tuple[int, int], PairGeometry]]:
    """VCs from projections of random 3D points ("two persons") of the scene."""
    views = database.read_views(db_path)
    poses = dict(zip(views.image_ids.tolist(), _cameras(), strict=True))
    points = rng.uniform([0.2, -0.8, 4.3], [1.0, 0.8, 5.0], (num_points, 3))
    person = (np.arange(num_points) >= num_points // 2).astype(np.int64)
    points_cam, visible = {}, {}
    keypoints = []
    for image_id, (rotation, translation) in poses.items():
        cam = points @ rotation.T + translation
        xy = cam @ K.T
        xy = xy[:, :2] / xy[:, 2:]
        inside = (xy > 0).all(1) & (xy < [WIDTH, HEIGHT]).all(1)
        track = np.flatnonzero(inside)
        points_cam[image_id], visible[image_id] = cam, track
        keypoints.append(
            VcKeypoints(
                image_id=image_id,
                xy_img=xy[track],
                person_id=person[track],
                track_id=track,
            )
        )
    pairs, geometries = [], {}
    ids = sorted(poses)
    for n, image_id1 in enumerate(ids):
        for image_id2 in ids[n + 1 :]:
            common, idx1, idx2 = np.intersect1d(
                visible[image_id1], visible[image_id2], return_indices=True
            )
            m = len(common)
            pairs.append(
                PairVcMatches(
                    image_id1=image_id1,
                    image_id2=image_id2,
                    idx1=idx1.astype(np.int64),
                    idx2=idx2.astype(np.int64),
                    person_id=person[common],
                    kind=rng.integers(0, len(HitKind), m),
                    points1_cam=points_cam[image_id1][common],
                    points2_cam=points_cam[image_id2][common],
                    a=rng.normal(size=m),
                    b=rng.normal(size=m),
                    is_inlier=rng.random(m) > 0.2,
                )
            )
            (r1, t1), (r2, t2) = poses[image_id1], poses[image_id2]
            rotation = r2 @ r1.T
            translation = t2 - rotation @ t1
            translation /= np.linalg.norm(translation)
            cross = np.array(
                [
                    [0, -translation[2], translation[1]],
                    [translation[2], 0, -translation[0]],
                    [-translation[1], translation[0], 0],
                ]
            )
            essential = cross @ rotation
            k_inv = np.linalg.inv(K)
            geometries[(image_id1, image_id2)] = PairGeometry(
                config=2,
                E=essential,
                F=k_inv.T @ essential @ k_inv,
                H=np.eye(3),
                cam2_from_cam1=np.column_stack([rotation, translation]),
            )
    return keypoints, pairs, geometries


@pytest.fixture
def vcs(db: Path) -> tuple[list[VcKeypoints], list[PairVcMatches], dict]:
    return _make_vcs(db, np.random.default_rng(0))


def _colmap_checksums(db_path: Path) -> dict[str, str]:
    return {
        table: digest
        for table, digest in database.table_checksums(db_path).items()
        if not table.startswith("colmap_vc_")
    }


def _assert_no_vc_in_matches(db_path: Path, num_classic: dict[int, int]) -> int:
    """Every match row of the database only uses classic keypoints; returns #rows."""
    total = 0
    for rows in (
        database.read_matches(db_path, include_vc=True),
        {
            k: g.inlier_matches
            for k, g in database.read_two_view_geometries(
                db_path, include_vc=True
            ).items()
        },
    ):
        for (image_id1, image_id2), matches in rows.items():
            limits = [num_classic[image_id1], num_classic[image_id2]]
            assert (matches < limits).all(), (image_id1, image_id2)
            total += len(matches)
    return total


# ------------------------------------------------------------------ reading


@pytest.mark.parametrize("db", SCHEMAS, indirect=True)
def test_read_views_and_keypoints(db: Path) -> None:
    views = database.read_views(db)
    is_4x = "frames" in database.table_checksums(db)
    assert views.schema == ("4.x" if is_4x else "3.x")
    assert views.image_names == tuple(f"img{i:02d}.png" for i in range(NUM_IMAGES))
    camera = views.cameras[int(views.camera_ids[0])]
    assert camera.model == pycolmap.CameraModelId.PINHOLE
    np.testing.assert_array_equal(camera.params, [FOCAL, FOCAL, 160, 120])
    xy = database.read_keypoints(db, int(views.image_ids[0]))
    assert xy.shape == (views.num_keypoints[0], 2) and xy.dtype == np.float64
    assert (xy > 0).all() and (xy < [WIDTH, HEIGHT]).all()
    assert (views.num_vc_keypoints == 0).all()


def test_pair_id_convention() -> None:
    assert database_schema.pair_id_from_images(1, 2) == 2147483647 + 2
    assert database_schema.pair_id_from_images(2, 1) == 2147483647 + 2
    assert database_schema.images_from_pair_id(3 * 2147483647 + 7) == (3, 7)


@pytest.mark.parametrize("db", SCHEMAS[:1], indirect=True)
def test_read_matches_swaps_reversed_pairs(db: Path) -> None:
    forward = database.read_matches(db, [(1, 2), (2, 1), (1, 99)])
    np.testing.assert_array_equal(forward[(2, 1)], forward[(1, 2)][:, ::-1])
    assert forward[(1, 99)].shape == (0, 2)


def _vc_codes(num_codes: int = 400) -> np.ndarray:
    """A sample of the per-image VC descriptor codes, (num_codes, 128) int64."""
    image_ids = np.random.default_rng(0).choice(8128, num_codes, replace=False) + 1
    rows = b"".join(database_schema.vc_descriptors(int(i), 1) for i in image_ids)
    return np.frombuffer(rows, np.uint8).reshape(-1, 128).astype(np.int64)


MAX_SIFT_DISTANCE = 0.7  # COLMAP's default SiftMatchingOptions.max_distance (3.8, 4.x)
SQ_NORM = 512.0**2  # COLMAP scales SIFT descriptors to norm 512


def test_vc_descriptor_codes_never_match_each_other() -> None:
    codes = _vc_codes()
    assert len(np.unique(codes, axis=0)) == len(codes)
    dots = codes @ codes.T
    np.fill_diagonal(dots, 0)
    # dot-product matchers (3.8, 4.x brute force): angle = acos(dot / 512^2)
    assert np.arccos(dots.max() / SQ_NORM) > MAX_SIFT_DISTANCE
    # L2 matchers (4.x index and guided matching): squared distance vs 0.49 * 512^2
    sq_norms = (codes**2).sum(1)
    sq_dists = sq_norms[:, None] + sq_norms[None] - 2 * codes @ codes.T
    np.fill_diagonal(sq_dists, 10**9)
    assert sq_dists.min() > MAX_SIFT_DISTANCE**2 * SQ_NORM


def test_vc_descriptor_codes_are_far_from_real_sift(db: Path) -> None:
    """Dot products: safe for any descriptor. L2: for any with norm > 508.43, i.e.
    not clipped at 255 (COLMAP 3.8 emits a few clipped or garbage descriptors for
    keypoints on the image border; 3.8 matches by dot product only)."""
    conn = sqlite3.connect(db)
    real = np.concatenate([
        np.frombuffer(data, np.uint8).reshape(-1, 128)
        for (data,) in conn.execute("SELECT data FROM descriptors")
    ]).astype(np.int64)  # fmt: skip
    conn.close()
    codes = _vc_codes()
    assert np.arccos((real @ codes.T).max() / SQ_NORM) > MAX_SIFT_DISTANCE
    sq_norms = (real**2).sum(1)
    unclipped = sq_norms > 2 * 255**2 + MAX_SIFT_DISTANCE**2 * SQ_NORM
    assert unclipped.mean() > 0.999
    sq_dists = sq_norms[:, None] + (codes**2).sum(1)[None] - 2 * real @ codes.T
    assert sq_dists[unclipped].min() > MAX_SIFT_DISTANCE**2 * SQ_NORM


def test_config_for_schema() -> None:
    assert database_schema.config_for_schema(9, database_schema.Schema.COLMAP_3) == 2
    assert database_schema.config_for_schema(9, database_schema.Schema.COLMAP_4) == 9
    with pytest.raises(ValueError, match=r"unknown to COLMAP 3\.x"):
        database_schema.config_for_schema(10, database_schema.Schema.COLMAP_3)


# ------------------------------------------------------------------ writing


def test_write_keeps_classic_rows_and_reads_back(db: Path, vcs: tuple) -> None:
    keypoints, pairs, geometries = vcs
    before = database.table_checksums(db)
    views = database.read_views(db)
    matches = database.read_matches(db)
    tvgs = database.read_two_view_geometries(db)
    conn = sqlite3.connect(db)
    blobs = {
        t: dict(conn.execute(f"SELECT image_id, data FROM {t}").fetchall())
        for t in ("keypoints", "descriptors")
    }
    conn.close()
    persons = [
        database.PersonAssociation(
            image_id1=1,
            image_id2=2,
            person_id1=0,
            person_id2=1,
            method=database.AssociationMethod.GEOMETRIC,
            score=0.5,
        )
    ]

    summary = database.write_virtual_correspondences(
        db, keypoints, pairs, geometries, persons=persons, run_info={"seed": 0}
    )

    assert summary.num_vcs == sum(len(p) for p in pairs)
    assert summary.num_descriptor_rows == summary.num_vc_keypoints > 0
    assert summary.num_matches_updated == len(matches) == 10
    after = database.table_checksums(db)
    for table in ("cameras", "images", "frames", "rigs", "frame_data"):
        assert after.get(table) == before.get(table)
    conn = sqlite3.connect(db)
    for table, old in blobs.items():  # old blobs are prefixes, new rows follow
        for image_id, data in conn.execute(f"SELECT image_id, data FROM {table}"):
            assert data.startswith(old[image_id])
    for pair_id, data in conn.execute("SELECT pair_id, data FROM matches"):
        old = matches[database_schema.images_from_pair_id(pair_id)]
        assert data.startswith(database_schema.encode_matches(old))
    conn.close()
    # the classic view of the database is the original one
    np.testing.assert_array_equal(
        database.read_views(db).num_keypoints, views.num_keypoints
    )
    assert database.read_matches(db).keys() == matches.keys()
    for key, old_tvg in tvgs.items():
        new_tvg = database.read_two_view_geometries(db)[key]
        np.testing.assert_array_equal(new_tvg.inlier_matches, old_tvg.inlier_matches)
    # the augmented rows
    new_views = database.read_views(db)
    np.testing.assert_array_equal(
        new_views.num_vc_keypoints, [len(kp) for kp in keypoints]
    )
    image_id = keypoints[0].image_id
    np.testing.assert_allclose(
        database.read_keypoints(db, image_id, include_vc=True)[-len(keypoints[0]) :],
        keypoints[0].xy_img,
        atol=1e-4,
    )
    stored = database.read_two_view_geometries(db, include_vc=True)
    for pair in pairs:
        key = (pair.image_id1, pair.image_id2)
        row, geometry = stored[key], geometries[key]
        offsets = views.num_keypoints[np.searchsorted(views.image_ids, key)]
        vc_rows = row.inlier_matches[len(tvgs[key].inlier_matches) :]
        np.testing.assert_array_equal(
            vc_rows, np.column_stack([pair.idx1, pair.idx2])[pair.is_inlier] + offsets
        )
        np.testing.assert_allclose(
            row.cam2_from_cam1, geometry.cam2_from_cam1, atol=1e-12
        )
        np.testing.assert_allclose(row.F, geometry.F)
        assert row.config == 2
    # round trip of the metadata
    kp_back, pairs_back = database.read_virtual_correspondences(db)
    for got, want in zip(kp_back + pairs_back, keypoints + pairs, strict=True):
        for name in want.__slots__:
            np.testing.assert_array_equal(getattr(got, name), getattr(want, name))
    assert database.read_person_associations(db) == persons


@pytest.mark.parametrize("db", SCHEMAS[:1], indirect=True)
def test_pycolmap_reads_quaternion_back(db: Path, vcs: tuple) -> None:
    """pycolmap 4's own reader sees the cam2_from_cam1 we wrote (qvec is w, x, y, z)."""
    database.write_virtual_correspondences(db, *vcs)
    copy = db.with_name("copy.db")  # pycolmap may migrate the file it opens
    shutil.copy(db, copy)
    with pycolmap.Database.open(copy) as pdb:
        geometry = pdb.read_two_view_geometry(1, 3)
        assert len(geometry.inlier_matches) == len(
            database.read_two_view_geometries(db, include_vc=True)[
                (1, 3)
            ].inlier_matches
        )
    np.testing.assert_allclose(
        geometry.cam2_from_cam1.matrix(), vcs[2][(1, 3)].cam2_from_cam1, atol=1e-12
    )


def test_write_twice_equals_once_and_strip_restores(db: Path, vcs: tuple) -> None:
    original = database.table_checksums(db)
    other = _make_vcs(db, np.random.default_rng(1), num_points=30)
    database.write_virtual_correspondences(db, *other, run_info={"seed": 0})
    database.write_virtual_correspondences(db, *vcs, run_info={"seed": 0})
    twice = database.table_checksums(db)
    assert twice != original

    summary = database.strip(db)
    assert summary.had_vcs and summary.num_matches_restored == 10
    assert database.table_checksums(db) == original
    database.write_virtual_correspondences(db, *vcs, run_info={"seed": 0})
    assert database.table_checksums(db) == twice
    database.strip(db)
    assert database.table_checksums(db) == original
    assert not database.strip(db).had_vcs  # stripping a clean database is a no-op


@pytest.mark.parametrize("db", SCHEMAS[:1], indirect=True)
def test_new_pairs_and_classic_inlier_override_are_stripped(db: Path) -> None:
    original = database.table_checksums(db)
    keypoints, pairs, geometries = _make_vcs(db, np.random.default_rng(0))
    _sql(
        db,
        "DELETE FROM matches WHERE pair_id = 2147483649",
        "DELETE FROM two_view_geometries WHERE pair_id = 2147483649",
    )
    without_pair = database.table_checksums(db)
    override = {(1, 3): np.array([[0, 0], [1, 1]])}
    summary = database.write_virtual_correspondences(
        db, keypoints, pairs, geometries, classic_inliers=override
    )
    assert (summary.num_matches_inserted, summary.num_geometries_inserted) == (1, 1)
    inliers = database.read_two_view_geometries(db, include_vc=True)[(1, 3)]
    np.testing.assert_array_equal(inliers.inlier_matches[:2], override[(1, 3)])
    database.strip(db)
    assert database.table_checksums(db) == without_pair != original


def test_failure_inside_transaction_rolls_back(
    db: Path, vcs: tuple, monkeypatch: pytest.MonkeyPatch
) -> None:
    database.write_virtual_correspondences(db, *vcs)
    augmented = database.table_checksums(db)

    def fail(*args: object, **kwargs: object) -> None:
        raise OSError("disk full")

    monkeypatch.setattr(database_write, "write_metadata", fail)
    other = _make_vcs(db, np.random.default_rng(1), num_points=30)
    with pytest.raises(OSError, match="disk full"):
        database.write_virtual_correspondences(db, *other)
    assert database.table_checksums(db) == augmented


@pytest.mark.parametrize("db", SCHEMAS[:1], indirect=True)
def test_killed_process_leaves_database_unchanged(db: Path, vcs: tuple) -> None:
    original = database.table_checksums(db)
    args = db.with_suffix(".pkl")
    args.write_bytes(pickle.dumps(vcs))
    script = (
        "import os, pickle, sys\n"
        "from colmap_vc import database, database_write\n"
        "database_write.write_metadata = lambda *a, **k: os._exit(3)\n"
        "database.write_virtual_correspondences(sys.argv[1], "
        "*pickle.loads(open(sys.argv[2], 'rb').read()))\n"
    )
    result = subprocess.run(
        [sys.executable, "-c", script, str(db), str(args)],
        cwd=Path(__file__).parents[1],
    )
    assert result.returncode == 3  # died after rewriting rows, before COMMIT
    assert database.table_checksums(db) == original


# ------------------------------------------------------------------ errors


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match=r"nothere\.db"):
        database.read_views(tmp_path / "nothere.db")
    with pytest.raises(FileNotFoundError):
        database.strip(tmp_path / "nothere.db")


def test_not_a_database(tmp_path: Path) -> None:
    text = tmp_path / "notes.db"
    text.write_text("this is not sqlite" * 100)
    with pytest.raises(ValueError, match=f"{re.escape(str(text))} is not a SQLite"):
        database.write_virtual_correspondences(text, [], [], {})
    assert text.read_text() == "this is not sqlite" * 100
    other = tmp_path / "other.db"
    _sql(other, "CREATE TABLE things (x)")
    with pytest.raises(ValueError, match=f"{re.escape(str(other))} is not a COLMAP"):
        database.read_views(other)


def test_no_keypoints(tmp_path: Path) -> None:
    empty = tmp_path / "empty.db"
    pycolmap.Database.open(empty).close()
    before = database.table_checksums(empty)
    with pytest.raises(ValueError, match="run feature extraction first"):
        database.write_virtual_correspondences(empty, [], [], {})
    with pytest.raises(ValueError, match="run feature extraction first"):
        database.read_views(empty)
    assert database.table_checksums(empty) == before


@pytest.mark.parametrize("db", SCHEMAS[:1], indirect=True)
def test_locked_database(db: Path, vcs: tuple) -> None:
    before = database.table_checksums(db)
    blocker = sqlite3.connect(db, isolation_level=None)
    blocker.execute("BEGIN IMMEDIATE")  # another writer holds the write lock
    try:
        with pytest.raises(RuntimeError, match=f"{re.escape(str(db))} is locked"):
            database.write_virtual_correspondences(db, *vcs)
        with pytest.raises(RuntimeError, match=f"{re.escape(str(db))} is locked"):
            database.strip(db)
    finally:
        blocker.execute("ROLLBACK")
        blocker.close()
    assert database.table_checksums(db) == before


@pytest.mark.parametrize("db", SCHEMAS[:1], indirect=True)
def test_bad_inputs(db: Path, vcs: tuple) -> None:
    keypoints, pairs, geometries = vcs
    before = database.table_checksums(db)
    ghost = VcKeypoints(
        image_id=99,
        xy_img=np.ones((1, 2)),
        person_id=np.zeros(1, np.int64),
        track_id=np.zeros(1, np.int64),
    )
    with pytest.raises(ValueError, match=r"images \[99\] are not in"):
        database.write_virtual_correspondences(db, [*keypoints, ghost], pairs, {})
    bad_pair = PairVcMatches(
        **{
            **{name: getattr(pairs[0], name) for name in pairs[0].__slots__},
            "image_id2": 99,
        }
    )
    with pytest.raises(ValueError, match="names image 99 without VcKeypoints"):
        database.write_virtual_correspondences(db, keypoints, [bad_pair], {})
    with pytest.raises(ValueError, match="given twice"):
        database.write_virtual_correspondences(db, keypoints, [pairs[0]] * 2, {})
    with pytest.raises(ValueError, match="exceed the keypoint counts"):
        database.write_virtual_correspondences(
            db,
            keypoints,
            pairs,
            geometries,
            classic_inliers={(1, 2): np.array([[10**6, 0]])},
        )
    assert database.table_checksums(db) == before


# ------------------------------------------------------------------ COLMAP still works


@pytest.mark.parametrize("guided", [False, True], ids=["plain", "guided"])
def test_rematching_never_matches_vc_keypoints(
    db: Path, vcs: tuple, guided: bool
) -> None:
    database.write_virtual_correspondences(db, *vcs)
    views = database.read_views(db)
    num_classic = dict(
        zip(views.image_ids.tolist(), views.num_keypoints.tolist(), strict=True)
    )
    _sql(db, "DELETE FROM matches", "DELETE FROM two_view_geometries")
    if views.schema == database.Schema.COLMAP_4:
        _match_pycolmap4(db, guided=guided)
    else:
        _match_colmap38(db, guided=guided)
    assert _assert_no_vc_in_matches(db, num_classic) > 1000


def _vc_observations(
    reconstruction: pycolmap.Reconstruction, num_classic: dict[int, int]
) -> int:
    """Number of VC keypoints that became observations of 3D points."""
    total = 0
    for image in reconstruction.images.values():
        idx = np.asarray(image.get_observation_point2D_idxs())
        total += int((idx >= num_classic[image.image_id]).sum())
    return total


def test_mappers_run_on_augmented_database(
    db: Path, vcs: tuple, scene_dir: Path, tmp_path: Path
) -> None:
    database.write_virtual_correspondences(db, *vcs)
    views = database.read_views(db)
    num_classic = dict(
        zip(views.image_ids.tolist(), views.num_keypoints.tolist(), strict=True)
    )
    out = tmp_path / "sparse"
    out.mkdir()
    if views.schema == database.Schema.COLMAP_4:
        pycolmap.set_random_seed(0)
        models = pycolmap.incremental_mapping(
            db,
            scene_dir / "images",
            out,
            pycolmap.IncrementalPipelineOptions(num_threads=1),
        )
        reconstruction = max(models.values(), key=lambda r: r.num_reg_images())
    else:
        _colmap(
            "mapper",
            "--database_path",
            str(db),
            "--image_path",
            str(scene_dir / "images"),
            "--output_path",
            str(out),
            "--Mapper.num_threads",
            "1",
        )
        reconstruction = pycolmap.Reconstruction(out / "0")
    assert reconstruction.num_reg_images() == NUM_IMAGES
    assert _vc_observations(reconstruction, num_classic) > 100


def test_colmap_vc_map_never_changes_the_database(
    db: Path, vcs: tuple, scene_dir: Path, tmp_path: Path
) -> None:
    """`map` reads: the file is byte-identical, a 3.8 database keeps its schema, and
    `strip` still restores the tables from before `augment` (issue 13, harm 2)."""
    import hashlib

    from colmap_vc import mapping

    original = database.table_checksums(db)
    database.write_virtual_correspondences(db, *vcs)
    digest = hashlib.sha256(db.read_bytes()).hexdigest()
    conn = sqlite3.connect(db)
    tables = database_schema.table_names(conn)
    conn.close()
    mapping.run(db, scene_dir / "images", tmp_path / "sparse")
    assert hashlib.sha256(db.read_bytes()).hexdigest() == digest
    conn = sqlite3.connect(db)
    assert database_schema.table_names(conn) == tables  # no frames/rigs added
    conn.close()
    database.strip(db)
    assert database.table_checksums(db) == original


def test_strip_refuses_after_user_changes_and_force_keeps_them(
    db: Path, vcs: tuple
) -> None:
    """The user re-matches one pair and deletes another after augment: strip refuses
    with nothing changed; --force keeps both edits and leaves no VC index behind
    (issue 13, harm 3)."""
    original = database.table_checksums(db)
    views = database.read_views(db)
    num_classic = dict(
        zip(views.image_ids.tolist(), views.num_keypoints.tolist(), strict=True)
    )
    database.write_virtual_correspondences(db, *vcs)
    pair_ids = [
        row[0]
        for row in sqlite3.connect(db).execute(
            "SELECT pair_id FROM matches WHERE rows > 1 ORDER BY pair_id"
        )
    ]
    changed, deleted = pair_ids[0], pair_ids[1]
    _sql(
        db,
        "UPDATE matches SET data = substr(data, 1, 8 * (rows - 1)), rows = rows - 1 "
        f"WHERE pair_id = {changed}",
        f"DELETE FROM matches WHERE pair_id = {deleted}",
    )
    edited = database.table_checksums(db)
    with pytest.raises(ValueError, match="strip refused, nothing changed") as error:
        database.strip(db)
    assert "matches rows of 1 pair(s) changed" in str(error.value)
    assert "matches rows of 1 pair(s) deleted" in str(error.value)
    assert database.table_checksums(db) == edited

    database.strip(db, force=True)
    after = database.table_checksums(db)
    assert not [t for t in after if t.startswith("colmap_vc_")]
    for table in ("keypoints", "descriptors", "two_view_geometries"):
        assert after[table] == original[table], table
    conn = sqlite3.connect(db)
    kept = dict(conn.execute("SELECT pair_id, rows FROM matches"))
    conn.close()
    assert deleted not in kept  # the user's deletion stays
    assert kept[changed] > 0  # the user's re-match stays, minus the VC matches
    _assert_no_vc_in_matches(db, num_classic)
