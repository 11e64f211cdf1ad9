"""Ground truth of identity of the synthetic priors, and scores against it.

The predicted priors are anonymous (no ``person_id``) unless asked for; who each prior
person really is goes into a separate file next to the ground-truth model,
``gt/persons.json`` for ``priors/`` (``gt/persons_<level>.json`` for
``priors_<level>/``)::

    {
      "version": 1,
      "priors": "priors",                    # the priors folder this file describes
      "false_detection": -1,                 # the id of a person that is not there
      "people": {"0": "person", "1": "person", "3": "bystander"},
      "images": {"cam00.jpg": [2, 0, -1], ...},   # true id of each prior person,
                                                  # in the order of the priors' persons
      "visible": {"cam00.jpg": [0, 1, 2], ...},   # people with any pixel in the image
      "dropped": {"cam00.jpg": {"1": "missed (p = 0.31: ...)"}, ...}
    }

Every image of the scene appears in ``images``, ``visible`` and ``dropped`` (possibly
with an empty list or object).
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ..priors import read_priors, write_priors
from ..structs import ImagePrior, ScenePriors

FALSE_DETECTION = -1
"""True id of a prior person that is not there (a false detection)."""
FALSE_ID_BASE = 1000
"""With ids given, false detection k of a scene gets id FALSE_ID_BASE + k (unique, so
it never links to anything)."""


@dataclass(frozen=True, kw_only=True, slots=True)
class GtPersons:
    """Contents of a gt persons file (format in the module docstring)."""

    priors: str
    people: dict[int, str]  # true id -> "person" or "bystander"
    images: dict[str, list[int]]  # image -> true id per prior person, in order
    visible: dict[str, list[int]]  # image -> ids of the people with pixels there
    dropped: dict[str, dict[int, str]]  # image -> {id: why the detector missed it}

    def to_json(self) -> dict:
        return {
            "version": 1,
            "priors": self.priors,
            "false_detection": FALSE_DETECTION,
            "people": {str(k): v for k, v in sorted(self.people.items())},
            "images": {k: list(v) for k, v in sorted(self.images.items())},
            "visible": {k: list(v) for k, v in sorted(self.visible.items())},
            "dropped": {
                k: {str(i): r for i, r in sorted(v.items())}
                for k, v in sorted(self.dropped.items())
            },
        }


def gt_persons_path(scene_dir: Path, priors_dir: str = "priors") -> Path:
    """``gt/persons.json`` for ``priors``, ``gt/persons_<level>.json`` for
    ``priors_<level>``."""
    suffix = priors_dir.removeprefix("priors")
    return Path(scene_dir) / "gt" / f"persons{suffix}.json"


def write_gt_persons(path: Path, gt: GtPersons) -> None:
    Path(path).write_text(json.dumps(gt.to_json(), indent=1) + "\n")


def read_gt_persons(path: Path) -> GtPersons:
    """Read a gt persons file; errors name the file and field."""
    path = Path(path)
    doc = json.loads(path.read_text())
    for key in ("priors", "people", "images", "visible", "dropped"):
        if key not in doc:
            raise ValueError(f"{path}: missing field {key!r}")
    if doc.get("version") != 1:
        raise ValueError(f"{path}: version {doc.get('version')!r}, expected 1")
    return GtPersons(
        priors=doc["priors"],
        people={int(k): v for k, v in doc["people"].items()},
        images={k: [int(i) for i in v] for k, v in doc["images"].items()},
        visible={k: [int(i) for i in v] for k, v in doc["visible"].items()},
        dropped={
            k: {int(i): r for i, r in v.items()} for k, v in doc["dropped"].items()
        },
    )


def true_ids_priors(priors: ScenePriors, gt: GtPersons) -> ScenePriors:
    """The same priors with each person's true id (false detections: unique ids from
    FALSE_ID_BASE), the "ids given" upper bound of the association."""
    images: dict[str, ImagePrior] = {}
    num_false = 0
    for name in sorted(priors.images):
        prior = priors.images[name]
        ids = gt.images.get(name, [])
        if len(ids) != len(prior.persons):
            raise ValueError(
                f"gt persons of {gt.priors!r}: image {name} lists {len(ids)} people, "
                f"the priors have {len(prior.persons)}"
            )
        persons = []
        for person, true_id in zip(prior.persons, ids, strict=True):
            if true_id == FALSE_DETECTION:
                true_id = FALSE_ID_BASE + num_false
                num_false += 1
            persons.append(replace(person, person_id=true_id))
        images[name] = replace(prior, persons=tuple(persons))
    return replace(priors, images=images)


def add_true_ids(
    scene_dir: Path, priors_dir: str = "priors", out_dir: str = "priors_ids"
) -> Path:
    """Write ``scene_dir/priors_dir`` with true ids into ``scene_dir/out_dir``."""
    scene_dir = Path(scene_dir)
    gt = read_gt_persons(gt_persons_path(scene_dir, priors_dir))
    priors = true_ids_priors(read_priors(scene_dir / priors_dir), gt)
    templates = {
        p.template: p.faces
        for image in priors.images.values()
        for p in image.persons
        if p.template is not None
    }
    write_priors(priors, scene_dir / out_dir, templates=templates)
    return scene_dir / out_dir


@dataclass(frozen=True, kw_only=True, slots=True)
class AssociationScore:
    """Links between prior persons of different images: truth against prediction.

    A true link joins two prior persons of different images that are the same real
    person (false detections link to nothing); a predicted link joins two with the
    same predicted id.
    """

    true_links: int
    predicted_links: int
    correct_links: int

    @property
    def precision(self) -> float:
        if not self.predicted_links:
            return 1.0
        return self.correct_links / self.predicted_links

    @property
    def recall(self) -> float:
        """The association accuracy: fraction of the true links that were made."""
        return self.correct_links / self.true_links if self.true_links else 1.0


def association_score(
    gt: GtPersons, predicted: Mapping[str, Sequence[int | None]]
) -> AssociationScore:
    """Score predicted ids (per image, in the priors' order; None or a negative id:
    unassociated)."""
    image, true, pred = [], [], []
    for k, (name, ids) in enumerate(sorted(gt.images.items())):
        got = list(predicted.get(name, [None] * len(ids)))
        if len(got) != len(ids):
            raise ValueError(
                f"image {name}: {len(got)} predicted ids for {len(ids)} prior persons"
            )
        image += [k] * len(ids)
        true += ids
        pred += [-1 if p is None else int(p) for p in got]
    img, t, p = np.array(image), np.array(true), np.array(pred)
    across = img[:, None] != img[None, :]
    upper = np.triu(np.ones_like(across), k=1) & across
    true_link = upper & (t[:, None] == t[None, :]) & (t[:, None] != FALSE_DETECTION)
    pred_link = upper & (p[:, None] == p[None, :]) & (p[:, None] >= 0)
    return AssociationScore(
        true_links=int(true_link.sum()),
        predicted_links=int(pred_link.sum()),
        correct_links=int((true_link & pred_link).sum()),
    )
