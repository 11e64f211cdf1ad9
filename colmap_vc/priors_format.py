"""The priors format's validation: ``priors.json`` and its arrays -> ScenePriors.

What docs/priors.md specifies, checked field by field: :func:`parse_doc` turns a
parsed ``priors.json`` and a way to open its ``.npz`` files into
:class:`~colmap_vc.structs.ScenePriors`, and raises :class:`PriorsError` naming the
file and the field. :mod:`colmap_vc.priors` reads and writes priors directories
with it (a write runs the same validation on what it is about to write).
"""

from __future__ import annotations

import json
import logging
import re
from collections.abc import Callable, Collection, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from colmap_vc.structs import (
    BoolArray,
    FloatArray,
    ImagePrior,
    IndexArray,
    PersonPrior,
    ScenePriors,
    SurfaceMap,
)

logger = logging.getLogger(__name__)

FORMAT_NAME = "colmap-vc-priors"
FORMAT_VERSION = 1
PRIORS_JSON = "priors.json"
_SURFACE_FIELDS = ("surface_xy", "surface_face", "surface_bary")
PERSON_FIELDS = {"vertices_cam", "faces", "mask", *_SURFACE_FIELDS}
PERSON_FIELDS |= {"keypoints_xy", "keypoints_cam", "keypoints_valid", "appearance"}
# Sanity limits of a human body mesh (docs/priors.md, "Validation").
MIN_DEPTH_M = 0.05  # at least MIN_FRONT_FRACTION of the vertices lie beyond this z
MIN_FRONT_FRACTION = 0.95
MIN_BODY_DIAG_M = 0.05  # bounding-box diagonal
MAX_BODY_DIAG_M = 10.0  # larger: probably millimetres
MAX_MEDIAN_DEPTH_M = 200.0  # larger: probably millimetres
BARY_TOL = 1e-3

_DTYPES = {"f": ("f", "float32 or float64"), "i": ("iu", "int32"), "b": ("b", "bool")}
_JSON_TYPES = {dict: "object", list: "array", str: "string", int: "integer"}
_KEYS = {
    "root": {"format", "version", "templates", "images"},
    "image": {"file", "width", "height", "focal_px", "persons"},
    "person": {"person_id", "confidence", "template"},
}
_PERSON_KEY = re.compile(r"p(\d+)/(.+)")
TEMPLATE_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]*")
_MISSING: Any = object()

NpzOpener = Callable[[Path], Mapping[str, np.ndarray]]
Size = tuple[int, int]  # (width, height) in pixels


class PriorsError(ValueError):
    """Invalid priors. The message is ``"<file>: <field>: <problem>"``."""

    def __init__(self, file: Path | str, field: str, problem: str) -> None:
        super().__init__(f"{file}: {field}: {problem}")
        self.file, self.field, self.problem = str(file), field, problem

    def __reduce__(self) -> tuple[type[PriorsError], tuple[str, str, str]]:
        # Exceptions pickle through their args; keep the 3-argument constructor.
        return (type(self), (self.file, self.field, self.problem))


class _Arrays:
    """The arrays ``source["p<i>/" + name]`` of one person; errors name the file."""

    def __init__(self, file: Path, source: Mapping[str, np.ndarray], prefix: str):
        self.file, self.source, self.prefix = file, source, prefix

    def has(self, name: str) -> bool:
        return self.prefix + name in self.source

    def error(self, name: str, problem: str) -> PriorsError:
        return PriorsError(self.file, self.prefix + name, problem)

    def get(self, name: str, kind: str, shape: tuple[int | str, ...]) -> np.ndarray:
        """Load and check an array: kind "f" -> finite float64, "i" -> int64, "b".

        A str in ``shape`` matches any size.
        """
        if not self.has(name):
            raise self.error(name, "missing array")
        a = np.asarray(self.source[self.prefix + name])
        if kind == "b" and a.dtype.kind in "iu" and np.isin(a, (0, 1)).all():
            a = a.astype(bool)  # tolerate 0/1 integer masks
        if a.dtype.kind not in _DTYPES[kind][0]:
            raise self.error(name, f"dtype {a.dtype}; expected {_DTYPES[kind][1]}")
        if a.ndim != len(shape) or any(
            isinstance(want, int) and have != want
            for have, want in zip(a.shape, shape, strict=True)
        ):
            want = ", ".join(map(str, shape)) + ("," if len(shape) == 1 else "")
            raise self.error(name, f"shape {a.shape}; expected ({want})")
        if kind == "f":
            num_bad = int(np.count_nonzero(~np.isfinite(a)))
            if num_bad:
                raise self.error(name, f"contains {num_bad} NaN or inf value(s)")
            return a.astype(np.float64)
        return a.astype(np.int64) if kind == "i" else a

    def check_range(self, name: str, idx: IndexArray, n: int, of: str) -> None:
        if idx.size and (idx.min() < 0 or idx.max() >= n):
            bad = idx.min() if idx.min() < 0 else idx.max()
            raise self.error(name, f"index {bad} out of range [0, {n}) of {of}")

    def check_inside(
        self, name: str, xy: FloatArray, size: Size | None, valid: BoolArray | None
    ) -> None:
        """Raise if pixels (the valid ones, if given) lie outside [0, W] x [0, H]."""
        if size is None:
            return
        outside = ((xy < 0) | (xy > np.array(size))).any(axis=1)
        if valid is not None:
            outside &= valid
        if outside.any():
            x, y = xy[np.argmax(outside)]
            raise self.error(
                name,
                f"{outside.sum()} of {len(xy)} pixel(s) outside the {size[0]}x"
                f"{size[1]} image, e.g. ({x:.1f}, {y:.1f}); pixels follow COLMAP "
                "(top-left pixel centre = (0.5, 0.5))",
            )


