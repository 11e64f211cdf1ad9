"""Tests of the priors format: round trip, and one PriorsError per validation rule."""

from __future__ import annotations

import dataclasses
import json
import logging
import pickle
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import trimesh

from colmap_vc.priors import PriorsError, focal_mismatches, read_priors, write_priors
from colmap_vc.structs import ImagePrior, PersonPrior, ScenePriors, SurfaceMap

WIDTH, HEIGHT = 640, 480
SIZES = {name: (WIDTH, HEIGHT) for name in ("cam0.jpg", "cams/a.jpg", "empty.jpg")}
K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])


def project(points_cam: np.ndarray) -> np.ndarray:
    """Pinhole projection (COLMAP pixel convention: principal point in pixels)."""
    uvw = points_cam @ K.T
    return uvw[:, :2] / uvw[:, 2:]


def sphere_person(rng: np.random.Generator, centre: list[float]) -> PersonPrior:
    """An icosphere 'body' (42 vertices, 80 faces) with every optional field."""
    mesh = trimesh.creation.icosphere(subdivisions=1, radius=0.4)
    verts = np.asarray(mesh.vertices) + centre
    faces = np.asarray(mesh.faces, dtype=np.int64)
    face_idx = rng.integers(0, len(faces), 50)
    bary = rng.dirichlet(np.ones(3), 50)
    points = np.einsum("nk,nkd->nd", bary, verts[faces[face_idx]])
    mask = np.zeros((HEIGHT, WIDTH), dtype=bool)
    mask[150:330, 230:410] = True
    return PersonPrior(
        vertices_cam=verts,
        faces=faces,
        template="sphere",
        person_id=0,
        confidence=0.9,
        surface_map=SurfaceMap(xy_img=project(points), face_idx=face_idx, bary=bary),
        keypoints_xy=project(verts[:6]),
        keypoints_cam=verts[:6],
        keypoints_valid=np.array([True, True, False, True, True, True]),
        mask=mask,
    )


def box_person() -> PersonPrior:
    """A box with its own faces and no optional field."""
    mesh = trimesh.creation.box(extents=(0.5, 1.7, 0.3))
    return PersonPrior(
        vertices_cam=np.asarray(mesh.vertices) + np.array([1.0, 0.0, 4.0]),
        faces=np.asarray(mesh.faces, dtype=np.int64),
        confidence=0.5,
    )


@pytest.fixture
def priors() -> ScenePriors:
    rng = np.random.default_rng(0)
    person_a = dataclasses.replace(
        sphere_person(rng, [0.1, 0.2, 3.0]), mask=None, person_id=np.int64(7)
    )
    images = [
        ImagePrior(
            image_name="cam0.jpg",
            persons=(sphere_person(rng, [0.0, 0.0, 3.0]), box_person()),
        ),
        ImagePrior(image_name="cams/a.jpg", persons=(person_a,)),
        ImagePrior(image_name="empty.jpg", persons=()),
    ]
    return ScenePriors(images={image.image_name: image for image in images})


@pytest.fixture
def priors_dir(tmp_path: Path, priors: ScenePriors) -> Path:
    write_priors(priors, tmp_path / "priors", image_sizes=SIZES)
    return tmp_path / "priors"


def as_written(a: np.ndarray) -> np.ndarray:
    return a.astype(np.float32).astype(np.float64)


def assert_same_person(got: PersonPrior, want: PersonPrior) -> None:
    assert (got.template, got.person_id, got.confidence) == (
        want.template,
        want.person_id,
        want.confidence,
    )
    assert got.vertices_cam.dtype == np.float64
    assert got.faces.dtype == np.int64
    np.testing.assert_array_equal(got.vertices_cam, as_written(want.vertices_cam))
    np.testing.assert_array_equal(got.faces, want.faces)
    for name in ("keypoints_xy", "keypoints_cam"):
        if getattr(want, name) is None:
            assert getattr(got, name) is None
        else:
            np.testing.assert_array_equal(
                getattr(got, name), as_written(getattr(want, name))
            )
    for name in ("keypoints_valid", "mask"):
        np.testing.assert_array_equal(getattr(got, name), getattr(want, name))
    if want.surface_map is None:
        assert got.surface_map is None
    else:
        assert got.surface_map is not None
        np.testing.assert_array_equal(
            got.surface_map.xy_img, as_written(want.surface_map.xy_img)
        )
        np.testing.assert_array_equal(
            got.surface_map.face_idx, want.surface_map.face_idx
        )
        np.testing.assert_array_equal(
            got.surface_map.bary, as_written(want.surface_map.bary)
        )


