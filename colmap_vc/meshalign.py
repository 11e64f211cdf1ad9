"""Mesh alignment: relative camera poses from the predicted body meshes alone.

The paper's "deep optimization" analog and colmap-vc's coarse prior: the same person's
predicted meshes in two cameras (same topology, vertex to vertex) aligned rigidly give
cam2_from_cam1 up to the meshes' errors (about 10-20 degrees), with no gross failures.
"""

from __future__ import annotations

from collections.abc import Collection

import numpy as np

from .structs import FloatArray, ImagePrior, PersonPrior, ScenePriors


def procrustes(src: FloatArray, dst: FloatArray) -> FloatArray:
    """Kabsch: the rigid (3, 4) [R | t] minimising ||R src + t - dst|| (no scale)."""
    mu_s, mu_d = src.mean(axis=0), dst.mean(axis=0)
    U, _, Vt = np.linalg.svd((dst - mu_d).T @ (src - mu_s))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt
    return np.concatenate([R, (mu_d - R @ mu_s)[:, None]], axis=1)


def mesh_alignment(prior1: ImagePrior, prior2: ImagePrior) -> FloatArray | None:
    """cam2_from_cam1 (3, 4) from the predicted meshes of the people both images share.

    The paper's "deep optimization" analog: the same person's two predicted meshes
    (same topology, vertex to vertex) aligned rigidly. People are matched by id; two
    images with one person each and no ids (what ``colmap-vc priors`` writes for
    one-person scenes) are taken to show the same person, as ``augment``'s geometric
    association takes them. Otherwise an image pair without a shared id gives None.
    """
    pairs: list[tuple[PersonPrior, PersonPrior]] = []
    if (
        len(prior1.persons) == 1
        and len(prior2.persons) == 1
        and None in (prior1.persons[0].person_id, prior2.persons[0].person_id)
    ):
        pairs = [(prior1.persons[0], prior2.persons[0])]
    else:
        by_id = {p.person_id: p for p in prior2.persons if p.person_id is not None}
        pairs = [
            (p, by_id[p.person_id])
            for p in prior1.persons
            if p.person_id is not None and p.person_id in by_id
        ]
    pairs = [(p, q) for p, q in pairs if len(p.vertices_cam) == len(q.vertices_cam)]
    if not pairs:
        return None
    return procrustes(
        np.concatenate([p.vertices_cam for p, _ in pairs]),
        np.concatenate([q.vertices_cam for _, q in pairs]),
    )


def mesh_alignment_poses(
    priors: ScenePriors, image_names: Collection[str] | None = None
) -> dict[str, FloatArray]:
    """cam_from_world (3, 4) per image from mesh alignment alone.

    The world is the camera frame of a reference image (the one seeing the most
    people); every other image is placed by :func:`mesh_alignment` of the people it
    shares with the reference. Images sharing no person with it are left out
    (unregistered). ``image_names`` restricts the images considered.
    """
    names = sorted(n for n in priors.images if image_names is None or n in image_names)
    if not names:
        return {}
    ref = max(names, key=lambda n: len(priors.images[n].persons))
    poses = {ref: np.concatenate([np.eye(3), np.zeros((3, 1))], axis=1)}
    for name in names:
        if name == ref:
            continue
        T = mesh_alignment(priors.images[ref], priors.images[name])
        if T is not None:
            poses[name] = T  # cam_from_(ref cam) = cam_from_world
    return poses
