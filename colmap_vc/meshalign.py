"""Mesh alignment: relative camera poses from the predicted body meshes alone.

The paper's "deep optimization" analog and colmap-vc's coarse prior: the same person's
predicted meshes in two cameras (same topology, vertex to vertex) aligned rigidly give
cam2_from_cam1 up to the meshes' errors (about 10-20 degrees). With several people,
each person gives a rotation and they are averaged; one rigid fit of all their
vertices together would rest on where the people stand relative to each other,
which monocular meshes place by their depth, far less well than their own shape.
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


TURNED_DEG = 90.0
"""A person's rotation farther than this from the others' consensus is a mesh turned
front to back (a pose estimator that took the back for the front), not a mesh error
(10-25 deg): it is left out of the average. The same bound as
``MappingOptions.max_image_prior_deviation_deg``."""


def mesh_alignment(prior1: ImagePrior, prior2: ImagePrior) -> FloatArray | None:
    """cam2_from_cam1 (3, 4) from the predicted meshes of the people both images share.

    The paper's "deep optimization" analog: the same person's two predicted meshes
    (same topology, vertex to vertex) aligned rigidly. People are matched by id; two
    images with one person each and no ids (what ``colmap-vc priors`` writes for
    one-person scenes) are taken to show the same person, as ``augment``'s geometric
    association takes them. Otherwise an image pair without a shared id gives None.

    Several shared people: each person's rigid fit gives a rotation; the one
    closest to the others (their medoid) and those within :data:`TURNED_DEG` of
    it are averaged (the chordal mean), and the translation is their centroids'
    mean offset under it. Two people whose rotations are farther apart than that
    say nothing about which mesh is turned: their vertices are fitted together,
    as one rigid fit (leaving such images without a mesh pose cost
    pose2sim_single t070 two of its four cameras, whose second "person" is a
    false detection). One rigid fit of every person's vertices together put the
    16-view, 3-person speed dome's cameras 55-155 deg from its reference image,
    where each person's own fit was within 25 deg of the truth: it rests on
    where the meshes put the people relative to each other, which monocular
    depth errors move (docs/real-data.md, "The meshes' poses with several
    people").
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
    if len(pairs) == 1:
        return procrustes(pairs[0][0].vertices_cam, pairs[0][1].vertices_cam)
    R = np.stack([procrustes(p.vertices_cam, q.vertices_cam)[:, :3] for p, q in pairs])
    # Angles between every two people's rotations, from the trace of R_i R_j^T.
    cos = (np.einsum("iab,jab->ij", R, R) - 1.0) / 2.0
    angle = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    medoid = int(np.argmin(angle.sum(axis=1)))
    keep = angle[medoid] <= TURNED_DEG
    if keep.sum() < 2 and len(pairs) == 2:
        return procrustes(  # nothing says which mesh is turned: one rigid fit
            np.concatenate([p.vertices_cam for p, _ in pairs]),
            np.concatenate([q.vertices_cam for _, q in pairs]),
        )
    U, _, Vt = np.linalg.svd(R[keep].sum(axis=0))
    mean = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    src = np.array([p.vertices_cam.mean(axis=0) for p, _ in pairs])[keep]
    dst = np.array([q.vertices_cam.mean(axis=0) for _, q in pairs])[keep]
    t = (dst - src @ mean.T).mean(axis=0)
    return np.concatenate([mean, t[:, None]], axis=1)


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