def test_round_trip(priors: ScenePriors, priors_dir: Path) -> None:
    loaded = read_priors(priors_dir, known_image_names=SIZES, image_sizes=SIZES)
    assert list(loaded.images) == list(priors.images)
    assert loaded.version == 1
    for name, image in priors.images.items():
        assert loaded.images[name].image_name == name
        assert len(loaded.images[name].persons) == len(image.persons)
        for got, want in zip(loaded.images[name].persons, image.persons, strict=True):
            assert_same_person(got, want)


def test_the_focal_length_the_priors_were_made_with(
    priors: ScenePriors, tmp_path: Path, caplog
) -> None:
    # Recorded when known, and compared with the database's cameras: the
    # meshes' depth follows the focal length they were fitted with.
    name = next(iter(priors.images))
    made = dataclasses.replace(priors.images[name], focal_px=1500.0)
    write_priors(ScenePriors(images={name: made}), tmp_path / "p")
    with caplog.at_level(logging.WARNING):
        loaded = read_priors(tmp_path / "p")
    assert "unknown" not in caplog.text  # a key of the format, not a typo
    assert loaded.images[name].focal_px == 1500.0
    assert focal_mismatches(loaded, {name: 1480.0}) == {}
    assert focal_mismatches(loaded, {name: 1250.0}) == {name: (1500.0, 1250.0)}
    assert focal_mismatches(priors, {name: 1250.0}) == {}  # not recorded


def test_read_json_path_and_subfolder(priors_dir: Path) -> None:
    assert (priors_dir / "images" / "cams" / "a.jpg.npz").is_file()
    assert (priors_dir / "templates" / "sphere.npz").is_file()
    doc = json.loads((priors_dir / "priors.json").read_text())
    assert doc["format"] == "colmap-vc-priors"
    assert doc["images"]["cams/a.jpg"]["file"] == "images/cams/a.jpg.npz"
    loaded = read_priors(priors_dir / "priors.json")
    assert loaded.images["cams/a.jpg"].persons[0].template == "sphere"


def test_database_images_without_priors_are_fine(priors_dir: Path) -> None:
    known = [*SIZES, "cams/b.jpg", "other.png"]
    loaded = read_priors(priors_dir, known_image_names=known)
    assert set(loaded.images) == set(SIZES)