def _check_body(arr: _Arrays, verts: FloatArray) -> None:
    """Units and cheirality checks of a body mesh in its camera frame (metres)."""
    diag = float(np.linalg.norm(verts.max(axis=0) - verts.min(axis=0)))
    z, median_z = verts[:, 2], float(np.median(verts[:, 2]))
    num_near = int(np.count_nonzero(z <= MIN_DEPTH_M))
    if diag > MAX_BODY_DIAG_M or median_z > MAX_MEDIAN_DEPTH_M:
        problem = "looks like millimetres; expected metres (bounding-box diagonal "
        problem += f"{diag:.4g}, median depth {median_z:.4g})"
    elif diag < MIN_BODY_DIAG_M:
        problem = "body is implausibly small (bounding-box diagonal "
        problem += f"{diag:.3g} < {MIN_BODY_DIAG_M} m); expected metres"
    elif z.mean() <= 0:
        problem = f"mesh is behind the camera (centroid z = {z.mean():.3g} m); "
        problem += "expected OpenCV camera axes (x right, y down, z forward)"
    elif num_near > (1 - MIN_FRONT_FRACTION) * len(z):
        problem = f"{num_near} of {len(z)} vertices ({100 * num_near / len(z):.1f}%) "
        problem += f"are behind the camera or closer than {MIN_DEPTH_M} m; at most "
        problem += f"{100 * (1 - MIN_FRONT_FRACTION):.0f}% may be"
    else:
        return
    raise arr.error("vertices_cam", problem)


def _parse_person(
    arr: _Arrays,
    meta: dict[str, Any],
    templates: Mapping[str, IndexArray],
    size: Size | None,
    uses: dict[str, tuple[int, str]],
) -> PersonPrior:
    """Validate the arrays of one person and build its :class:`PersonPrior`."""
    verts = arr.get("vertices_cam", "f", ("V", 3))
    num_verts = len(verts)
    if num_verts < 3:
        raise arr.error("vertices_cam", f"{num_verts} vertices; expected at least 3")
    template = meta["template"]
    if template is None:
        faces = arr.get("faces", "i", ("F", 3))
        arr.check_range("faces", faces, num_verts, "vertices_cam")
    elif arr.has("faces"):
        raise arr.error("faces", f"stored although template {template!r} is set")
    else:
        faces = templates[template]
        # Topology agreement: all meshes of one template have the same vertex count.
        here = f"{arr.file}: {arr.prefix}vertices_cam"
        num_first, first = uses.setdefault(template, (num_verts, here))
        problem = f"{num_verts} vertices, but template {template!r} "
        if num_verts != num_first:
            problem += f"has {num_first} in {first}; one template, one topology"
            raise arr.error("vertices_cam", problem)
        if faces.max() >= num_verts:
            raise arr.error("vertices_cam", problem + f"indexes vertex {faces.max()}")
    _check_body(arr, verts)

    surface = None
    has_surface = [arr.has(name) for name in _SURFACE_FIELDS]
    if any(has_surface):
        if not all(has_surface):
            name = _SURFACE_FIELDS[has_surface.index(False)]
            raise arr.error(name, "missing array (surface_* arrays go together)")
        xy = arr.get("surface_xy", "f", ("N", 2))
        face_idx = arr.get("surface_face", "i", (len(xy),))
        bary = arr.get("surface_bary", "f", (len(xy), 3))
        arr.check_range("surface_face", face_idx, len(faces), "the faces")
        bad = (bary < -BARY_TOL).any(axis=1) | (abs(bary.sum(axis=1) - 1) > BARY_TOL)
        if bad.any():
            row = int(np.argmax(bad))
            raise arr.error(
                "surface_bary",
                f"{bad.sum()} row(s) are not barycentric (non-negative, summing to 1 "
                f"within {BARY_TOL}), e.g. row {row}: {bary[row].round(4).tolist()}",
            )
        arr.check_inside("surface_xy", xy, size, None)
        surface = SurfaceMap(xy_img=xy, face_idx=face_idx, bary=bary)

    # Any subset of the keypoint arrays; the present ones agree on K.
    num_kp: int | str = "K"
    kp_xy = kp_cam = kp_valid = None
    if arr.has("keypoints_xy"):
        kp_xy = arr.get("keypoints_xy", "f", (num_kp, 2))
        num_kp = len(kp_xy)
    if arr.has("keypoints_cam"):
        kp_cam = arr.get("keypoints_cam", "f", (num_kp, 3))
        num_kp = len(kp_cam)
    if arr.has("keypoints_valid"):
        kp_valid = arr.get("keypoints_valid", "b", (num_kp,))
    if kp_xy is not None:  # joints off the frame are fine when marked invalid
        arr.check_inside("keypoints_xy", kp_xy, size, kp_valid)
    mask_shape = ("H", "W") if size is None else (size[1], size[0])
    mask = arr.get("mask", "b", mask_shape) if arr.has("mask") else None
    appearance = None
    if arr.has("appearance"):
        appearance = arr.get("appearance", "f", ("R", 4))
        if (appearance[:, 3] < 0).any():
            raise arr.error("appearance", "negative region weight (column 3)")
    return PersonPrior(
        vertices_cam=verts,
        faces=faces,
        surface_map=surface,
        keypoints_xy=kp_xy,
        keypoints_cam=kp_cam,
        keypoints_valid=kp_valid,
        mask=mask,
        appearance=appearance,
        **meta,
    )


