"""The synthetic world: ground truth is self-consistent, deterministic, as specified."""

from __future__ import annotations

import hashlib
import itertools
import json
from pathlib import Path

import numpy as np
import pycolmap
import pytest

from colmap_vc import raycast
from colmap_vc.evaluation import rotation_angle_deg
from colmap_vc.priors import read_priors
from colmap_vc.synthetic import SynthOptions, generate, noise
from colmap_vc.synthetic.gt import (
    FALSE_DETECTION,
    FALSE_ID_BASE,
    association_score,
    gt_persons_path,
    read_gt_persons,
    true_ids_priors,
)
from colmap_vc.synthetic.layout import (
    LayoutOptions,
    Preset,
    make_layout,
    pair_angle_deg,
)


def _gt(scene: Path) -> pycolmap.Reconstruction:
    return pycolmap.Reconstruction(scene / "gt" / "sparse")


def test_gt_model_loads_and_matches_the_scene_spec(dome_scene):
    rec = _gt(dome_scene)
    spec = json.loads((dome_scene / "scene.json").read_text())
    assert rec.num_reg_images() == len(spec["cameras"]) == 6
    by_name = {im.name: im for im in rec.images.values()}
    for cam in spec["cameras"]:
        image = by_name[cam["name"]]
        np.testing.assert_allclose(
            image.cam_from_world().matrix(), cam["cam_from_world"], atol=1e-12
        )
        np.testing.assert_allclose(image.camera.params, cam["params"])
        assert (dome_scene / "images" / cam["name"]).is_file()
    # The text model says the same as the binary one.
    text = pycolmap.Reconstruction()
    text.read_text(str(dome_scene / "gt" / "sparse"))
    assert {im.name for im in text.images.values()} == set(by_name)


def test_gt_surface_maps_reproject_to_their_surface_points(dome_scene):
    rec = _gt(dome_scene)
    priors = read_priors(dome_scene / "gt" / "priors")
    checked = 0
    for image in rec.images.values():
        data = np.load(dome_scene / "gt" / "surface" / (Path(image.name).stem + ".npz"))
        by_id = {p.person_id: p for p in priors.images[image.name].persons}
        for pid in np.unique(data["person_id"]):
            sel = data["person_id"] == pid
            person = by_id[int(pid)]
            points = raycast.surface_points(
                person.vertices_cam,
                person.faces,
                data["face"][sel].astype(np.int64),
                data["bary"][sel].astype(np.float64),
            )
            xy = image.camera.img_from_cam(points)
            err = np.linalg.norm(xy - data["xy"][sel], axis=1)
            assert err.max() < 0.5, f"{image.name} person {pid}: {err.max():.3f} px"
            checked += int(sel.sum())
    assert checked > 10_000


def test_gt_priors_agree_across_cameras_through_the_gt_poses(dome_scene):
    """The same person's GT mesh, moved from camera i to camera j by the GT poses."""
    rec = _gt(dome_scene)
    priors = read_priors(dome_scene / "gt" / "priors")
    images = sorted(rec.images.values(), key=lambda im: im.name)
    for a, b in itertools.combinations(images, 2):
        pa = {p.person_id: p for p in priors.images[a.name].persons}
        pb = {p.person_id: p for p in priors.images[b.name].persons}
        for pid in set(pa) & set(pb):
            T_a = a.cam_from_world().matrix()
            T_b = b.cam_from_world().matrix()
            world = (pa[pid].vertices_cam - T_a[:, 3]) @ T_a[:, :3]
            in_b = world @ T_b[:, :3].T + T_b[:, 3]
            # float32 storage of the priors: ~1e-6 m at a few metres.
            assert np.abs(in_b - pb[pid].vertices_cam).max() < 1e-4


