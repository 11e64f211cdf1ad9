"""Anny bodies: shared topology, numpy LBS reproduces the export, surface, joints."""

import json

import numpy as np
import pytest
import trimesh

from colmap_vc.synthetic import bodies as body_lib

# From colmap_vc/data/anny_bodies.json ("validation"): numpy LBS with 4 fitted
# weights vs Anny's own skinning, max 4.5 mm and mean 0.015 mm over all 48 meshes.
LBS_MAX_M = 6e-3
LBS_MEAN_M = 1e-4


@pytest.fixture(scope="module")
def model() -> body_lib.BodyModel:
    return body_lib.load_bodies()


@pytest.fixture(scope="module")
def info() -> dict:
    return json.loads(body_lib.DEFAULT_PATH.with_suffix(".json").read_text())


def test_shapes_dtypes_and_shared_topology(model, info):
    num_p, num_q, num_v, _ = model.posed_vertices.shape
    assert (num_p, num_q) == (len(model.phenotype_names), len(model.pose_names))
    assert num_p >= 6 and num_q >= 8
    assert model.posed_vertices.dtype == np.float64
    assert model.faces.dtype == np.int64 and model.faces.max() == num_v - 1
    assert model.rest_vertices.shape == (num_p, num_v, 3)
    assert info["counts"]["vertices"] == num_v and info["counts"]["faces"] == len(
        model.faces
    )
    # One closed surface: every edge is shared by exactly two faces.
    mesh = trimesh.Trimesh(model.rest_vertices[0], model.faces, process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.volume > 0  # outward normals
    required = {"head", "torso", "foot_left", "foot_right"} | {
        f"{part}_{side}"
        for part in ("upper_arm", "lower_arm", "hand", "upper_leg", "lower_leg")
        for side in ("left", "right")
    }
    assert required <= set(model.part_names)
    assert set(np.unique(model.face_part)) == set(range(len(model.part_names)))
    assert model.joint_names[0] == "pelvis"
    assert np.allclose(model.skin_w.sum(axis=1), 1.0) and (model.skin_w >= 0).all()
    assert np.allclose(model.joint_regressor_w.sum(axis=1), 1.0, atol=1e-5)
    # Articulation-noise scales: none on the root, one joint's worth along the spine.
    scale = model.bone_sigma_scale
    assert scale[model.bone_parent < 0] == 0 and ((scale >= 0) & (scale <= 1)).all()
    spine = [i for i, n in enumerate(model.bone_names) if n.startswith("spine")]
    assert np.isclose(np.sum(scale[spine] ** 2), 1.0)


@pytest.mark.parametrize("phenotype", range(6))
def test_numpy_lbs_reproduces_the_export(model, phenotype):
    for pose in range(model.num_poses):
        posed = body_lib.pose_body(model, phenotype, pose)
        err = np.linalg.norm(posed - model.posed_vertices[phenotype, pose], axis=1)
        assert err.max() < LBS_MAX_M and err.mean() < LBS_MEAN_M, model.pose_names[pose]


def test_bodies_are_grounded_and_face_plus_y(model):
    posed = model.posed_vertices
    assert np.abs(posed[..., 2].min(axis=-1)).max() < 2e-4  # int16 rounding
    pelvis = body_lib.joints(model, posed)[..., 0, :]
    assert np.abs(pelvis[..., :2]).max() < 0.02
    rest = model.rest_vertices[2]
    part = np.array(model.part_names)[model.face_part]

    def centre(name: str) -> np.ndarray:
        return rest[np.unique(model.faces[part == name])].mean(axis=0)

    # Person's left on -X; toes point forward (+Y) from the ankles.
    assert centre("hand_left")[0] < -0.2 < 0.2 < centre("hand_right")[0]
    ankle = body_lib.joints(model, rest)[model.joint_names.index("left_ankle")]
    assert centre("foot_left")[1] > ankle[1] + 0.03


def test_heights_are_plausible(model):
    heights = np.ptp(
        model.posed_vertices[:, model.pose_names.index("standing"), :, 2], axis=1
    )
    for name, height in zip(model.phenotype_names, heights, strict=True):
        if name == "child":
            assert 1.0 < height < 1.5
        else:
            assert 1.5 < height < 2.0, name


def test_template_samples_lie_on_every_body(model):
    s = len(model.template_face_idx)
    assert 1500 <= s <= 3000
    assert (model.template_bary >= 0).all()
    assert np.allclose(model.template_bary.sum(axis=1), 1.0, atol=1e-6)
    for verts in model.posed_vertices.reshape(-1, *model.posed_vertices.shape[2:]):
        points = body_lib.template_points(model, verts)
        mesh = trimesh.Trimesh(verts, model.faces, process=False)
        _, dist, _ = trimesh.proximity.closest_point(mesh, points[::20])
        assert dist.max() < 1e-6
    # Spread evenly over the surface: no two samples much closer than their spacing.
    points = body_lib.template_points(model, model.rest_vertices.mean(axis=0))
    d = np.linalg.norm(points[:, None] - points[None], axis=-1)
    np.fill_diagonal(d, np.inf)
    nearest = d.min(axis=1)
    assert nearest.min() > 0.4 * np.median(nearest)


@pytest.mark.parametrize("phenotype", range(6))
def test_joints_are_inside_the_standing_body(model, phenotype):
    verts = model.posed_vertices[phenotype, model.pose_names.index("standing")]
    mesh = trimesh.Trimesh(verts, model.faces, process=False)
    assert mesh.contains(body_lib.joints(model, verts)).all()


def test_mirror_of_mirror_is_identity(model):
    rng = np.random.default_rng(0)
    face = rng.integers(len(model.faces), size=500)
    bary = rng.dirichlet(np.ones(3), size=500)
    face1, bary1 = body_lib.mirror_surface(model, face, bary)
    face2, bary2 = body_lib.mirror_surface(model, face1, bary1)
    assert np.array_equal(face2, face) and np.allclose(bary2, bary)
    assert not np.array_equal(face1, face)


@pytest.mark.parametrize("phenotype", range(6))
def test_mirror_is_the_x_reflection_at_rest(model, phenotype):
    rest = model.rest_vertices[phenotype]
    face, bary = body_lib.mirror_surface(
        model, model.template_face_idx, model.template_bary
    )
    mirrored = body_lib.surface_points(model, rest, face, bary)
    reflected = body_lib.template_points(model, rest) * [-1.0, 1.0, 1.0]
    assert np.linalg.norm(mirrored - reflected, axis=1).max() < 2e-3


def test_perturbing_a_bone_moves_only_its_subtree(model):
    bone = model.bone_names.index("lowerarm01.L")  # the left elbow
    delta = np.zeros_like(model.pose_rotvec[0])
    delta[bone] = [0.3, -0.2, 0.4]
    standing = model.pose_names.index("standing")
    before = body_lib.pose_body(model, 2, standing)
    after = body_lib.pose_body(model, 2, standing, delta_rotvec=delta)
    subtree = body_lib.bone_subtree(model, bone)
    skinned = (np.isin(model.skin_idx, subtree) & (model.skin_w > 0)).any(axis=1)
    moved = np.linalg.norm(after - before, axis=1) > 1e-9
    assert moved.any() and not (moved & ~skinned).any()
    assert set(np.array(model.bone_names)[subtree]) == {
        "lowerarm01.L",
        "lowerarm02.L",
        "wrist.L",
    }


def test_undoing_the_pose_gives_the_rest_shape(model):
    pose = model.pose_names.index("dancing")
    verts = body_lib.pose_body(model, 4, pose, delta_rotvec=-model.pose_rotvec[pose])
    assert np.allclose(verts, model.rest_vertices[4], atol=1e-6)


def test_shape_blend_interpolates_phenotypes(model):
    pose = model.pose_names.index("walking")
    same = body_lib.pose_body(model, 0, pose, shape_blend=(3, 0.0))
    other = body_lib.pose_body(model, 0, pose, shape_blend=(3, 1.0))
    assert np.allclose(same, body_lib.pose_body(model, 0, pose))
    assert np.allclose(other, body_lib.pose_body(model, 3, pose))


def test_bad_inputs_raise(model, tmp_path):
    with pytest.raises(FileNotFoundError, match="make bodies"):
        body_lib.load_bodies(tmp_path / "missing.npz")
    with pytest.raises(ValueError, match="delta_rotvec"):
        body_lib.pose_body(model, 0, 0, delta_rotvec=np.zeros((3, 3)))
    with pytest.raises(ValueError, match="out of range"):
        body_lib.pose_body(model, model.num_phenotypes, 0)