class _Json:
    """Typed access to the JSON objects of one ``priors.json``; errors name it."""

    def __init__(self, path: Path) -> None:
        self.path, self.unknown = path, set[str]()

    def obj(self, value: Any, where: str, kind: str) -> dict[str, Any]:
        if not isinstance(value, dict):
            problem = f"expected an object, got {value!r:.60}"
            raise PriorsError(self.path, where, problem)
        self.unknown.update(f"{kind}.{key}" for key in value.keys() - _KEYS[kind])
        return value

    def get(
        self,
        obj: dict[str, Any],
        key: str,
        kind: Any,
        where: str,
        default: Any = _MISSING,
    ) -> Any:
        """``obj[key]`` of JSON type ``kind``, or ``default`` when absent or null."""
        name, value = f"{where}.{key}" if where else key, obj.get(key)
        if value is None:
            if default is _MISSING:
                raise PriorsError(self.path, name, "missing")
            return default
        kinds = kind if isinstance(kind, tuple) else (kind,)
        if not isinstance(value, kinds) or (
            isinstance(value, bool) and bool not in kinds
        ):
            want = " or ".join(_JSON_TYPES.get(k, "number") for k in kinds)
            raise PriorsError(self.path, name, f"expected {want}, got {value!r:.60}")
        return value

    def open(self, open_npz: NpzOpener, rel: str, where: str) -> tuple[Path, Any]:
        path = self.path.parent / rel
        try:
            return path, open_npz(path)
        except FileNotFoundError:
            raise PriorsError(self.path, where, f"{path} does not exist") from None


def _parse_templates(
    js: _Json, doc: dict[str, Any], open_npz: NpzOpener
) -> dict[str, IndexArray]:
    templates: dict[str, IndexArray] = {}
    for name, rel in js.get(doc, "templates", dict, "", {}).items():
        where = f"templates[{json.dumps(name)}]"
        if not isinstance(rel, str):
            raise PriorsError(js.path, where, f"expected a .npz path, got {rel!r:.60}")
        path, source = js.open(open_npz, rel, where)
        arr = _Arrays(path, source, "")
        faces = arr.get("faces", "i", ("F", 3))
        if len(faces) == 0 or faces.min() < 0:
            raise arr.error("faces", "empty or with negative vertex indices")
        faces.flags.writeable = False  # shared by every person of the template
        templates[name] = faces
    return templates