def test_predicted_priors_follow_the_noise_model(dome_scene):
    gt = read_priors(dome_scene / "gt" / "priors")
    pred = read_priors(dome_scene / "priors")
    who = read_gt_persons(gt_persons_path(dome_scene))
    rotations, joint_px = [], []
    rec = _gt(dome_scene)
    cams = {im.name: im.camera for im in rec.images.values()}
    for name, image_prior in pred.images.items():
        truth = {p.person_id: p for p in gt.images[name].persons}
        for p, true_id in zip(image_prior.persons, who.images[name], strict=True):
            if true_id == FALSE_DETECTION:
                continue
            t = truth[true_id]
            # Kabsch rotation between the centred meshes: the global orientation error
            # (plus some articulation and shape error).
            A = p.vertices_cam - p.vertices_cam.mean(0)
            B = t.vertices_cam - t.vertices_cam.mean(0)
            U, _, Vt = np.linalg.svd(A.T @ B)
            R = U @ np.diag([1, 1, np.sign(np.linalg.det(U @ Vt))]) @ Vt
            rotations.append(rotation_angle_deg(R))
            # The refit keeps the predicted joints near the person in 2D.
            xy = cams[name].img_from_cam(p.keypoints_cam)
            true_xy = cams[name].img_from_cam(t.keypoints_cam)
            joint_px.append(np.median(np.linalg.norm(xy - true_xy, axis=1)))
            assert p.surface_map is not None and 0 < len(p.surface_map) < 1.05 * len(
                t.surface_map
            )
            assert 0.7 <= p.confidence <= 0.95
    assert 3.0 < np.median(rotations) < 20.0
    assert np.median(joint_px) < 15.0


def test_a_persons_size_error_is_shared_by_its_views(dome_scene):
    """Every view of a person errs about its size alike (scene.json's
    ``size_error``), and a view adds a smaller error of its own."""
    spec = json.loads((dome_scene / "scene.json").read_text())
    shared = {p["person_id"]: p["size_error"]["realistic"] for p in spec["people"]}
    low, high = noise.NOISE_LEVELS[noise.NoiseLevel.REALISTIC].person_size_error
    assert all(low <= abs(e) <= high for e in shared.values())
    gt = read_priors(dome_scene / "gt" / "priors")
    pred = read_priors(dome_scene / "priors")
    who = read_gt_persons(gt_persons_path(dome_scene))

    def size(v: np.ndarray) -> float:
        return float(np.sqrt(((v - v.mean(0)) ** 2).sum(1).mean()))

    ratios: dict[int, list[float]] = {}
    for name, image_prior in pred.images.items():
        truth = {p.person_id: p for p in gt.images[name].persons}
        for p, true_id in zip(image_prior.persons, who.images[name], strict=True):
            if true_id != FALSE_DETECTION:
                t = truth[true_id].vertices_cam
                ratios.setdefault(true_id, []).append(size(p.vertices_cam) / size(t))
    assert set(ratios) == set(shared)
    for person_id, r in ratios.items():
        # The view's own error (up to 5%) and the other phenotype's proportions
        # spread the views about the person's size.
        assert np.median(r) == pytest.approx(1.0 + shared[person_id], abs=0.03)


def test_person_size_error_depends_on_the_person_only():
    model = noise.NOISE_LEVELS[noise.NoiseLevel.REALISTIC]
    errors = [noise.person_size_error(model, 3, person_id) for person_id in range(40)]
    assert errors == [noise.person_size_error(model, 3, i) for i in range(40)]
    assert all(0.03 <= abs(e) <= 0.08 for e in errors)
    assert 5 < sum(e > 0 for e in errors) < 35  # either sign
    assert noise.person_size_error(model, 4, 0) != errors[0]
    assert noise.person_size_error(model, 3, FALSE_DETECTION) == 0.0
    clean = noise.NOISE_LEVELS[noise.NoiseLevel.CLEAN]
    assert noise.person_size_error(clean, 3, 0) == 0.0


def test_clean_priors_are_the_ground_truth(dome_scene):
    gt = read_priors(dome_scene / "gt" / "priors")
    for prior in gt.images.values():
        for p in prior.persons:
            assert p.confidence == 1.0
            assert p.keypoints_valid is not None and p.keypoints_valid.any()


