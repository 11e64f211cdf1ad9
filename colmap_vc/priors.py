"""Human-prior I/O: the versioned priors format (docs/priors.md) <-> ScenePriors.

A priors directory holds ``priors.json`` (human-readable metadata) and compressed
``.npz`` arrays: one file per image, with arrays ``p<i>/<field>`` for its i-th person,
and one file per shared mesh template with its ``faces``. :func:`read_priors`
validates everything (:mod:`colmap_vc.priors_format`) and raises
:class:`PriorsError` naming the file and the field; :func:`write_priors` runs the
same validation before it writes anything.
"""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Collection, Mapping
from pathlib import Path, PurePosixPath
from typing import Any

import numpy as np

from colmap_vc.priors_format import (
    FORMAT_NAME,
    FORMAT_VERSION,
    PRIORS_JSON,
    TEMPLATE_NAME,
    PriorsError,
    Size,
    parse_doc,
)
from colmap_vc.structs import IndexArray, PersonPrior, ScenePriors

__all__ = [
    "PriorsError",
    "focal_mismatches",
    "read_priors",
    "write_priors",
]

logger = logging.getLogger(__name__)


def _load_npz(path: Path) -> dict[str, np.ndarray]:
    """All arrays of an .npz file (the file is closed again at once)."""
    if not path.is_file():
        raise FileNotFoundError(path)
    key = "(file)"
    try:
        npz = np.load(path, allow_pickle=False)
        if not isinstance(npz, np.lib.npyio.NpzFile):
            raise ValueError("a single .npy array, not an .npz archive")
        with npz:
            arrays = {}
            for key in npz.files:  # on error, ``key`` names the failing array
                arrays[key] = npz[key]
        return arrays
    except Exception as exc:  # corrupt files raise many kinds (zip, zlib, parsing)
        raise PriorsError(path, key, f"unreadable .npz: {exc}") from exc


def focal_mismatches(
    priors: ScenePriors, focal_px: Mapping[str, float], max_ratio: float = 1.05
) -> dict[str, tuple[float, float]]:
    """Images whose priors were made with a focal length more than ``max_ratio``
    from their database camera's ``focal_px`` -> (the priors', the database's).

    The meshes' depth follows the focal length they were fitted with, and the
    virtual correspondences cast through them follow it too: priors made with
    COLMAP's guess (1.2 times the larger side) and mapped with a calibration put
    the people 10-50 % off in depth. Default 5 %: the metric scale's own target."""
    out = {}
    for name, image in priors.images.items():  # loop over images
        if image.focal_px is None or name not in focal_px:
            continue
        ratio = image.focal_px / focal_px[name]
        if max(ratio, 1.0 / ratio) > max_ratio:
            out[name] = (image.focal_px, float(focal_px[name]))
    return out