def _parse_image(
    js: _Json,
    name: str,
    entry: Any,
    open_npz: NpzOpener,
    templates: Mapping[str, IndexArray],
    db_size: Size | None,
    uses: dict[str, tuple[int, str]],
) -> ImagePrior:
    where = f"images[{json.dumps(name)}]"
    entry = js.obj(entry, where, "image")
    width = js.get(entry, "width", int, where, None)
    height = js.get(entry, "height", int, where, None)
    size = None if width is None or height is None else (width, height)
    if (width, height) != (None, None) and (size is None or min(size) < 1):
        raise PriorsError(js.path, f"{where}.width", "set width and height, both > 0")
    if db_size is not None:
        if size is not None and size != db_size:
            problem = f"{width}x{height}, but the database image is %dx%d" % db_size
            raise PriorsError(js.path, f"{where}.width", problem)
        size = db_size
    focal = js.get(entry, "focal_px", (int, float), where, None)
    if focal is not None and not focal > 0:
        raise PriorsError(js.path, f"{where}.focal_px", f"{focal}, must be > 0")
    persons_doc = js.get(entry, "persons", list, where)
    rel = js.get(entry, "file", str, where)
    npz_path, source = js.open(open_npz, rel, f"{where}.file")
    for key in source:  # flag likely typos: arrays no person will read
        match = _PERSON_KEY.fullmatch(key)
        if match and (
            int(match[1]) >= len(persons_doc) or match[2] not in PERSON_FIELDS
        ):
            js.unknown.add(f"array {rel}:{key}")

    persons, seen_ids = [], set[int]()
    for i, person_doc in enumerate(persons_doc):
        at = f"{where}.persons[{i}]"
        person_doc = js.obj(person_doc, at, "person")
        meta = {
            "person_id": js.get(person_doc, "person_id", int, at, None),
            "confidence": float(js.get(person_doc, "confidence", (int, float), at, 1)),
            "template": js.get(person_doc, "template", str, at, None),
        }
        if meta["person_id"] in seen_ids:
            problem = f"{meta['person_id']} appears twice in one image"
            raise PriorsError(js.path, f"{at}.person_id", problem)
        if not 0.0 <= meta["confidence"] <= 1.0:
            problem = f"{meta['confidence']} not in [0, 1]"
            raise PriorsError(js.path, f"{at}.confidence", problem)
        if meta["template"] not in (None, *templates):
            problem = f"unknown template {meta['template']!r}; have {sorted(templates)}"
            raise PriorsError(js.path, f"{at}.template", problem)
        if meta["person_id"] is not None:
            seen_ids.add(meta["person_id"])
        arr = _Arrays(npz_path, source, f"p{i}/")
        persons.append(_parse_person(arr, meta, templates, size, uses))
    return ImagePrior(
        image_name=name,
        persons=tuple(persons),
        focal_px=None if focal is None else float(focal),
    )


def parse_doc(
    doc: Any,
    json_path: Path,
    open_npz: NpzOpener,
    known_image_names: Collection[str] | None,
    image_sizes: Mapping[str, Size] | None,
) -> ScenePriors:
    """Validate a parsed ``priors.json`` and the arrays it refers to."""
    js = _Json(json_path)
    doc = js.obj(doc, "(root)", "root")
    if doc.get("format") != FORMAT_NAME:
        got = "missing" if doc.get("format") is None else repr(doc["format"])
        raise PriorsError(json_path, "format", f"{got}; expected {FORMAT_NAME!r}")
    version = js.get(doc, "version", int, "")
    if version != FORMAT_VERSION:
        problem = (
            f"unsupported version {version}; this colmap-vc reads {FORMAT_VERSION}"
        )
        raise PriorsError(json_path, "version", problem)
    images_doc = js.get(doc, "images", dict, "")
    if known_image_names is not None:
        known = set(known_image_names)
        strangers = [name for name in images_doc if name not in known]
        if strangers:
            listed = ", ".join(map(repr, strangers[:5]))
            more = ", ..." if len(strangers) > 5 else ""
            problem = f"{len(strangers)} image(s) not in the database: {listed}{more}"
            if len(strangers) == len(images_doc):  # another folder, or renamed
                raise PriorsError(json_path, "images", problem)
            # Priors of a whole folder, a database of some of its images.
            logger.warning("%s: images: ignoring %s", json_path, problem)
            images_doc = {k: v for k, v in images_doc.items() if k in known}
    templates = _parse_templates(js, doc, open_npz)
    sizes = {k: (int(w), int(h)) for k, (w, h) in (image_sizes or {}).items()}
    uses: dict[str, tuple[int, str]] = {}
    images = {
        name: _parse_image(js, name, entry, open_npz, templates, sizes.get(name), uses)
        for name, entry in images_doc.items()
    }
    if js.unknown:
        unknown = sorted(js.unknown)
        more = f" and {len(unknown) - 6} more" if len(unknown) > 6 else ""
        logger.warning(
            "%s: ignoring %d unknown entries: %s%s",
            json_path,
            len(unknown),
            ", ".join(unknown[:6]),
            more,
        )
    return ScenePriors(images=images, version=version)