def test_database_has_the_true_intrinsics_and_features(dome_scene):
    from colmap_vc import database

    views = database.read_views(dome_scene / "database.db")
    rec = _gt(dome_scene)
    by_name = {im.name: im for im in rec.images.values()}
    assert set(views.image_names) == set(by_name)
    for name, cam_id, n in zip(
        views.image_names, views.camera_ids, views.num_keypoints, strict=True
    ):
        np.testing.assert_allclose(
            views.cameras[int(cam_id)].params, by_name[name].camera.params
        )
        assert views.cameras[int(cam_id)].model == by_name[name].camera.model
        assert 50 < n <= 2048 * 2  # SIFT cap (COLMAP may add a second orientation)
    assert len(database.read_matches(dome_scene / "database.db")) > 0


def _digest(folder: Path) -> dict[str, str]:
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


def test_same_seed_gives_the_same_files(tmp_path):
    opts = dict(num_cameras=2, width=160, height=120, make_database=False, num_people=1)
    a = generate("dome", tmp_path / "a", SynthOptions(seed=3, **opts)).out_dir
    b = generate("dome", tmp_path / "b", SynthOptions(seed=3, **opts)).out_dir
    c = generate("dome", tmp_path / "c", SynthOptions(seed=4, **opts)).out_dir
    assert _digest(a) == _digest(b)
    assert _digest(a)["images/cam00.jpg"] != _digest(c)["images/cam00.jpg"]


def test_existing_output_is_not_overwritten(tmp_path):
    out = tmp_path / "scene"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    with pytest.raises(FileExistsError, match="overwrite"):
        generate(
            "dome",
            out,
            SynthOptions(num_cameras=2, width=80, height=60, make_database=False),
        )
    assert (out / "keep.txt").read_text() == "mine"


def _angles(layout) -> list[float]:
    return [
        pair_angle_deg(a, b, np.array([0.0, 0.0, 1.0]))
        for a, b in itertools.combinations(layout.cameras, 2)
    ]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_dome_layout_is_all_around(seed):
    layout = make_layout(
        Preset.DOME, np.random.default_rng(seed), num_phenotypes=6, num_poses=8
    )
    assert 8 <= len(layout.cameras) <= 16
    angles = np.array(_angles(layout))
    assert (angles >= 90).mean() > 0.25 and angles.max() > 120
    for cam in layout.cameras:
        r = np.linalg.norm(cam.centre - np.r_[0.0, 0.0, 1.0])
        assert 2.5 < r < 5.5
        assert cam.centre[2] > 0.5


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_dense_layout_overlaps(seed):
    layout = make_layout(
        Preset.DENSE, np.random.default_rng(seed), num_phenotypes=6, num_poses=8
    )
    steps = [
        pair_angle_deg(a, b, np.array([0.0, 0.0, 1.0]))
        for a, b in zip(layout.cameras[:-1], layout.cameras[1:], strict=True)
    ]
    assert min(steps) >= 3 and max(steps) <= 25


@pytest.mark.parametrize("angle", [0.0, 60.0, 150.0])
def test_pair_layout_has_the_requested_angle(angle):
    layout = make_layout(
        Preset.PAIR,
        np.random.default_rng(0),
        num_phenotypes=6,
        num_poses=8,
        options=LayoutOptions(pair_angle_deg=angle),
    )
    assert len(layout.cameras) == 2
    target = np.r_[layout.people[0].position_xy, 1.0]
    assert pair_angle_deg(*layout.cameras, target) == pytest.approx(angle, abs=1e-6)


def test_bad_options_are_rejected():
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError, match="num_people"):
        make_layout(
            Preset.DOME,
            rng,
            num_phenotypes=6,
            num_poses=8,
            options=LayoutOptions(num_people=4),
        )
    with pytest.raises(ValueError, match="camera_model"):
        make_layout(
            Preset.DOME,
            rng,
            num_phenotypes=6,
            num_poses=8,
            options=LayoutOptions(camera_model="FISHEYE_X"),
        )
    with pytest.raises(ValueError):
        Preset("cathedral")


# --- Detection failures, anonymity and the identity ground truth ---------------------

