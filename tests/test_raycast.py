"""Ray casting: hits lie on the mesh and reproject to their pixels; misses are empty."""

import numpy as np
import pycolmap
import pytest
import trimesh

from colmap_vc import raycast


@pytest.fixture(scope="module")
def sphere_and_box():
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    box = trimesh.creation.box(extents=[0.5, 0.5, 0.5])
    box.apply_translation([0.3, -0.2, 2.0])
    return [
        (np.asarray(sphere.vertices), np.asarray(sphere.faces)),
        (np.asarray(box.vertices), np.asarray(box.faces)),
    ]


CAMERAS = [
    pycolmap.Camera(model="PINHOLE", width=160, height=120, params=[150, 150, 80, 60]),
    pycolmap.Camera(
        model="OPENCV",
        width=160,
        height=120,
        params=[150, 151, 81, 59, -0.1, 0.02, 1e-3, -1e-3],
    ),
]


def _pose() -> np.ndarray:
    angle = 0.3
    R = np.array(
        [
            [np.cos(angle), 0, np.sin(angle)],
            [0, 1, 0],
            [-np.sin(angle), 0, np.cos(angle)],
        ]
    )
    centre = np.array([-1.2, 0.1, -4.0])
    return np.c_[R, -R @ centre]


@pytest.mark.parametrize("camera", CAMERAS, ids=lambda c: c.model.name)
def test_hits_reproject_to_their_pixels(sphere_and_box, camera):
    scene = raycast.build_scene(sphere_and_box)
    cam_from_world = _pose()
    xy = raycast.pixel_grid(camera.width, camera.height)
    origins, dirs = raycast.rays_world(camera, cam_from_world, xy)
    hits = raycast.all_hits(scene, origins, dirs)
    assert len(hits) > 100
    points = np.zeros((len(hits), 3))
    for g, (v, f) in enumerate(sphere_and_box):
        sel = hits.geom_idx == g
        points[sel] = raycast.surface_points(v, f, hits.face_idx[sel], hits.bary[sel])
    along_ray = origins[hits.ray_idx] + hits.depth[:, None] * dirs[hits.ray_idx]
    np.testing.assert_allclose(points, along_ray, atol=1e-9)
    reproj, z = raycast.project(camera, cam_from_world, points)
    assert (z > 0).all()
    assert np.abs(reproj - xy[hits.ray_idx]).max() < 1e-6
    # Hits of one ray are sorted by depth and barycentrics are valid.
    same_ray = hits.ray_idx[1:] == hits.ray_idx[:-1]
    assert (np.diff(hits.depth)[same_ray] > 0).all()
    assert (hits.bary > -1e-9).all() and np.allclose(hits.bary.sum(1), 1.0)


def test_rays_through_a_closed_sphere_hit_it_twice(sphere_and_box):
    scene = raycast.build_scene(sphere_and_box[:1])
    rng = np.random.default_rng(0)
    targets = rng.uniform(-0.5, 0.5, size=(500, 3))  # inside the unit sphere
    origins = np.tile([0.0, 0.0, -5.0], (500, 1))
    dirs = targets - origins
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    hits = raycast.all_hits(scene, origins, dirs)
    np.testing.assert_array_equal(np.bincount(hits.ray_idx, minlength=500), 2)


def test_misses_return_empty_arrays(sphere_and_box):
    scene = raycast.build_scene(sphere_and_box)
    origins = np.array([[10.0, 10.0, 10.0]])
    dirs = np.array([[0.0, 0.0, 1.0]])
    hits = raycast.all_hits(scene, origins, dirs)
    assert len(hits) == 0
    assert hits.bary.shape == (0, 3) and hits.bary.dtype == np.float64
    assert hits.face_idx.dtype == np.int64 and hits.depth.shape == (0,)
    geom, face, depth, _bary = raycast.first_hits(scene, origins, dirs)
    assert face[0] == -1 and geom[0] == -1 and np.isinf(depth[0])
    empty = raycast.all_hits(scene, np.zeros((0, 3)), np.zeros((0, 3)))
    assert len(empty) == 0 and empty.bary.shape == (0, 3)


def test_embree_and_brute_force_agree(sphere_and_box):
    pytest.importorskip("embreex")
    embree = raycast.build_scene(sphere_and_box)
    assert embree.uses_embree
    brute = raycast.MeshScene(embree.vertices, embree.faces, None, uses_embree=False)
    rng = np.random.default_rng(1)
    origins = rng.normal(size=(400, 3)) * 0.1 + [0, 0, -5]
    dirs = rng.normal(size=(400, 3)) * 0.15 + [0, 0, 1]
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    a = raycast.all_hits(embree, origins, dirs)
    b = raycast.all_hits(brute, origins, dirs)
    np.testing.assert_array_equal(a.ray_idx, b.ray_idx)
    np.testing.assert_array_equal(a.face_idx, b.face_idx)
    np.testing.assert_allclose(a.depth, b.depth, atol=1e-9)


def test_bad_shapes_raise():
    with pytest.raises(ValueError, match="origins"):
        raycast.first_hits(
            raycast.build_scene([(np.eye(3), np.array([[0, 1, 2]]))]),
            np.zeros((2, 2)),
            np.zeros((2, 3)),
        )


def test_inside_face_clips_grazing_hits_into_their_face() -> None:
    bary = np.array([[-0.0012, 0.2236, 0.7776], [0.2, 0.3, 0.5], [0.0, 0.0, 0.0]])
    hit = np.array([True, True, False])
    out = raycast.inside_face(bary, hit)
    assert (out[hit] >= 0).all() and np.allclose(out[hit].sum(axis=1), 1.0)
    assert np.allclose(out[1], bary[1]) and np.allclose(out[2], 0.0)
    assert np.abs(out[0] - bary[0]).max() < 2e-3