def test_priors_of_images_the_database_lacks_are_ignored_and_listed(
    priors_dir: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Priors of a whole folder, a database of some of its images: the others are
    skipped, and the warning names them."""
    with caplog.at_level(logging.WARNING, logger="colmap_vc.priors_format"):
        loaded = read_priors(priors_dir, known_image_names=["cam0.jpg"])
    assert set(loaded.images) == {"cam0.jpg"}
    message = caplog.text
    assert "priors.json: images: ignoring 2 image(s) not in the database" in message
    assert "'cams/a.jpg'" in message
    assert "'empty.jpg'" in message


def test_priors_of_no_database_image_are_an_error(priors_dir: Path) -> None:
    """Not one name in common (another folder, renamed images): refused."""
    with pytest.raises(PriorsError) as info:
        read_priors(priors_dir, known_image_names=["other.jpg"])
    message = str(info.value)
    assert "priors.json: images: 3 image(s) not in the database" in message
    assert "'cam0.jpg'" in message


def test_at_most_five_unknown_images_are_listed(
    tmp_path: Path, priors: ScenePriors
) -> None:
    image = priors.images["cam0.jpg"]
    names = [f"x{i}.jpg" for i in range(7)]
    many = ScenePriors(
        images={n: dataclasses.replace(image, image_name=n) for n in names}
    )
    write_priors(many, tmp_path)
    with pytest.raises(PriorsError, match=r"7 image\(s\).*'x4.jpg', \.\.\.$"):
        read_priors(tmp_path, known_image_names=[])


def test_write_checks_template_faces(tmp_path: Path, priors: ScenePriors) -> None:
    faces = priors.images["cam0.jpg"].persons[0].faces
    write_priors(priors, tmp_path / "ok", templates={"sphere": faces})
    with pytest.raises(ValueError, match=r"faces differ.*'sphere'"):
        write_priors(priors, tmp_path / "bad", templates={"sphere": faces[::-1]})


def test_write_validates_before_writing(tmp_path: Path, priors: ScenePriors) -> None:
    person = priors.images["cam0.jpg"].persons[1]
    bad_verts = person.vertices_cam.copy()
    bad_verts[0, 0] = np.nan
    image = ImagePrior(
        image_name="cam0.jpg",
        persons=(dataclasses.replace(person, vertices_cam=bad_verts),),
    )
    with pytest.raises(PriorsError, match=r"cam0.jpg.npz: p0/vertices_cam: .*NaN"):
        write_priors(ScenePriors(images={"cam0.jpg": image}), tmp_path)
    assert not (tmp_path / "priors.json").exists()


@pytest.mark.parametrize("name", ["../up.jpg", "/abs.jpg", ""])
def test_write_rejects_unsafe_names(tmp_path: Path, name: str) -> None:
    with pytest.raises(ValueError, match="bad image name"):
        write_priors(
            ScenePriors(images={name: ImagePrior(image_name=name, persons=())}),
            tmp_path,
        )


def test_missing_priors_dir(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError):
        read_priors(tmp_path / "nowhere")


def test_unknown_arrays_and_keys_warn(
    priors_dir: Path, caplog: pytest.LogCaptureFixture
) -> None:
    edit_npz(priors_dir / "images/cam0.jpg.npz", lambda d: d.update(p0_maks=[]))
    edit_npz(priors_dir / "images/cam0.jpg.npz", lambda d: d.update({"p0/maks": []}))
    edit_json(priors_dir, lambda doc: doc["images"]["cam0.jpg"].update(note="hi"))
    with caplog.at_level(logging.WARNING, logger="colmap_vc.priors_format"):
        read_priors(priors_dir)
    assert "p0/maks" in caplog.text
    assert "image.note" in caplog.text
    assert "p0_maks" not in caplog.text


def test_invalid_keypoints_may_leave_the_image(priors_dir: Path) -> None:
    def move_invalid(d: dict[str, np.ndarray]) -> None:
        d["p0/keypoints_xy"][2] = [-50.0, 900.0]  # keypoints_valid[2] is False

    edit_npz(priors_dir / "images/cam0.jpg.npz", move_invalid)
    read_priors(priors_dir, image_sizes=SIZES)


def test_error_pickles() -> None:
    error = pickle.loads(pickle.dumps(PriorsError("a.npz", "p0/faces", "bad")))
    assert (str(error), error.field) == ("a.npz: p0/faces: bad", "p0/faces")


def edit_npz(path: Path, edit: Callable[[dict[str, np.ndarray]], Any]) -> None:
    with np.load(path) as npz:
        arrays = {key: npz[key] for key in npz}
    edit(arrays)
    with path.open("wb") as f:
        np.savez_compressed(f, **arrays)


def edit_json(priors_dir: Path, edit: Callable[[dict[str, Any]], Any]) -> None:
    path = priors_dir / "priors.json"
    doc = json.loads(path.read_text())
    edit(doc)
    path.write_text(json.dumps(doc))


def setitem(key: str, index: Any, value: Any) -> Callable[[dict], None]:
    def edit(d: dict[str, np.ndarray]) -> None:
        d[key][index] = value

    return edit


def replace(key: str, fn: Callable[[np.ndarray], Any]) -> Callable[[dict], None]:
    def edit(d: dict[str, np.ndarray]) -> None:
        d[key] = fn(d[key])

    return edit


def delete(key: str) -> Callable[[dict], None]:
    return lambda d: d.pop(key)


def shrink(v: np.ndarray) -> np.ndarray:
    centre = v.mean(axis=0)
    return centre + 0.01 * (v - centre)


def half_behind(v: np.ndarray) -> np.ndarray:
    v = v.copy()
    v[:5, 2] = -0.1  # 5 of 42 vertices behind, centroid still in front
    return v


CAM0 = "images/cam0.jpg.npz"
SPHERE = "templates/sphere.npz"
NPZ_CASES = [
    (CAM0, setitem("p0/vertices_cam", (3, 1), np.nan), "p0/vertices_cam", "NaN"),
    (CAM0, setitem("p0/surface_bary", (0, 0), np.inf), "p0/surface_bary", "inf"),
    (CAM0, replace("p1/vertices_cam", lambda v: v[:, :2]), "p1/vertices_cam", "shape"),
    (CAM0, replace("p1/vertices_cam", np.int32), "p1/vertices_cam", "dtype"),
    (CAM0, delete("p1/vertices_cam"), "p1/vertices_cam", "missing array"),
    (CAM0, setitem("p1/faces", (0, 0), 100), "p1/faces", "out of range"),
    (CAM0, replace("p1/faces", np.float32), "p1/faces", "dtype"),
    (CAM0, delete("p1/faces"), "p1/faces", "missing array"),
    (CAM0, lambda d: d.update({"p0/faces": d["p1/faces"]}), "p0/faces", "template"),
    (CAM0, replace("p0/surface_face", lambda a: a[:-1]), "p0/surface_face", "shape"),
    (CAM0, delete("p0/surface_bary"), "p0/surface_bary", "go together"),
    (CAM0, setitem("p0/surface_bary", 2, 0.5), "p0/surface_bary", "barycentric"),
    (CAM0, setitem("p0/surface_bary", 2, [1.5, -0.5, 0]), "p0/surface_bary", "row 2"),
    (CAM0, setitem("p0/surface_face", 0, 80), "p0/surface_face", "out of range"),
    (CAM0, replace("p0/keypoints_cam", lambda a: a[:-1]), "p0/keypoints_cam", "shape"),
    (CAM0, replace("p0/keypoints_valid", np.float32), "p0/keypoints_valid", "dtype"),
    (CAM0, replace("p0/mask", lambda a: a[:, :-1]), "p0/mask", "(480, 640)"),
    (
        CAM0,
        setitem("p0/vertices_cam", (slice(None), 2), -3),
        "p0/vertices_cam",
        "behind",
    ),
    (CAM0, replace("p0/vertices_cam", half_behind), "p0/vertices_cam", "5 of 42"),
    (
        CAM0,
        replace("p0/vertices_cam", lambda v: v * 1e3),
        "p0/vertices_cam",
        "millimet",
    ),
    (CAM0, replace("p0/vertices_cam", shrink), "p0/vertices_cam", "small"),
    (CAM0, setitem("p0/surface_xy", 7, [700, 10]), "p0/surface_xy", "640x480 image"),
    (CAM0, setitem("p0/keypoints_xy", 0, [-5, 10]), "p0/keypoints_xy", "outside"),
    (SPHERE, setitem("faces", (0, 0), -1), "faces", "negative"),
    (SPHERE, delete("faces"), "faces", "missing array"),
]


@pytest.mark.parametrize(("file", "edit", "field", "problem"), NPZ_CASES)
def test_invalid_arrays(
    priors_dir: Path, file: str, edit: Callable, field: str, problem: str
) -> None:
    edit_npz(priors_dir / file, edit)
    with pytest.raises(PriorsError) as info:
        read_priors(priors_dir, image_sizes=SIZES)
    assert f"{file}: {field}: " in str(info.value)
    assert problem in str(info.value)
    assert (info.value.field, Path(info.value.file)) == (field, priors_dir / file)


def test_topology_mismatch(priors_dir: Path) -> None:
    add_vertex = replace("p0/vertices_cam", lambda v: np.vstack([v, v[:1]]))
    edit_npz(priors_dir / "images/cams/a.jpg.npz", add_vertex)
    with pytest.raises(PriorsError) as info:
        read_priors(priors_dir)
    assert "cams/a.jpg.npz: p0/vertices_cam: 43 vertices" in str(info.value)
    assert f"template 'sphere' has 42 in {priors_dir / CAM0}" in str(info.value)


def test_template_faces_beyond_vertices(priors_dir: Path) -> None:
    edit_npz(priors_dir / SPHERE, setitem("faces", (0, 0), 42))
    with pytest.raises(PriorsError) as info:
        read_priors(priors_dir)
    # Reported at the first person using the template.
    assert f"{CAM0}: p0/vertices_cam: 42 vertices" in str(info.value)
    assert "indexes vertex 42" in str(info.value)


def image0(doc: dict[str, Any]) -> dict[str, Any]:
    return doc["images"]["cam0.jpg"]


WHERE0 = 'images["cam0.jpg"]'
JSON_CASES = [
    (lambda doc: doc.pop("format"), "format", "missing"),
    (
        lambda doc: doc.update(format="colmap-vc"),
        "format",
        "expected 'colmap-vc-priors'",
    ),
    (lambda doc: doc.update(version=2), "version", "unsupported version 2"),
    (lambda doc: doc.update(version="1"), "version", "expected integer"),
    (lambda doc: doc.update(images=[]), "images", "expected object"),
    (lambda doc: doc.update(templates={"sphere": 3}), 'templates["sphere"]', "path"),
    (lambda doc: image0(doc).pop("persons"), f"{WHERE0}.persons", "missing"),
    (lambda doc: image0(doc).update(width=1280), f"{WHERE0}.width", "database"),
    (lambda doc: image0(doc).pop("height"), f"{WHERE0}.width", "width and height"),
    (
        lambda doc: image0(doc)["persons"][0].update(template="smpl"),
        f"{WHERE0}.persons[0].template",
        "unknown template 'smpl'",
    ),
    (
        lambda doc: image0(doc)["persons"][1].update(confidence=1.5),
        f"{WHERE0}.persons[1].confidence",
        "not in [0, 1]",
    ),
    (
        lambda doc: image0(doc)["persons"][1].update(confidence="high"),
        f"{WHERE0}.persons[1].confidence",
        "expected integer or number",
    ),
    (
        lambda doc: image0(doc)["persons"][1].update(person_id=0),
        f"{WHERE0}.persons[1].person_id",
        "appears twice",
    ),
    (lambda doc: image0(doc).update(focal_px=0), f"{WHERE0}.focal_px", "> 0"),
    (
        lambda doc: image0(doc).update(file="images/nothing.npz"),
        f"{WHERE0}.file",
        "nothing.npz does not exist",
    ),
]


@pytest.mark.parametrize(("edit", "field", "problem"), JSON_CASES)
def test_invalid_json(priors_dir: Path, edit: Callable, field: str, problem: str):
    edit_json(priors_dir, edit)
    with pytest.raises(PriorsError) as info:
        read_priors(priors_dir, image_sizes=SIZES)
    assert f"priors.json: {field}: " in str(info.value)
    assert problem in str(info.value)


def test_malformed_json(priors_dir: Path) -> None:
    path = priors_dir / "priors.json"
    path.write_text(path.read_text()[:-10])
    with pytest.raises(PriorsError, match=r"priors.json: \(root\): malformed JSON"):
        read_priors(priors_dir)


def test_missing_and_corrupt_npz(priors_dir: Path) -> None:
    (priors_dir / "images/cams/a.jpg.npz").unlink()
    with pytest.raises(PriorsError, match=r'images\["cams/a.jpg"\].file: .*a.jpg.npz'):
        read_priors(priors_dir)
    (priors_dir / "images/cams/a.jpg.npz").write_bytes(b"not a zip")
    with pytest.raises(PriorsError, match=r"a.jpg.npz: \(file\): unreadable"):
        read_priors(priors_dir)