CROWD = dict(
    seed=1,
    num_people=3,
    num_cameras=8,
    noise="hard",
    extra_noise=("clean",),
    bystander=True,
    close_pair=True,
    dress_alike=True,
    make_database=False,
)


@pytest.fixture(scope="module")
def crowd(tmp_path_factory) -> tuple[Path, Path]:
    """The same 3-person dome (+ bystander, close pair, dressed alike, hard detection
    failures) written anonymous and with ids."""
    root = tmp_path_factory.mktemp("crowd")
    anon = generate("dome", root / "anon", SynthOptions(**CROWD)).out_dir
    ids = generate("dome", root / "ids", SynthOptions(with_ids=True, **CROWD)).out_dir
    return anon, ids


def _pixel_owner(scene: Path, name: str) -> dict[tuple[int, int], int]:
    data = np.load(scene / "gt" / "surface" / (Path(name).stem + ".npz"))
    px = np.floor(data["xy"]).astype(int)
    return dict(zip(map(tuple, px), data["person_id"].tolist(), strict=True))


def test_predicted_priors_are_anonymous_by_default(crowd):
    anon, _ = crowd
    for folder in ("priors", "priors_clean"):
        priors = read_priors(anon / folder)
        persons = [p for im in priors.images.values() for p in im.persons]
        assert persons and all(p.person_id is None for p in persons), folder
    # The ground-truth priors keep their ids.
    gt = read_priors(anon / "gt" / "priors")
    assert all(p.person_id is not None for im in gt.images.values() for p in im.persons)


def test_gt_persons_maps_every_prior_person_to_its_true_id(crowd):
    anon, _ = crowd
    priors = read_priors(anon / "priors")
    who = read_gt_persons(gt_persons_path(anon, "priors"))
    assert who.priors == "priors" and set(who.images) == set(priors.images)
    checked = 0
    for name, prior in priors.images.items():
        owner = _pixel_owner(anon, name)
        assert who.visible[name] == sorted(set(owner.values()))
        reported = [i for i in who.images[name] if i != FALSE_DETECTION]
        # Every visible person is either reported (once) or dropped with a reason.
        assert sorted(reported + list(who.dropped[name])) == who.visible[name]
        assert len(who.images[name]) == len(prior.persons)
        for person, true_id in zip(prior.persons, who.images[name], strict=True):
            if true_id == FALSE_DETECTION:
                continue
            px = np.floor(person.surface_map.xy_img).astype(int)
            on = [owner.get(tuple(p), -2) for p in px]
            assert np.mean(np.array(on) == true_id) > 0.99, (name, true_id)
            checked += 1
    assert checked >= 15
    # The clean level reports every visible person.
    clean = read_gt_persons(gt_persons_path(anon, "priors_clean"))
    for name, ids in clean.images.items():
        assert sorted(ids) == clean.visible[name] and not clean.dropped[name]


def test_missed_people_are_absent_from_the_priors(crowd):
    anon, _ = crowd
    priors = read_priors(anon / "priors")
    who = read_gt_persons(gt_persons_path(anon, "priors"))
    dropped = [(n, i, r) for n, d in who.dropped.items() for i, r in d.items()]
    assert any(r.startswith("missed") for _, _, r in dropped), dropped
    for name, person_id, reason in dropped:
        assert reason.split(" ")[0] in ("missed", "cut", "too"), reason
        assert person_id in who.visible[name] and person_id not in who.images[name]
        # No reported person covers the dropped person's pixels.
        owner = _pixel_owner(anon, name)
        for person in priors.images[name].persons:
            px = np.floor(person.surface_map.xy_img).astype(int)
            on = np.array([owner.get(tuple(p), -2) for p in px])
            assert np.mean(on == person_id) < 0.5