def read_priors(
    path: Path,
    *,
    known_image_names: Collection[str] | None = None,
    image_sizes: Mapping[str, Size] | None = None,
) -> ScenePriors:
    """Read and validate priors (format in docs/priors.md).

    Args:
        path: The priors directory, or its ``priors.json``.
        known_image_names: The database's image names; priors of other names are
            ignored with a warning (priors of a folder, a database of some of its
            images), an error when no name is known (another folder, renamed
            images). Database images without priors are fine (the caller skips
            them).
        image_sizes: ``(width, height)`` per image name, e.g. from the database
            cameras; enables the mask-shape and pixels-inside-the-image checks.

    Returns:
        The priors, with float64 / int64 / bool arrays.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        PriorsError: Anything invalid; the message names the file and the field.
    """
    path = Path(path)
    json_path = path / PRIORS_JSON if path.is_dir() else path
    if not json_path.is_file():
        raise FileNotFoundError(f"no priors at {path} (expected {PRIORS_JSON})")
    try:
        doc = json.loads(json_path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise PriorsError(json_path, "(root)", f"malformed JSON: {exc}") from exc

    priors = parse_doc(doc, json_path, _load_npz, known_image_names, image_sizes)
    num_persons = sum(len(image.persons) for image in priors.images.values())
    logger.info("read %d persons in %d images", num_persons, len(priors.images))
    return priors


def _person_arrays(person: PersonPrior) -> dict[str, np.ndarray]:
    """The on-disk arrays of one person: float32, int32 and bool."""
    surface = person.surface_map
    arrays = {
        "vertices_cam": person.vertices_cam,
        "faces": person.faces if person.template is None else None,
        "surface_xy": None if surface is None else surface.xy_img,
        "surface_face": None if surface is None else surface.face_idx,
        "surface_bary": None if surface is None else surface.bary,
        "keypoints_xy": person.keypoints_xy,
        "keypoints_cam": person.keypoints_cam,
        "keypoints_valid": person.keypoints_valid,
        "mask": person.mask,  # bool in a compressed npz costs ~nothing off the edges
        "appearance": person.appearance,
    }
    dtypes = {"f": np.float32, "i": np.int32, "u": np.int32, "b": np.bool_}
    return {
        name: a.astype(dtypes[a.dtype.kind])
        for name, a in arrays.items()
        if a is not None
    }


def _save_npz(path: Path, arrays: Mapping[str, Any]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    with tmp.open("wb") as f:  # a file object: numpy appends no ".npz"
        np.savez_compressed(f, **arrays)
    os.replace(tmp, path)


def write_priors(
    priors: ScenePriors,
    out_dir: Path,
    *,
    templates: Mapping[str, IndexArray] | None = None,
    image_sizes: Mapping[str, Size] | None = None,
) -> Path:
    """Validate and write priors as a priors directory (format in docs/priors.md).

    Args:
        priors: The priors; image names must be relative paths without "..".
        out_dir: The priors directory, created if needed.
        templates: Faces ``(F, 3)`` per template name. Persons whose ``template`` is
            set must have exactly these faces; a template missing here is taken from
            its first person.
        image_sizes: ``(width, height)`` per image name, stored in ``priors.json``.

    Returns:
        The path of ``priors.json``, written last (to a temporary file, then renamed).

    Raises:
        ValueError: Inconsistent templates, or unsafe image or template names.
        PriorsError: Invalid priors, as :func:`read_priors` would report them.
    """
    if priors.version != FORMAT_VERSION:
        raise ValueError(
            f"can only write version {FORMAT_VERSION}, not {priors.version}"
        )
    out_dir = Path(out_dir)
    faces_of = {k: np.asarray(v, dtype=np.int64) for k, v in (templates or {}).items()}
    staged: dict[Path, dict[str, np.ndarray]] = {}
    doc_images: dict[str, Any] = {}
    for name, image in priors.images.items():
        parts = PurePosixPath(name).parts
        if image.image_name != name or not parts or parts[0] == "/" or ".." in parts:
            raise ValueError(f"bad image name {name!r} (key of {image.image_name!r})")
        entry: dict[str, Any] = {"file": f"images/{name}.npz"}
        if image_sizes is not None and name in image_sizes:
            entry["width"], entry["height"] = map(int, image_sizes[name])
        if image.focal_px is not None:
            entry["focal_px"] = float(image.focal_px)
        entry["persons"] = [
            {
                "person_id": None if p.person_id is None else int(p.person_id),
                "confidence": float(p.confidence),
                "template": p.template,
            }
            for p in image.persons
        ]
        arrays = staged[out_dir / entry["file"]] = {}
        for i, person in enumerate(image.persons):
            if person.template is not None:
                ref = faces_of.setdefault(person.template, person.faces)
                if not np.array_equal(ref, person.faces):
                    raise ValueError(
                        f"image {name!r}, person {i}: faces differ from those of "
                        f"template {person.template!r}"
                    )
            arrays.update({f"p{i}/{k}": a for k, a in _person_arrays(person).items()})
        doc_images[name] = entry
    doc_templates = {}
    for name, faces in faces_of.items():
        if not TEMPLATE_NAME.fullmatch(name):
            raise ValueError(f"bad template name {name!r}: use letters, digits, _.-")
        doc_templates[name] = f"templates/{name}.npz"
        staged[out_dir / doc_templates[name]] = {"faces": faces.astype(np.int32)}
    doc = {
        "format": FORMAT_NAME,
        "version": FORMAT_VERSION,
        "templates": doc_templates,
        "images": doc_images,
    }
    json_path = out_dir / PRIORS_JSON
    parse_doc(doc, json_path, staged.__getitem__, None, image_sizes)  # validate
    # Arrays of an earlier priors.json here that this one does not list (stale).
    stale = (
        {
            p
            for sub in ("images", "templates")
            for p in (out_dir / sub).rglob("*.npz")
            if p not in staged
        }
        if json_path.is_file()
        else set()
    )
    for path, arrays in staged.items():
        _save_npz(path, arrays)
    tmp = json_path.with_name(PRIORS_JSON + ".tmp")
    tmp.write_text(json.dumps(doc, indent=1, ensure_ascii=False) + "\n", "utf-8")
    os.replace(tmp, json_path)  # last: a complete priors.json means complete arrays
    for path in sorted(stale):
        path.unlink()
    if stale:
        logger.info("removed %d array file(s) of the earlier priors", len(stale))
    logger.info("wrote priors of %d images to %s", len(doc_images), out_dir)
    return json_path
