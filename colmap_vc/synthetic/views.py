"""What each rendered view of a synthetic scene shows, and what a detector and
prior network report in it: the ground truth of every visible person
(:func:`person_views`), the ground-truth surface map file
(:func:`write_surface_map`) and one level's predicted priors with who they really
are (:func:`detect` into :class:`Detections`)."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap
from scipy.spatial import cKDTree

from ..structs import ImagePrior
from . import bodies as body_lib
from .detection import (
    DETECTION_LEVELS,
    false_person_view,
    landmark_visibility,
    miss_reason,
    with_appearance,
)
from .gt import FALSE_DETECTION, FALSE_ID_BASE
from .layout import CameraSpec, PersonPlacement, SceneLayout
from .noise import (
    NOISE_LEVELS,
    NoiseLevel,
    PersonView,
    person_size_error,
    predict_person,
)
from .render import FIRST_PERSON, RenderedView, World


def person_views(
    view: RenderedView,
    layout: SceneLayout,
    posed: list[np.ndarray],
    spec: CameraSpec,
    world: World,
) -> list[PersonView]:
    """Ground truth of every person visible in a rendered view."""
    out = []
    for k, person in enumerate(layout.people):
        mask = view.geom_idx == FIRST_PERSON + k
        if not mask.any():
            continue
        rows, cols = np.nonzero(mask)
        body_from_world = world.people[k].body_from_world
        R_bw, t_bw = body_from_world[:, :3], body_from_world[:, 3]
        world_from_body = np.concatenate([R_bw.T, (-R_bw.T @ t_bw)[:, None]], axis=1)
        C = spec.cam_from_world
        cam_from_body = np.concatenate(
            [
                C[:, :3] @ world_from_body[:, :3],
                (C[:, :3] @ world_from_body[:, 3] + C[:, 3])[:, None],
            ],
            axis=1,
        )
        out.append(
            PersonView(
                person_id=person.person_id,
                phenotype=person.phenotype,
                pose=person.pose,
                body_vertices=posed[k],
                cam_from_body=cam_from_body,
                xy_img=np.stack([cols, rows], axis=1, dtype=np.float64) + 0.5,
                face_idx=view.face_idx[rows, cols],
                bary=view.bary[rows, cols],
                mask=mask,
            )
        )
    return out


def write_surface_map(
    path: Path, views: list[PersonView], bodies: body_lib.BodyModel
) -> int:
    """gt/surface/<image>.npz: every person pixel with its surface point."""
    if not views:
        np.savez_compressed(
            path,
            xy=np.zeros((0, 2), np.float32),
            person_id=np.zeros(0, np.int16),
            face=np.zeros(0, np.int32),
            bary=np.zeros((0, 3), np.float32),
            template_idx=np.zeros(0, np.int32),
        )
        return 0
    template_idx = []
    for v in views:
        rest = bodies.rest_vertices[v.phenotype]
        samples = body_lib.surface_points(
            bodies, rest, bodies.template_face_idx, bodies.template_bary
        )
        points = body_lib.surface_points(bodies, rest, v.face_idx, v.bary)
        template_idx.append(cKDTree(samples).query(points)[1])
    np.savez_compressed(
        path,
        xy=np.concatenate([v.xy_img for v in views]).astype(np.float32),
        person_id=np.concatenate(
            [np.full(len(v.xy_img), v.person_id) for v in views]
        ).astype(np.int16),
        face=np.concatenate([v.face_idx for v in views]).astype(np.int32),
        bary=np.concatenate([v.bary for v in views]).astype(np.float32),
        template_idx=np.concatenate(template_idx).astype(np.int32),
    )
    return sum(len(v.xy_img) for v in views)


@dataclass(kw_only=True, slots=True)
class Detections:
    """Predicted priors of one level and the ground truth of who they are."""

    priors: dict[str, ImagePrior] = field(default_factory=dict)
    true_ids: dict[str, list[int]] = field(default_factory=dict)
    dropped: dict[str, dict[int, str]] = field(default_factory=dict)
    num_false: int = 0
    size_errors: dict[int, float] = field(default_factory=dict)
    """Each true person's size error at this level, shared by its views."""


def size_errors_of(
    level: NoiseLevel, seed: int, people: Sequence[PersonPlacement]
) -> dict[int, float]:
    """The size error of every person of the scene at ``level`` (person id: e)."""
    model = NOISE_LEVELS[level]
    return {p.person_id: person_size_error(model, seed, p.person_id) for p in people}


def detect(
    out: Detections,
    bodies: body_lib.BodyModel,
    views: list[PersonView],
    view: RenderedView,
    layout: SceneLayout,
    image_name: str,
    camera: pycolmap.Camera,
    level: NoiseLevel,
    rng: np.random.Generator,
    with_ids: bool,
) -> None:
    """What a detector + prior network report in one image: some of the people, maybe
    a false one, in random order, each with its noisy prior (anonymous unless
    ``with_ids``)."""
    model = DETECTION_LEVELS[level]
    index_of = {p.person_id: k for k, p in enumerate(layout.people)}
    kept: list[PersonView] = []
    dropped: dict[int, str] = {}
    for v in views:
        vis = landmark_visibility(
            bodies, v, camera, view.geom_idx, FIRST_PERSON + index_of[v.person_id]
        )
        reason = miss_reason(vis, model, rng)
        if reason is None:
            kept.append(v)
        else:
            dropped[v.person_id] = reason
    if rng.random() < model.false_prob:
        fake = false_person_view(bodies, camera, rng, person_id=FALSE_DETECTION)
        if fake is not None:
            kept.append(fake)
    order = rng.permutation(len(kept))
    persons, true_ids = [], []
    for i in order:
        predicted = predict_person(
            bodies,
            kept[i],
            camera,
            level,
            rng,
            size_error=out.size_errors.get(kept[i].person_id, 0.0),
        )
        if predicted is None:  # the estimator's fit failed: no one reported
            if kept[i].person_id != FALSE_DETECTION:
                dropped[kept[i].person_id] = "fit failed"
            continue
        person = with_appearance(predicted, view.image, bodies.joint_names)
        true_id = kept[i].person_id
        if not with_ids:
            pid = None
        elif true_id == FALSE_DETECTION:
            pid = FALSE_ID_BASE + out.num_false
            out.num_false += 1
        else:
            pid = true_id
        persons.append(dataclasses.replace(person, person_id=pid))
        true_ids.append(true_id)
    out.priors[image_name] = ImagePrior(image_name=image_name, persons=tuple(persons))
    out.true_ids[image_name] = true_ids
    out.dropped[image_name] = dropped