def test_bystander_is_seen_by_a_few_cameras_only(crowd):
    anon, _ = crowd
    who = read_gt_persons(gt_persons_path(anon, "priors"))
    (bystander,) = [i for i, role in who.people.items() if role == "bystander"]
    seen = sum(bystander in ids for ids in who.visible.values())
    assert 1 <= seen < len(who.visible)
    spec = json.loads((anon / "scene.json").read_text())
    people = {p["person_id"]: np.array(p["position_xy"]) for p in spec["people"]}
    group = np.mean([xy for i, xy in people.items() if i != bystander], axis=0)
    assert 3.0 <= np.linalg.norm(people[bystander] - group) <= 5.0
    # The close pair: persons 0 and 1 stand 0.5-0.8 m apart.
    assert 0.5 <= np.linalg.norm(people[0] - people[1]) <= 0.8


def test_false_detections_are_flagged_and_are_nobody(crowd):
    anon, ids = crowd
    priors = read_priors(anon / "priors")
    gt = read_priors(anon / "gt" / "priors")
    who = read_gt_persons(gt_persons_path(anon, "priors"))
    false = [
        (name, k)
        for name, true_ids in who.images.items()
        for k, i in enumerate(true_ids)
        if i == FALSE_DETECTION
    ]
    assert false, "the hard level of this seed makes false detections"
    for name, k in false:
        fake = priors.images[name].persons[k].vertices_cam
        for real in gt.images[name].persons:
            # Same topology: vertex-wise distance to every real person's true mesh.
            assert np.median(np.linalg.norm(fake - real.vertices_cam, axis=1)) > 0.2
    # With ids, each false detection gets its own id, linked to nothing.
    with_ids = read_priors(ids / "priors")
    fake_ids = [with_ids.images[n].persons[k].person_id for n, k in false]
    assert len(set(fake_ids)) == len(fake_ids)
    assert all(i >= FALSE_ID_BASE for i in fake_ids)


def test_with_ids_adds_the_true_ids_and_changes_nothing_else(crowd):
    anon, ids = crowd
    a, b = _digest(anon), _digest(ids)
    # Images, ground truth, surface maps: the same bytes.
    same = [k for k in a if not k.startswith("priors") and k != "scene.json"]
    assert same and all(a[k] == b[k] for k in same)
    pa, pb = read_priors(anon / "priors"), read_priors(ids / "priors")
    who = read_gt_persons(gt_persons_path(anon, "priors"))
    derived = true_ids_priors(pa, who)
    for name in pa.images:
        for x, y, z in zip(
            pa.images[name].persons,
            pb.images[name].persons,
            derived.images[name].persons,
            strict=True,
        ):
            np.testing.assert_array_equal(x.vertices_cam, y.vertices_cam)
            np.testing.assert_array_equal(x.surface_map.xy_img, y.surface_map.xy_img)
            assert y.person_id == z.person_id is not None
        assert [p.person_id for p in pb.images[name].persons if p.person_id < 1000] == [
            i for i in who.images[name] if i != FALSE_DETECTION
        ]


def test_association_score_counts_links_across_views(crowd):
    anon, _ = crowd
    who = read_gt_persons(gt_persons_path(anon, "priors"))
    truth = {
        n: [None if i == FALSE_DETECTION else i for i in ids]
        for n, ids in who.images.items()
    }
    perfect = association_score(who, truth)
    assert perfect.true_links > 0
    assert perfect.precision == perfect.recall == 1.0
    nothing = association_score(who, {})
    assert nothing.predicted_links == 0 and nothing.recall == 0.0
    everyone = association_score(who, {n: [0] * len(i) for n, i in who.images.items()})
    assert everyone.recall == 1.0 and everyone.precision < 1.0
    # Swapping two people's ids in one image breaks exactly their links.
    name = max(who.images, key=lambda n: len(set(who.images[n]) - {FALSE_DETECTION}))
    swapped = dict(truth)
    row = list(truth[name])
    j, k = [i for i, t in enumerate(row) if t is not None][:2]
    row[j], row[k] = row[k], row[j]
    swapped[name] = row
    score = association_score(who, swapped)
    assert score.correct_links < perfect.correct_links
    assert score.predicted_links == perfect.predicted_links


def test_crowd_scenes_are_deterministic(tmp_path):
    opts = dict(CROWD, num_cameras=3, width=320, height=240, extra_noise=())
    a = generate("dome", tmp_path / "a", SynthOptions(**opts)).out_dir
    b = generate("dome", tmp_path / "b", SynthOptions(**opts)).out_dir
    da, db = _digest(a), _digest(b)
    assert "gt/persons.json" in da and da == db


