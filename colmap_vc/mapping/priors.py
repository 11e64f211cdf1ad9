"""The people's meshes as a check on a model, and the priors `map` uses.

A model is compared with the relative poses the meshes give (mesh alignment): the
whole model (:func:`prior_deviation_deg`, `auto` mapper) and each image
(:func:`leave_out_prior_outliers_inplace`: a wrong camera is worse than none); and
each image with the up its people's meshes give, against the other images' views
of the same people (:func:`leave_out_tilted_inplace`).
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Collection, Mapping
from pathlib import Path

import numpy as np
import pycolmap

from .. import database
from ..estimators.body import anny_keypoint_mirror, body_axis_points
from ..evaluation import poses_by_name, relative_pose, rotation_angle_deg
from ..gravity import long_axis_up
from ..meshalign import mesh_alignment, mesh_alignment_poses
from ..priors import read_priors
from ..structs import ScenePriors
from ..vc_records import VcRecords, person_identities

logger = logging.getLogger(__name__)


def pair_deviations_deg(
    rec: pycolmap.Reconstruction, priors: ScenePriors, names: Collection[str]
) -> dict[tuple[str, str], float]:
    """Rotation difference (deg) between the model's relative pose of two of its
    posed images ``names`` and their own mesh alignment, keyed both ways, for the
    pairs that share people.

    Each pair by its own meshes, not through one reference image: a reference
    whose alignment to an image errs (a mesh turned front to back, people whose
    layout the two images' meshes disagree on) would give every pair of that
    image the same error, and a median over pairs would not protect it.
    """
    model = poses_by_name(rec)
    posed = sorted(n for n in names if n in model and n in priors.images)
    dev: dict[tuple[str, str], float] = {}
    for i, a in enumerate(posed):  # loop over image pairs (3x3 fits, cheap)
        for b in posed[i + 1 :]:
            T = mesh_alignment(priors.images[a], priors.images[b])  # b_from_a
            if T is not None:
                dev[a, b] = dev[b, a] = rotation_angle_deg(
                    relative_pose(model[a], model[b])[:, :3] @ T[:, :3].T
                )
    return dev


def prior_deviation_deg(
    rec: pycolmap.Reconstruction,
    priors: ScenePriors,
    exempt: frozenset[str] = frozenset(),
) -> float:
    """Median rotation difference (deg) of a model's and the meshes' relative poses,
    over the pairs of its images not both in ``exempt`` (images that classic
    matches place: the meshes do not judge their relative pose); 0 without such
    a pair.

    The meshes' relative poses here are read through one reference image
    (:func:`~colmap_vc.meshalign.mesh_alignment_poses`), not pair by pair as the
    per-image check reads them: the `auto` choice's 35 deg was set on that
    reading, and reading the pairs instead moved pose2sim_single t050 from 81 to
    75 AUC@15 and kept pose2sim_multi t090's wrong cam03 (docs/real-data.md)."""
    model = poses_by_name(rec)
    mesh = mesh_alignment_poses(priors, image_names=set(model))
    common = sorted(set(mesh) & set(model))
    diffs = [
        rotation_angle_deg(
            relative_pose(model[a], model[b])[:, :3]
            @ relative_pose(mesh[a], mesh[b])[:, :3].T
        )
        for i, a in enumerate(common)
        for b in common[i + 1 :]
        if not (a in exempt and b in exempt)
    ]
    return float(np.median(diffs)) if diffs else 0.0


def keypoint_mirror(
    num_samples: int, priors: ScenePriors | None
) -> dict[int, int] | None:
    """Template track id -> its left/right counterpart's, for the camera check."""
    if priors is None:
        return None
    persons = [p for ip in priors.images.values() for p in ip.persons]
    perm = anny_keypoint_mirror(persons)
    if perm is None:
        return None
    if num_samples <= 0:
        return None
    return {num_samples + k: num_samples + int(j) for k, j in enumerate(perm.tolist())}


def leave_out_prior_outliers_inplace(
    rec: pycolmap.Reconstruction,
    priors: ScenePriors,
    max_deviation_deg: float,
    *,
    exempt: frozenset[str] = frozenset(),
) -> dict[str, str]:
    """Deregister images whose pose contradicts the meshes (image name -> why).

    Per registered image: the median over its pairs (with the other registered
    images it shares people with) of the rotation difference between the model's
    relative pose and the pair's own mesh alignment (:func:`pair_deviations_deg`).
    The worst image above ``max_deviation_deg`` is left out, then the next, while
    3 or more remain (with 2 the images cannot tell which of the two is wrong). A
    wrong camera is worse than none.
    """
    if max_deviation_deg <= 0:
        return {}
    image_ids = {im.name: i for i, im in rec.images.items() if im.has_pose}
    dev = pair_deviations_deg(rec, priors, set(image_ids) - exempt)
    placed = sorted({a for a, _ in dev})
    left: dict[str, str] = {}
    while len(placed) >= 3:
        pairs = {a: [dev[a, b] for b in placed if (a, b) in dev] for a in placed}
        medians = {a: float(np.median(d)) for a, d in pairs.items() if d}
        logger.debug("deviation from the meshes: %s", medians)
        worst = max(medians, key=lambda a: (medians[a], a))
        if medians[worst] <= max_deviation_deg:
            break
        left[worst] = (
            f"left out: its pose contradicts the body meshes (relative rotations "
            f"{medians[worst]:.0f} deg from theirs, median over the "
            f"{len(pairs[worst])} images it shares people with; more than any "
            f"mesh error, {max_deviation_deg:g} deg)"
        )
        _leave_out(rec, image_ids[worst], left[worst])
        placed.remove(worst)
    return left


def people_up_deviations_deg(
    rec: pycolmap.Reconstruction, priors: ScenePriors, names: Collection[str]
) -> dict[str, dict[int, float]]:
    """Per posed image of ``names``, per identified person that two or more other
    posed images of ``names`` see: the angle (deg) between the person's up in this
    image and the mean of the other images' ups of that person, all turned into
    the world by the model. A person's up is the long axis of its 3D keypoints
    off the arms (:func:`~colmap_vc.estimators.body.body_axis_points`; the mesh's
    for priors without named keypoints); a person's several priors in one image
    (a static camera's instants) are averaged.

    One body seen at one instant has one up, whichever way it leans or is turned:
    a mesh turned front to back (a person seen from the back taken as facing the
    camera) keeps its long axis, where its relative rotation is 180 deg off. The
    difference is the camera's tilt error plus the meshes'."""
    model = poses_by_name(rec)
    posed = sorted(n for n in names if n in model and n in priors.images)
    world: dict[int, dict[str, np.ndarray]] = {}
    for n in posed:  # loop over images, then their people (a handful)
        axes: dict[int, list[np.ndarray]] = {}
        for p in priors.images[n].persons:
            if p.person_id is not None:
                axes.setdefault(p.person_id, []).append(
                    long_axis_up(body_axis_points(p))
                )
        for pid, a in axes.items():
            up = np.mean(a, axis=0)
            world.setdefault(pid, {})[n] = model[n][:, :3].T @ (up / np.linalg.norm(up))
    out: dict[str, dict[int, float]] = {}
    for pid, views in sorted(world.items()):
        if len(views) < 3:
            continue  # with one other view, nothing says which of the two is wrong
        ups = np.array([views[n] for n in sorted(views)])
        others = ups.sum(axis=0) - ups  # row i: the sum of the other views' ups
        cos = np.einsum("ij,ij->i", ups, others) / np.linalg.norm(others, axis=1)
        angle = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
        for n, a in zip(sorted(views), angle.tolist(), strict=True):
            out.setdefault(n, {})[pid] = a
    return out


def leave_out_tilted_inplace(
    rec: pycolmap.Reconstruction,
    priors: ScenePriors,
    min_deg: float,
    ratio: float,
    *,
    exempt: frozenset[str] = frozenset(),
) -> dict[str, str]:
    """Deregister images whose pose tilts their people away from the up the other
    images give the same people (image name -> why).

    Per registered image: the median over its people of
    :func:`people_up_deviations_deg`. The worst image is left out when that is
    above ``min_deg`` and above ``ratio`` times the median deviation of the other
    images' people judged without it (the scene's own noise: the meshes' tilt
    errors depend on the pose estimator); then the others are judged again,
    while 4 or more remain (the others' noise is read from people that three
    other images see). The check needs no vertical lines in the scene
    (the gravity step's up check does). ``min_deg`` <= 0: no check."""
    if min_deg <= 0:
        return {}
    image_ids = {im.name: i for i, im in rec.images.items() if im.has_pose}
    placed = sorted(set(image_ids) - exempt)
    left: dict[str, str] = {}
    while len(placed) >= 4:
        dev = people_up_deviations_deg(rec, priors, placed)
        medians = {n: float(np.median(list(d.values()))) for n, d in dev.items()}
        if not medians:
            break
        logger.debug("people's up against the other images': %s", medians)
        worst = max(medians, key=lambda n: (medians[n], n))
        if medians[worst] <= min_deg:
            break
        rest = [n for n in placed if n != worst]
        spread = [
            a
            for d in people_up_deviations_deg(rec, priors, rest).values()
            for a in d.values()
        ]
        if len(spread) < 2 or medians[worst] <= ratio * float(np.median(spread)):
            break
        left[worst] = (
            f"left out: its pose tilts its people {medians[worst]:.0f} deg from the "
            f"up the other images give them (median over {len(dev[worst])} of its "
            f"people, each seen by two or more other images), more than {min_deg:g} "
            f"deg and {ratio:g} times the other images' median "
            f"({float(np.median(spread)):.1f} deg)"
        )
        _leave_out(rec, image_ids[worst], left[worst])
        placed = rest
    return left


def _leave_out(rec: pycolmap.Reconstruction, image_id: int, reason: str) -> None:
    """Deregister an image of the model, with its reason in the log."""
    logger.warning("%s %s", rec.image(image_id).name, reason)
    rec.deregister_frame(rec.image(image_id).frame_id)


def read_image_priors(
    run_info: Mapping[str, object],
    priors_path: Path | None,
    image_names: tuple[str, ...],
) -> ScenePriors | None:
    """The priors given, else those `augment` recorded in the database (its
    ``run_info``), else None: each image's own people."""
    if priors_path is not None:
        return read_priors(priors_path, known_image_names=image_names)
    recorded = run_info.get("priors")
    if not recorded:
        return None
    try:
        if not Path(str(recorded)).exists():
            return None
        return read_priors(Path(str(recorded)), known_image_names=image_names)
    except OSError as error:
        raise OSError(
            f"the priors augment used, {recorded} (recorded in the database), "
            f"cannot be read ({error.strerror or error}): give --priors"
        ) from error


def with_associated_ids(priors: ScenePriors, records: VcRecords) -> ScenePriors:
    """Anonymous people get the identity `augment`'s association gave them
    (``records``: the database's, :func:`~colmap_vc.vc_records.read_vc_records`).

    Mesh alignment (the auto mapper's check and the mesh-initialised mapper) pairs
    people by identity; with anonymous multi-person priors it could pair nobody.
    People the association left out stay anonymous.
    """
    views = records.views
    id_of = dict(zip(views.image_names, views.image_ids.tolist(), strict=True))
    return _with_identities(priors, records.identity, id_of)


def apply_associations(
    priors: ScenePriors,
    associations: list[database.PersonAssociation],
    id_of: Mapping[str, int],
) -> ScenePriors:
    """:func:`with_associated_ids` from the associations themselves (``id_of``:
    image name -> the database's image id), as `augment` computes them
    (``VirtualCorrespondences.associations``) before it writes them."""
    return _with_identities(priors, person_identities(associations), id_of)


def _with_identities(
    priors: ScenePriors,
    identity: Mapping[tuple[int, int], int],
    id_of: Mapping[str, int],
) -> ScenePriors:
    """``priors`` with each anonymous person that ``identity`` ((image id, person
    index) -> identity) names given an id above the ids the priors use."""
    if not identity:
        return priors
    offset = 1 + max(
        (
            p.person_id
            for ip in priors.images.values()
            for p in ip.persons
            if p.person_id is not None
        ),
        default=-1,
    )
    images = {}
    for name, ip in priors.images.items():
        persons = tuple(
            p
            if p.person_id is not None or (id_of.get(name), k) not in identity
            else dataclasses.replace(p, person_id=offset + identity[(id_of[name], k)])
            for k, p in enumerate(ip.persons)
        )
        images[name] = dataclasses.replace(ip, persons=persons)
    return dataclasses.replace(priors, images=images)
