"""Mesh alignment of several people: a rotation per person, averaged robustly."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from colmap_vc.evaluation import rotation_angle_deg
from colmap_vc.meshalign import mesh_alignment, procrustes
from colmap_vc.structs import ImagePrior, PersonPrior

FACES = np.zeros((1, 3), dtype=np.int64)


def _prior(meshes: list[np.ndarray]) -> ImagePrior:
    return ImagePrior(
        image_name="image.jpg",
        persons=tuple(
            PersonPrior(vertices_cam=v, faces=FACES, person_id=k)
            for k, v in enumerate(meshes)
        ),
    )


def _scene(rng, num_people: int):
    """People (50-vertex bodies, 1.7 m tall) 4-6 m in front of camera 1, and
    camera 2's true cam2_from_cam1: 70 deg around the vertical, 5 m aside."""
    body = rng.normal(0.0, 1.0, (50, 3)) * [0.2, 0.5, 0.1]
    people = [
        body @ Rotation.from_euler("y", rng.uniform(0, 360), degrees=True).as_matrix().T
        + [rng.uniform(-2, 2), 0.0, rng.uniform(4, 6)]
        for _ in range(num_people)
    ]
    R = Rotation.from_euler("y", 70, degrees=True).as_matrix()
    t = np.array([-5.0, 0.0, 3.0])
    return people, R, t


def _in_camera2(X: np.ndarray, R: np.ndarray, t: np.ndarray, depth: float = 1.0):
    """X seen by camera 2, its body placed ``depth`` times as far along its ray
    (a monocular mesh's depth error: shape right, distance wrong)."""
    Y = X @ R.T + t
    c = Y.mean(axis=0)
    return Y - c + depth * c


def test_people_placed_at_wrong_depths_still_give_the_rotation(rng):
    """Each person's mesh in camera 2 sits 25-40 % too near or far: one rigid fit
    of all vertices is pulled by where the people stand relative to each other,
    the average of the per-person rotations is not."""
    people, R, t = _scene(rng, 3)
    depths = [1.4, 0.75, 1.25]
    first = _prior(people)
    second = _prior(
        [_in_camera2(X, R, t, d) for X, d in zip(people, depths, strict=True)]
    )
    T = mesh_alignment(first, second)
    assert T is not None and rotation_angle_deg(T[:, :3] @ R.T) < 1e-6
    together = procrustes(
        np.concatenate(people), np.concatenate([p.vertices_cam for p in second.persons])
    )
    assert rotation_angle_deg(together[:, :3] @ R.T) > 5.0  # the old fit


def test_a_mesh_turned_front_to_back_is_left_out(rng):
    """One of three people turned 180 deg about their own vertical (a pose
    estimator that took the back for the front): the other two give the rotation.
    With two people, one turned, nothing says which: one rigid fit of both, as
    without the average."""
    people, R, t = _scene(rng, 3)
    seen = [_in_camera2(X, R, t) for X in people]
    c = seen[1].mean(axis=0)
    turn = Rotation.from_euler("y", 180, degrees=True).as_matrix()
    seen[1] = (seen[1] - c) @ turn.T + c
    T = mesh_alignment(_prior(people), _prior(seen))
    assert T is not None and rotation_angle_deg(T[:, :3] @ R.T) < 1e-6
    assert np.allclose(T[:, 3], t, atol=1e-6)  # the two agreeing people's offset
    both = mesh_alignment(_prior(people[:2]), _prior(seen[:2]))
    together = procrustes(np.concatenate(people[:2]), np.concatenate(seen[:2]))
    assert both is not None and np.allclose(both, together)


@pytest.mark.parametrize("num_people", [1, 2])
def test_one_or_two_agreeing_people_give_the_exact_pose(rng, num_people):
    people, R, t = _scene(rng, num_people)
    T = mesh_alignment(_prior(people), _prior([_in_camera2(X, R, t) for X in people]))
    assert T is not None
    assert rotation_angle_deg(T[:, :3] @ R.T) < 1e-6 and np.allclose(T[:, 3], t)