def test_dress_alike_shares_the_clothes():
    from colmap_vc.synthetic import bodies as body_lib
    from colmap_vc.synthetic.render import build_world

    bodies = body_lib.load_bodies()
    outfits = {}
    for alike in (False, True):
        rng = np.random.default_rng(5)
        layout = make_layout(
            Preset.DOME,
            rng,
            num_phenotypes=bodies.rest_vertices.shape[0],
            num_poses=bodies.pose_rotvec.shape[0],
            options=LayoutOptions(num_people=2, num_cameras=2),
        )
        posed = [body_lib.pose_body(bodies, p.phenotype, p.pose) for p in layout.people]
        world = build_world(layout, bodies, posed, rng, dress_alike=alike)
        outfits[alike] = [p.outfit for p in world.people]
    distinct, alike = outfits[False], outfits[True]
    assert not np.allclose(distinct[0].shirt, distinct[1].shirt)
    np.testing.assert_array_equal(alike[1].shirt, alike[0].shirt)
    np.testing.assert_array_equal(alike[1].trousers, alike[0].trousers)
    assert alike[1].pattern == alike[0].pattern
    np.testing.assert_array_equal(alike[1].skin, distinct[1].skin)


def test_cli_flags_reach_the_generator(tmp_path):
    from colmap_vc.cli import main

    common = ["--cameras", "2", "--people", "2", "--width", "160", "--height", "120"]
    common += ["--no-database", "--close-pair", "--bystander", "--dress-alike"]
    for name, extra in (("anon", []), ("ids", ["--with-ids"])):
        assert main(["synth", "dome", str(tmp_path / name), *common, *extra]) == 0
    spec = json.loads((tmp_path / "ids" / "scene.json").read_text())
    opts = spec["options"]
    assert opts["with_ids"] and opts["close_pair"] and opts["bystander"]
    assert opts["dress_alike"] and spec["people"][-1]["bystander"]
    anon = read_priors(tmp_path / "anon" / "priors")
    ids = read_priors(tmp_path / "ids" / "priors")
    assert all(p.person_id is None for im in anon.images.values() for p in im.persons)
    who = read_gt_persons(gt_persons_path(tmp_path / "ids"))
    for name, prior in ids.images.items():
        got = [p.person_id for p in prior.persons]
        want = who.images[name]
        assert [g for g, w in zip(got, want, strict=True) if w >= 0] == [
            w for w in want if w >= 0
        ]


def test_a_turned_prior_faces_away_and_is_read_off_its_own_mesh(dome_scene):
    """The front/back confusion of a pose estimator (noise ``turn_prob``): the mesh
    turns 180 deg about the body's vertical axis through the pelvis, its facing
    (left shoulder - right shoulder) x up reverses, and the dense map names the
    turned mesh's points under each pixel."""
    from colmap_vc.synthetic import noise
    from colmap_vc.synthetic.bodies import joints, load_bodies, pose_body

    bodies = load_bodies()
    body = pose_body(bodies, 0, 0)
    # Body frame (left -X, forward +Y, up +Z) -> camera (x right, y down, z ahead):
    # the person stands 4 m ahead, facing the camera.
    R = np.array([[-1.0, 0, 0], [0, 0, -1.0], [0, -1.0, 0]])
    view = noise.PersonView(
        person_id=0,
        phenotype=0,
        pose=0,
        body_vertices=body,
        cam_from_body=np.c_[R, [0.0, 0.0, 4.0]],
        xy_img=np.zeros((0, 2)),
        face_idx=np.zeros(0, np.int64),
        bary=np.zeros((0, 3)),
        mask=np.zeros((480, 640), bool),
    )
    verts = body @ R.T + [0.0, 0.0, 4.0]
    turned = noise._turned(bodies, view, verts)
    names = bodies.joint_names
    up = R @ [0.0, 0.0, 1.0]

    def facing(v):
        j = joints(bodies, v)
        return np.cross(
            j[names.index("left_shoulder")] - j[names.index("right_shoulder")], up
        )

    assert facing(verts) @ facing(turned) < 0  # now faces away
    assert np.allclose(joints(bodies, turned)[0], joints(bodies, verts)[0])
    assert np.allclose(noise._turned(bodies, view, turned), verts)
    camera = pycolmap.Camera(
        model="PINHOLE", width=640, height=480, params=[500.0, 500.0, 320.0, 240.0]
    )
    xy = np.asarray(camera.img_from_cam(turned[::20]))
    smap = noise._map_of_mesh(turned, bodies.faces, camera, xy)
    assert len(smap.xy_img) > 0.8 * len(xy)
    points = np.einsum("nk,nkd->nd", smap.bary, turned[bodies.faces[smap.face_idx]])
    assert np.allclose(camera.img_from_cam(points), smap.xy_img, atol=1e-3)


# --- Scaling: many cameras, static cameras over instants, databases without SIFT ----


def test_names_sort_in_camera_order_past_100_cameras():
    def names(n: int) -> list[str]:
        layout = make_layout(
            Preset.DOME,
            np.random.default_rng(0),
            num_phenotypes=6,
            num_poses=8,
            options=LayoutOptions(num_cameras=n),
        )
        return [c.name for c in layout.cameras]

    assert names(100)[-1] == "cam99.jpg"  # two digits up to 100, as always
    many = names(128)
    assert many[0] == "cam000.jpg" and many[-1] == "cam127.jpg"
    assert sorted(many) == many and len(set(many)) == 128
    assert len(names(256)) == 256


def test_too_many_cameras_are_refused():
    rng = np.random.default_rng(0)
    for preset, n, most in ((Preset.DOME, 257, 256), (Preset.DENSE, 65, 64)):
        with pytest.raises(
            ValueError, match=f"num_cameras={n} must be between 2 and {most}"
        ):
            make_layout(
                preset,
                rng,
                num_phenotypes=6,
                num_poses=8,
                options=LayoutOptions(num_cameras=n),
            )
    with pytest.raises(ValueError, match="num_instants"):
        generate("dome", Path("/nonexistent"), SynthOptions(num_instants=0))


INSTANTS = ["--cameras", "3", "--people", "2", "--width", "160", "--height", "120"]


@pytest.fixture(scope="module")
def instants_scene(tmp_path_factory) -> Path:
    """3 static cameras x 3 instants, 2 people each, database without SIFT (CLI)."""
    from colmap_vc.cli import main

    out = tmp_path_factory.mktemp("instants") / "scene"
    args = ["synth", "dome", str(out), *INSTANTS, "--instants", "3", "--no-sift"]
    assert main(args) == 0
    return out


def test_instants_share_the_camera_poses(instants_scene):
    rec = _gt(instants_scene)
    spec = json.loads((instants_scene / "scene.json").read_text())
    assert spec["options"]["num_instants"] == 3 and not spec["options"]["sift"]
    names = sorted(im.name for im in rec.images.values())
    assert names == [f"cam{i:02d}_t{k:02d}.jpg" for i in range(3) for k in range(3)]
    assert names == sorted(c["name"] for c in spec["cameras"])
    poses: dict[str, list[np.ndarray]] = {}
    for image in rec.images.values():
        camera = image.name.split("_")[0]
        poses.setdefault(camera, []).append(image.cam_from_world().matrix())
        assert (instants_scene / "images" / image.name).is_file()
        assert (
            instants_scene / "gt/surface" / f"{Path(image.name).stem}.npz"
        ).is_file()
    for same in poses.values():
        assert len(same) == 3
        for pose in same[1:]:
            np.testing.assert_array_equal(pose, same[0])
    assert not np.allclose(poses["cam00"][0], poses["cam01"][0])
    # The backdrop stays: images of one camera differ where the people are only.
    import cv2

    t0, t1 = (
        cv2.imread(str(instants_scene / "images" / f"cam00_t0{k}.jpg")).astype(float)
        for k in (0, 1)
    )
    assert np.median(np.abs(t0 - t1)) < 4


def test_instants_have_distinct_people(instants_scene):
    spec = json.loads((instants_scene / "scene.json").read_text())
    who = read_gt_persons(gt_persons_path(instants_scene))
    assert sorted(who.people) == list(range(6))
    people = {p["person_id"]: p for p in spec["people"]}
    assert [p["instant"] for p in spec["people"]] == [0, 0, 1, 1, 2, 2]
    positions = np.array([p["position_xy"] for p in spec["people"]])
    assert np.linalg.norm(positions[0] - positions[2:], axis=1).min() > 1e-3
    gt = read_priors(instants_scene / "gt" / "priors")
    assert set(gt.images) == set(who.visible) and len(gt.images) == 9
    for name, ids in who.visible.items():
        instant = int(name.split("_t")[1][:2])
        assert ids and {people[i]["instant"] for i in ids} == {instant}, name
        assert sorted(p.person_id for p in gt.images[name].persons) == ids
        owners = np.load(instants_scene / "gt/surface" / f"{Path(name).stem}.npz")
        assert sorted(set(owners["person_id"].tolist())) == ids


def test_database_without_sift_has_cameras_and_images_only(instants_scene):
    from colmap_vc import database

    views = database.read_views(instants_scene / "database.db")
    rec = _gt(instants_scene)
    by_name = {im.name: im for im in rec.images.values()}
    assert sorted(views.image_names) == sorted(by_name)
    assert list(views.image_names) == sorted(views.image_names)
    assert len(set(views.camera_ids.tolist())) == len(views.image_names)
    for name, camera_id in zip(views.image_names, views.camera_ids, strict=True):
        camera = views.cameras[int(camera_id)]
        assert camera.model == by_name[name].camera.model
        np.testing.assert_allclose(camera.params, by_name[name].camera.params)
    assert not views.num_keypoints.any() and not views.num_vc_keypoints.any()
    assert database.read_matches(instants_scene / "database.db") == {}


def test_instants_are_deterministic_and_instant_0_is_the_one_instant_scene(tmp_path):
    opts = dict(seed=2, num_cameras=2, num_people=1, width=160, height=120, sift=False)
    one = generate("dome", tmp_path / "one", SynthOptions(**opts)).out_dir
    a = generate("dome", tmp_path / "a", SynthOptions(num_instants=2, **opts)).out_dir
    b = generate("dome", tmp_path / "b", SynthOptions(num_instants=2, **opts)).out_dir
    assert _digest(a) == _digest(b)
    # One instant keeps today's names; more instants leave instant 0 as it was.
    d1, da = _digest(one), _digest(a)
    assert sorted(p for p in d1 if p.startswith("images/")) == [
        "images/cam00.jpg",
        "images/cam01.jpg",
    ]
    for cam in ("cam00", "cam01"):
        assert d1[f"images/{cam}.jpg"] == da[f"images/{cam}_t00.jpg"]
        assert d1[f"gt/surface/{cam}.npz"] == da[f"gt/surface/{cam}_t00.npz"]
        assert da[f"images/{cam}_t00.jpg"] != da[f"images/{cam}_t01.jpg"]


def test_a_left_right_flip_of_the_dense_map_mirrors_whole_limbs():
    """A flipped arm takes its hand along and a flipped leg its foot (docs/
    synthetic.md: "whole limbs mirrored left/right"); until NOISE_REVISION 2 the
    hands and feet stayed unflipped."""
    from colmap_vc.synthetic import bodies as body_lib

    names = np.array(body_lib.load_bodies().part_names)
    chains = {
        limb: set(names[noise.limb_part_ids(names, limb)].tolist())
        for limb in ("arm", "leg")
    }
    sides = ("left", "right")
    assert chains["arm"] == {
        f"{part}_{side}"
        for part in ("upper_arm", "lower_arm", "hand")
        for side in sides
    }
    assert chains["leg"] == {
        f"{part}_{side}"
        for part in ("upper_leg", "lower_leg", "foot")
        for side in sides
    }
