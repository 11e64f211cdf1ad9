"""Keypoint BA: identity tracks are right, and the pass pulls perturbed poses back."""

from __future__ import annotations

import dataclasses
import shutil

import numpy as np
import pycolmap
import pytest

from colmap_vc import augment, database, mapping
from colmap_vc.camera_check import check_cameras_inplace
from colmap_vc.evaluation import evaluate_reconstruction
from colmap_vc.gba.ceres import bundle_adjust_inplace
from colmap_vc.keypoint_ba import KeypointBaOptions, keypoint_bundle_adjustment
from colmap_vc.keypoint_tracks import (
    KeypointTracks,
    add_keypoint_points,
    keypoint_tracks,
    mirrored_tracks,
    relabelled,
    solve_tracks,
    subset,
    track_system,
    triangulate_tracks,
)
from colmap_vc.mapping.up import keypoint_noise_px
from colmap_vc.vc_records import person_identities, read_vc_records


def _adjust(rec: pycolmap.Reconstruction) -> None:
    """The camera check's bundle adjustment: COLMAP's, Cauchy loss at 4 px."""
    bundle_adjust_inplace(rec, 4.0)


@pytest.fixture(scope="module")
def mapped(dome_scene, tmp_path_factory):
    """The clean-prior dome, augmented and mapped without the keypoint pass."""
    work = tmp_path_factory.mktemp("kba")
    db = work / "database.db"
    shutil.copyfile(dome_scene / "database.db", db)
    augment.run(
        db, dome_scene / "gt" / "priors", augment.AugmentOptions(show_progress=False)
    )
    rec, _ = mapping.run(
        db,
        dome_scene / "images",
        work / "sparse",
        mapping.MappingOptions(num_threads=2, keypoint_ba=False, show_progress=False),
    )
    return db, rec


def test_person_identities_follow_association_chains():
    A = database.AssociationMethod("geometric")
    assoc = [
        database.PersonAssociation(
            image_id1=1, image_id2=2, person_id1=0, person_id2=1, method=A, score=1.0
        ),
        database.PersonAssociation(
            image_id1=2, image_id2=3, person_id1=1, person_id2=0, method=A, score=1.0
        ),
        database.PersonAssociation(
            image_id1=1, image_id2=2, person_id1=1, person_id2=0, method=A, score=1.0
        ),
    ]
    ident = person_identities(assoc)
    assert ident[(1, 0)] == ident[(2, 1)] == ident[(3, 0)]
    assert ident[(1, 1)] == ident[(2, 0)] != ident[(1, 0)]


def test_identity_tracks_triangulate_consistently(mapped):
    db, rec = mapped
    registered = np.array(list(rec.reg_image_ids()), dtype=np.int64)
    tracks = keypoint_tracks(read_vc_records(db), registered)
    assert tracks.num_tracks > 0
    # One observation per image and track.
    pairs = np.stack([tracks.track, tracks.image_id], axis=1)
    assert len(np.unique(pairs, axis=0)) == len(pairs)
    # Clean priors: every track's rays meet (reprojection of its DLT point, px).
    X, counts = triangulate_tracks(rec, tracks)
    err = []
    for image_id in np.unique(tracks.image_id):
        sel = tracks.image_id == image_id
        image = rec.image(int(image_id))
        T = image.cam_from_world().matrix()
        pc = X[tracks.track[sel]] @ T[:, :3].T + T[:, 3]
        xy = np.asarray(rec.camera(image.camera_id).img_from_cam(pc))
        err.append(np.linalg.norm(xy - tracks.xy_img[sel], axis=1))
    assert (counts >= 2).all() and np.median(np.concatenate(err)) < 2.0


def test_a_left_out_camera_no_longer_counts_in_keypoint_tracks(mapped):
    """A camera check that leaves an image out (deregisters it) and then re-adds
    keypoint points: the left-out image neither triangulates nor observes them
    (its frame has no pose; reading it raised in pycolmap, seen at 128 images)."""
    db, rec = mapped
    rec = pycolmap.Reconstruction(rec)
    registered = np.array(sorted(rec.reg_image_ids()), dtype=np.int64)
    tracks = keypoint_tracks(read_vc_records(db), registered)
    X_all, counts_all = triangulate_tracks(rec, tracks)
    gone = int(registered[0])
    for point_id in list(rec.point3D_ids()):
        rec.delete_point3D(point_id)
    rec.deregister_frame(rec.image(gone).frame_id)
    X, counts = triangulate_tracks(rec, tracks)
    seen = np.bincount(tracks.track[tracks.image_id == gone], minlength=len(counts))
    assert np.array_equal(counts, counts_all - seen)
    good, _ = add_keypoint_points(rec, tracks, min_track_length=2)
    assert good.any() and rec.num_points3D() == int(good.sum())
    assert all(
        e.image_id != gone for p in rec.points3D.values() for e in p.track.elements
    )
    kept = (counts == counts_all) & np.isfinite(X_all).all(axis=1)
    assert np.allclose(X[kept], X_all[kept])


def test_tracks_without_one_image_equal_triangulating_the_others(mapped):
    """The label test triangulates each image's tracks from all *other* images by
    taking that image's equations out of the whole system: the same points as
    triangulating the other images' observations alone."""
    from colmap_vc.keypoint_tracks import solve_tracks, track_system

    db, rec = mapped
    registered = np.array(sorted(rec.reg_image_ids()), dtype=np.int64)
    tracks = keypoint_tracks(read_vc_records(db), registered)
    system = track_system(rec, tracks)
    for image_id in registered[:3]:
        mine = tracks.image_id == image_id
        X, counts = solve_tracks(system, tracks, mine)
        X_ref, counts_ref = triangulate_tracks(rec, subset(tracks, ~mine))
        n = len(counts_ref)
        assert np.array_equal(counts[:n], counts_ref)
        ok = (counts_ref >= 2) & np.isfinite(X_ref).all(axis=1)
        assert ok.sum() > 10 and np.allclose(X[:n][ok], X_ref[ok], atol=1e-6)


def _turned(
    rec: pycolmap.Reconstruction, rng: np.random.Generator, deg: float
) -> pycolmap.Reconstruction:
    """A copy of ``rec`` with every camera turned by ``deg`` about a random axis."""
    out = pycolmap.Reconstruction(rec)
    for image in out.images.values():
        w = rng.normal(size=3)
        dR = pycolmap.Rotation3d(w / np.linalg.norm(w) * np.deg2rad(deg)).matrix()
        T = image.cam_from_world().matrix()
        new = pycolmap.Rigid3d(pycolmap.Rotation3d(dR @ T[:, :3]), T[:, 3])
        out.frame(image.frame_id).rig_from_world = new
    return out


def test_keypoint_ba_pulls_perturbed_poses_back(dome_scene, mapped, rng):
    db, rec = mapped
    gt = pycolmap.Reconstruction(dome_scene / "gt" / "sparse")
    before = evaluate_reconstruction(rec, gt).median_error_deg
    perturbed = _turned(rec, rng, 5.0)
    assert evaluate_reconstruction(perturbed, gt).median_error_deg > 3.0
    snapshot = {i: im.cam_from_world().matrix() for i, im in perturbed.images.items()}
    out, summary = keypoint_bundle_adjustment(
        read_vc_records(db), perturbed, KeypointBaOptions(surface_per_image=0.0)
    )
    assert summary.num_tracks > 0 and summary.num_surface_observations == 0
    assert evaluate_reconstruction(out, gt).median_error_deg < max(1.0, 2 * before)
    for i, im in perturbed.images.items():  # the input is not modified
        assert np.array_equal(im.cam_from_world().matrix(), snapshot[i])


def test_the_default_weighs_each_images_surface_points_to_a_fixed_total(
    dome_scene, mapped, rng
):
    """Every VC-only point of the mapper's model stays; an image's N surface
    observations weigh ``surface_per_image`` keypoint observations together (noise
    sqrt(N / budget) each), none are drawn; the same input gives the same model,
    and the poses come back from a 5 deg perturbation."""
    db, rec = mapped
    gt = pycolmap.Reconstruction(dome_scene / "gt" / "sparse")
    views = database.read_views(db)
    first_vc = dict(
        zip(views.image_ids.tolist(), views.num_keypoints.tolist(), strict=True)
    )
    kp = keypoint_tracks(read_vc_records(db), np.array(sorted(rec.images)))
    keypoint_obs = set(zip(kp.image_id.tolist(), kp.point2D_idx.tolist(), strict=True))
    surface = [  # the VC-only points that observe no keypoint VC
        (e.image_id, e.point2D_idx)
        for p in rec.points3D.values()
        if all(
            e.point2D_idx >= first_vc[e.image_id]
            and (e.image_id, e.point2D_idx) not in keypoint_obs
            for e in p.track.elements
        )
        for e in p.track.elements
    ]
    assert len(surface) > 20 * rec.num_reg_images()  # many more than the budget
    perturbed = _turned(rec, rng, 5.0)
    options = KeypointBaOptions(surface_per_image=6.0)
    out, summary = keypoint_bundle_adjustment(read_vc_records(db), perturbed, options)
    assert summary.num_surface_observations == len(surface)
    assert summary.num_surface_observations_dropped == 0
    assert summary.people is not None
    for image_id, sigma in summary.people.sigma_px.items():
        mine = [k for i, k in surface if i == image_id]
        assert np.isfinite(sigma).sum() == len(mine)
        # Weights 1 / sigma^2 of the image's surface observations sum to 6.
        assert np.sum(sigma[mine] ** -2.0) == pytest.approx(6.0)
    again, _ = keypoint_bundle_adjustment(read_vc_records(db), perturbed, options)
    for i, im in out.images.items():
        assert np.array_equal(
            im.cam_from_world().matrix(), again.image(i).cam_from_world().matrix()
        )
    assert evaluate_reconstruction(out, gt).median_error_deg < 1.0


def _tracks_from_points(rec, points, rng, noise_px=1.0):
    """Keypoint tracks of 3D points seen by every camera of ``rec``."""
    track, image_id, xy = [], [], []
    for i, image in sorted(rec.images.items()):
        T = image.cam_from_world().matrix()
        uv = rec.camera(image.camera_id).img_from_cam(points @ T[:, :3].T + T[:, 3])
        track.append(np.arange(len(points)))
        image_id.append(np.full(len(points), i))
        xy.append(np.asarray(uv) + rng.normal(0, noise_px, (len(points), 2)))
    order = np.argsort(np.concatenate(track), kind="stable")
    t, im, p = (np.concatenate(a)[order] for a in (track, image_id, xy))
    return KeypointTracks(track=t, image_id=im, point2D_idx=np.zeros_like(t), xy_img=p)


@pytest.mark.parametrize("turn_deg", [40, 180])
@pytest.mark.parametrize("keypoints", ["right", "garbage"])
def test_camera_check_re_poses_or_leaves_out_a_wrong_camera(
    dome_scene, rng, keypoints, turn_deg
):
    """A camera turned 40 deg, or 180 deg so that every point is behind it (as a
    prior turned front to back can place it): re-posed by PnP when its keypoints
    are right, left out when they fit nothing; the other cameras are untouched."""
    from scipy.spatial.transform import Rotation

    rec = pycolmap.Reconstruction(dome_scene / "gt" / "sparse")
    points = rng.normal(0, 0.4, (30, 3)) * [1, 2, 1] + [0, -0.9, 0]  # a body's extent
    tracks = _tracks_from_points(rec, points, rng)
    name = sorted(im.name for im in rec.images.values())[1]
    image = rec.find_image_with_name(name)
    if keypoints == "garbage":
        mine = tracks.image_id == image.image_id
        tracks.xy_img[mine] = rng.permutation(tracks.xy_img[mine])
    truth = {im.name: im.cam_from_world().matrix() for im in rec.images.values()}
    T = truth[name]
    turn = Rotation.from_euler("y", turn_deg, degrees=True).as_matrix()
    rec.frame(image.frame_id).rig_from_world = pycolmap.Rigid3d(
        pycolmap.Rotation3d(turn @ T[:, :3]), turn @ T[:, 3]
    )
    Xc = points @ (turn @ T[:, :3]).T + turn @ T[:, 3]
    assert (Xc[:, 2] < 0).all() == (turn_deg == 180)
    check = check_cameras_inplace(
        rec, tracks, KeypointBaOptions(loss_scale_px=4.0), _adjust
    )
    relocalised, left_out = check.relocalised, check.left_out
    if keypoints == "right":
        assert relocalised == [name] and not left_out
        got = rec.find_image_with_name(name).cam_from_world().matrix()
        assert np.abs(got[:, :3] @ T[:, :3].T - np.eye(3)).max() < 0.02
    else:
        assert relocalised == [] and list(left_out) == [name]
        assert not rec.find_image_with_name(name).has_pose
    for other in truth:
        if other != name:  # the others stay where they were (to BA noise)
            got = rec.find_image_with_name(other).cam_from_world().matrix()
            assert np.abs(got[:, :3] @ truth[other][:, :3].T - np.eye(3)).max() < 0.02


def test_camera_check_never_judges_a_camera_classic_matches_place(dome_scene, rng):
    """A camera whose people fit nothing (a wrong prior) but that observes enough
    model points through SIFT keypoints is where those put it: kept, not moved."""
    rec = pycolmap.Reconstruction(dome_scene / "gt" / "sparse")
    points = rng.normal(0, 0.4, (30, 3)) * [1, 2, 1] + [0, -0.9, 0]
    tracks = _tracks_from_points(rec, points, rng)
    names = sorted(im.name for im in rec.images.values())
    image = rec.find_image_with_name(names[1])
    mine = tracks.image_id == image.image_id
    tracks.xy_img[mine] = rng.permutation(tracks.xy_img[mine])  # its people: wrong
    # 40 background points seen by it and its neighbour through classic keypoints.
    other = rec.find_image_with_name(names[2])
    background = rng.uniform(-1.5, 1.5, (40, 3)) + np.array([0.0, 0.0, 0.5])
    for im in (image, other):
        T = im.cam_from_world().matrix()
        uv = rec.camera(im.camera_id).img_from_cam(background @ T[:, :3].T + T[:, 3])
        im.points2D = pycolmap.Point2DList([pycolmap.Point2D(p) for p in uv])
    for k, X in enumerate(background):
        track = pycolmap.Track()
        track.add_element(image.image_id, k)
        track.add_element(other.image_id, k)
        rec.add_point3D(X, track)
    before = image.cam_from_world().matrix()
    num_classic = {
        i: (40 if i in (image.image_id, other.image_id) else 0) for i in rec.images
    }
    options = KeypointBaOptions(loss_scale_px=4.0)
    check = check_cameras_inplace(
        pycolmap.Reconstruction(rec),
        tracks,
        options,
        _adjust,
        num_classic=dict.fromkeys(rec.images, 0),
    )
    assert list(check.left_out) == [names[1]]  # without the SIFT points: left out
    check = check_cameras_inplace(
        rec, tracks, options, _adjust, num_classic=num_classic
    )
    assert not check.relocalised and not check.left_out
    assert np.allclose(rec.image(image.image_id).cam_from_world().matrix(), before)


@pytest.mark.parametrize("loss_px", [4.0, 40.0])
def test_camera_check_exchanges_left_and_right(dome_scene, rng, loss_px, caplog):
    """A camera whose pose estimator labelled the person's left as right (seen from
    the back, taken for the front) sits on the mirror side: the check re-poses it
    with left and right exchanged and its keypoints join their counterparts'
    tracks, so the bundle adjustment keeps it there. With a loose limit (40 px)
    a pose for the labels as they are fits within it too (14 px); the exchange
    fits better (1 px) and is taken at once, not the PnP pose (pose2sim_single
    t070: PnP as labelled at the limit, 40 px, then the meshes left the camera
    out)."""
    rec = pycolmap.Reconstruction(dome_scene / "gt" / "sparse")
    # 12 "left" points at x < 0 and their mirror images: track k pairs with k ^ 1.
    left = rng.normal(0, 0.3, (12, 3)) * [1, 2, 1] + [-0.25, -0.9, 0]
    points = np.repeat(left, 2, axis=0)
    points[1::2, 0] = -points[1::2, 0] + 0.1 * rng.normal(size=12)
    tracks = _tracks_from_points(rec, points, rng)
    name = sorted(im.name for im in rec.images.values())[1]
    image_id = rec.find_image_with_name(name).image_id
    swap = np.arange(len(points)) ^ 1
    xy = tracks.xy_img.copy()
    # Its detection of keypoint k is where keypoint k ^ 1 is: labels exchanged.
    sel = np.flatnonzero(tracks.image_id == image_id)
    sel = sel[np.argsort(tracks.track[sel])]
    xy[sel] = tracks.xy_img[sel][swap]
    idx = np.zeros(len(tracks.track), dtype=np.int64)
    for i in np.unique(tracks.image_id):  # keypoint k is point2D k of every image
        sel = tracks.image_id == i
        idx[sel] = tracks.track[sel]
        rec.image(int(i)).points2D = pycolmap.Point2DList(
            [pycolmap.Point2D(p) for p in xy[sel][np.argsort(tracks.track[sel])]]
        )
    keys = np.stack([np.zeros(len(points), np.int64), 2000 + np.arange(len(points))], 1)
    tracks = KeypointTracks(
        track=tracks.track,
        image_id=tracks.image_id,
        point2D_idx=idx,
        xy_img=xy,
        keys=keys,
    )
    mirror = {2000 + k: 2000 + int(swap[k]) for k in range(len(points))}
    assert (mirrored_tracks(tracks, mirror) == swap).all()
    truth = {im.name: im.cam_from_world().matrix() for im in rec.images.values()}
    options = KeypointBaOptions(loss_scale_px=loss_px, min_check_points=8)
    # Without the mirror the camera is left out (or re-posed where its labels
    # fit); with it, re-posed where it is.
    plain = pycolmap.Reconstruction(rec)
    check = check_cameras_inplace(plain, tracks, options, _adjust)
    assert not check.mirrored
    assert list(check.left_out) == [name] or check.relocalised == [name]
    num_classic = dict.fromkeys(rec.images, 0)  # every keypoint is a VC
    caplog.clear()
    check = check_cameras_inplace(
        rec, tracks, options, _adjust, mirror=mirror, num_classic=num_classic
    )
    assert check.mirrored == [name] == check.relocalised and not check.left_out
    assert "re-posed by PnP" not in caplog.text
    for other, T in truth.items():
        got = rec.find_image_with_name(other).cam_from_world().matrix()
        assert np.abs(got[:, :3] @ T[:, :3].T - np.eye(3)).max() < 0.02, other
    assert len(rec.points3D) == len(points)  # rebuilt, one per keypoint
    # What map's gravity step weighs the ups against: the keypoint noise of the
    # tracks as the model now holds them (1 px was added), not as labelled.
    held, labelled = (keypoint_noise_px(rec, t, 0.5) for t in (check.tracks, tracks))
    assert held < 2.0 and labelled > 10 * held, (held, labelled)


def _rotation_deg(a: np.ndarray, b: np.ndarray) -> float:
    cos = (np.trace(a[:, :3] @ b[:, :3].T) - 1) / 2
    return float(np.rad2deg(np.arccos(np.clip(cos, -1, 1))))


def _posed_where_labels_fit(rec, image_id, xy, points) -> None:
    """Pose image ``image_id`` where its keypoints ``xy`` (of ``points``) fit, as
    the mapper would: PnP on the true points."""
    image = rec.image(image_id)
    est = pycolmap.AbsolutePoseEstimationOptions()
    est.ransac.max_error = 1e3
    found = pycolmap.estimate_and_refine_absolute_pose(
        xy, points, rec.camera(image.camera_id), est
    )
    assert found is not None
    rec.frame(image.frame_id).rig_from_world = found["cam_from_world"]


def _label_check(rec, tracks, num_templates: int, adjust=_adjust):
    """The camera check where only the label test can fire (the ratio test is
    off), tracks 2000 + k and 2000 + (k ^ 1) left/right counterparts."""
    options = KeypointBaOptions(
        loss_scale_px=4.0, min_check_points=8, max_check_ratio=1e3
    )
    return check_cameras_inplace(
        rec,
        tracks,
        options,
        adjust,
        mirror={2000 + k: 2000 + (k ^ 1) for k in range(num_templates)},
        num_classic=dict.fromkeys(rec.images, 0),
    )


@pytest.mark.parametrize("exchanged", [True, False])
def test_camera_check_tests_left_and_right_where_no_camera_misses_by_far(
    dome_scene, rng, exchanged
):
    """A camera on the mirror side whose error stays within the check's ratio (a
    nearly symmetric pose): its labels exchanged fit the others' points
    significantly better, so it is re-posed with them and the model comes to the
    optimum the same adjustment reaches from the truth. Where every label is
    right, nobody is exchanged and no camera moves."""
    rec = pycolmap.Reconstruction(dome_scene / "gt" / "sparse")
    left = rng.normal(0, 0.3, (12, 3)) * [1, 2, 1] + [-0.25, -0.9, 0]
    points = np.repeat(left, 2, axis=0)
    points[1::2, 0] = -points[1::2, 0] + 0.05 * rng.normal(size=12)
    tracks = _tracks_from_points(rec, points, rng, noise_px=1.0)
    keys = np.stack([np.zeros(len(points), np.int64), 2000 + np.arange(len(points))], 1)
    tracks = KeypointTracks(
        track=tracks.track,
        image_id=tracks.image_id,
        point2D_idx=tracks.track.copy(),  # keypoint k is point2D k of every image
        xy_img=tracks.xy_img,
        keys=keys,
    )

    def with_keypoints(xy: np.ndarray) -> pycolmap.Reconstruction:
        out = pycolmap.Reconstruction(dome_scene / "gt" / "sparse")
        for i in np.unique(tracks.image_id):
            mine = np.flatnonzero(tracks.image_id == i)
            mine = mine[np.argsort(tracks.track[mine])]
            out.image(int(i)).points2D = pycolmap.Point2DList(
                [pycolmap.Point2D(p) for p in xy[mine]]
            )
        return out

    optimum = with_keypoints(tracks.xy_img)  # the right labels, adjusted
    add_keypoint_points(optimum, tracks, 2)
    _adjust(optimum)
    rec = with_keypoints(tracks.xy_img)
    truth = {im.name: im.cam_from_world().matrix() for im in rec.images.values()}
    # Not one of the two cameras that fix the gauge (the first two by id).
    name = sorted(truth)[3]
    image = rec.find_image_with_name(name)
    if exchanged:
        swap = np.arange(len(points)) ^ 1
        sel = np.flatnonzero(tracks.image_id == image.image_id)
        sel = sel[np.argsort(tracks.track[sel])]
        xy = tracks.xy_img.copy()
        xy[sel] = tracks.xy_img[sel][swap]  # its detection k is where k ^ 1 is
        tracks = dataclasses.replace(tracks, xy_img=xy)
        rec = with_keypoints(xy)
        image = rec.find_image_with_name(name)
        # The mapper put it where those labels fit: PnP on the true points.
        _posed_where_labels_fit(rec, image.image_id, xy[sel], points)
        assert _rotation_deg(image.cam_from_world().matrix(), truth[name]) > 10
    add_keypoint_points(rec, tracks, 2)
    # The ratio test alone would never fire: only the label test can.
    adjusted = []
    check = _label_check(
        rec, tracks, len(points), lambda r: adjusted.append(_adjust(r))
    )
    assert not check.left_out
    assert check.mirrored == check.relocalised == ([name] if exchanged else [])
    # The trial's adjustment is the model's: one per confirmed exchange.
    assert len(adjusted) == (1 if exchanged else 0)
    for im in rec.images.values():
        got = im.cam_from_world().matrix()
        if exchanged:
            want = optimum.find_image_with_name(im.name).cam_from_world().matrix()
            assert _rotation_deg(got, want) < 0.1, im.name
        else:
            assert np.array_equal(got, truth[im.name]), im.name


def _two_people_seen_from_the_back(dome_scene, rng):
    """A static camera's image holding two instants' people, both labelled left
    for right, posed where those labels fit -> (model with their points, tracks,
    keypoints per person, the image's id and name)."""
    gt = pycolmap.Reconstruction(dome_scene / "gt" / "sparse")
    people = []
    for shift in ([0.0, 0.0, 0.0], [0.6, 0.4, 0.0]):  # two instants' people
        left = rng.normal(0, 0.3, (12, 3)) * [1, 2, 1] + [-0.25, -0.9, 0]
        pts = np.repeat(left, 2, axis=0)
        pts[1::2, 0] = -pts[1::2, 0] + 0.05 * rng.normal(size=12)
        people.append(pts + shift)
    points = np.concatenate(people)
    n = len(people[0])
    tracks = _tracks_from_points(gt, points, rng, noise_px=1.0)
    keys = np.stack([np.arange(2 * n) // n, 2000 + np.arange(2 * n) % n], axis=1)
    swap = np.arange(2 * n) ^ 1  # left <-> right within each person
    name = sorted(im.name for im in gt.images.values())[3]  # not a gauge camera
    image_id = gt.find_image_with_name(name).image_id
    sel = np.flatnonzero(tracks.image_id == image_id)
    sel = sel[np.argsort(tracks.track[sel])]
    xy = tracks.xy_img.copy()
    xy[sel] = tracks.xy_img[sel][swap]  # both of its people mislabelled
    tracks = KeypointTracks(
        track=tracks.track,
        image_id=tracks.image_id,
        point2D_idx=tracks.track.copy(),  # keypoint k is point2D k of every image
        xy_img=xy,
        keys=keys,
    )
    rec = pycolmap.Reconstruction(gt)
    for i in np.unique(tracks.image_id):
        mine = np.flatnonzero(tracks.image_id == i)
        mine = mine[np.argsort(tracks.track[mine])]
        rec.image(int(i)).points2D = pycolmap.Point2DList(
            [pycolmap.Point2D(p) for p in xy[mine]]
        )
    _posed_where_labels_fit(rec, image_id, xy[sel], points)  # as the mapper would
    add_keypoint_points(rec, tracks, 2)
    return rec, tracks, n, image_id, name


def test_every_person_a_camera_sees_from_the_back_is_exchanged(dome_scene, rng):
    """A static camera's one image holds the people of every instant; a person
    on a treadmill seen from the back is mislabelled at several of them. Each
    (image, person) is exchanged on its own, so the second person of the same
    camera is too (a camera once left the candidates after one exchange), and
    every keypoint then fits its point. An exchanged person whose image holds
    as many other keypoints leaves the tracks: a poor witness once the camera is
    on the right side."""
    rec, tracks, n, image_id, name = _two_people_seen_from_the_back(dome_scene, rng)
    check = _label_check(rec, tracks, n)
    assert check.mirrored == check.relocalised == [name] and not check.left_out
    errors = [  # every observation of the rebuilt points
        np.linalg.norm(
            np.asarray(
                rec.camera(rec.image(e.image_id).camera_id).img_from_cam(
                    rec.image(e.image_id).cam_from_world() * point.xyz
                )
            )
            - rec.image(e.image_id).points2D[e.point2D_idx].xy
        )
        for point in rec.points3D.values()
        for e in point.track.elements
    ]
    assert len(rec.points3D) == 2 * n and max(errors) < 6.0
    # The first person exchanged leaves that image's tracks (the second holds as
    # many keypoints); the second, then alone, stays as the camera's witness.
    seen = [e.image_id for p in rec.points3D.values() for e in p.track.elements]
    assert seen.count(image_id) == n


def test_the_people_one_ranking_finds_are_tried_in_turn(dome_scene, rng, monkeypatch):
    """After a confirmed exchange the people the last ranking found are tested
    again one by one and tried, not ranked again with everybody: one ranking
    finds both people seen from the back, a second finds nobody left. (Ranking
    again after every exchange made the check's cost grow with the cube of a
    static camera's instants.) Both are still exchanged."""
    from colmap_vc import label_check

    rec, tracks, n, image_id, name = _two_people_seen_from_the_back(dome_scene, rng)
    rankings: list[int] = []
    rank = label_check.ranked_exchanges

    def counted(*args, **kwargs):
        found = rank(*args, **kwargs)
        rankings.append(len(found))
        return found

    monkeypatch.setattr(label_check, "ranked_exchanges", counted)
    check = _label_check(rec, tracks, n)
    assert check.mirrored == [name] and not check.left_out
    assert rankings == [2, 0]
    assert {(i, p) for i, p in check.exchanged} == {(image_id, 0), (image_id, 1)}


def test_the_label_test_fits_an_image_as_labelled_once(dome_scene, rng, monkeypatch):
    """The image's pose for all its keypoints as labelled is the same whichever
    person's labels are exchanged: the label test fits it once per image (with
    static cameras an image holds every instant's people), and each person's
    test reads what it reads when it fits that pose itself."""
    from colmap_vc import label_check

    rec, tracks, n, image_id, _ = _two_people_seen_from_the_back(dome_scene, rng)
    options = KeypointBaOptions(loss_scale_px=4.0, min_check_points=8)
    partner = mirrored_tracks(tracks, {2000 + k: 2000 + (k ^ 1) for k in range(n)})
    fits: list[int] = []
    pnp = label_check.robust_pnp

    def counted(*args, **kwargs):
        fits.append(len(args[1]))
        return pnp(*args, **kwargs)

    monkeypatch.setattr(label_check, "robust_pnp", counted)
    found = label_check.ranked_exchanges(
        rec, tracks, partner, [image_id], options, 50.0, set()
    )
    assert found and found[0].image_id == image_id
    assert len(fits) == 1 + 2  # as labelled once, then each person exchanged
    others = solve_tracks(
        track_system(rec, tracks), tracks, tracks.image_id == image_id
    )
    fit = label_check.image_fit(rec, tracks, image_id, others, options, 50.0)
    for identity in (0, 1):
        swapped = relabelled(tracks, image_id, partner, identity)
        given, fresh = (
            label_check.label_test(
                rec, tracks, swapped, image_id, identity, others, options, 50.0, f
            )
            for f in (fit, None)
        )
        assert given[:3] == fresh[:3] and given[2] == n
        assert np.allclose(given[3].matrix(), fresh[3].matrix())
        assert given[1] < given[0]  # exchanged, the person fits better


def test_labels_exchanged_needs_a_gain_beyond_the_medians_sampling_error():
    from colmap_vc.label_check import labels_exchanged

    assert labels_exchanged(9.0, 4.5, 17, 2.0)  # half: 2.8 standard errors
    assert not labels_exchanged(9.0, 6.0, 17, 2.0)  # 2/3: 1.6
    assert labels_exchanged(9.0, 7.2, 200, 2.0)  # 0.8 on 200 keypoints: 3.2
    assert not labels_exchanged(4.0, 9.0, 17, 2.0)  # worse
    assert not labels_exchanged(np.inf, 4.0, 17, 2.0)
    assert not labels_exchanged(9.0, 4.5, 0, 2.0)


@pytest.mark.parametrize("second", ["object", "phantom"])
def test_a_person_two_images_see_is_checked_against_the_others(dome_scene, rng, second):
    """A person seen by every camera holds the model. One seen by two images is
    checked against it: a static object detected as a person (the same 3D points
    in both) fits and stays; a phantom (a different body in each image, linked
    by the association) misses and is left out."""
    from colmap_vc.people_check import check_few_view_people, unchecked_people

    rec = pycolmap.Reconstruction(dome_scene / "gt" / "sparse")
    person = rng.normal(0, 0.3, (17, 3)) * [1, 2, 1] + [0, -0.9, 0]
    held = _tracks_from_points(rec, person, rng)
    ids = sorted(rec.images)[:2]
    other = rng.normal(0, 0.3, (17, 3)) * [1, 2, 1] + [1.0, -0.9, 0.5]
    extra = _tracks_from_points(rec, other, rng)
    extra = subset(extra, np.isin(extra.image_id, ids))
    if second == "phantom":  # the second image sees another body elsewhere
        body = rng.normal(0, 0.3, (17, 3)) * [1, 2, 1] + [-1.0, -0.9, -0.5]
        moved = _tracks_from_points(rec, body, rng)
        at = extra.image_id == ids[1]
        extra.xy_img[at] = moved.xy_img[moved.image_id == ids[1]]
    n = len(person)
    tracks = KeypointTracks(
        track=np.r_[held.track, extra.track + n],
        image_id=np.r_[held.image_id, extra.image_id],
        point2D_idx=np.zeros(len(held.track) + len(extra.track), np.int64),
        xy_img=np.r_[held.xy_img, extra.xy_img],
        keys=np.stack([np.repeat([0, 1], n), np.r_[np.arange(n), np.arange(n)]], 1),
    )
    assert unchecked_people(tracks) == [1]
    kept, missed = check_few_view_people(rec, tracks, [1], 2.5, 4.0)
    if second == "object":
        assert not missed and len(kept.track) == len(tracks.track)
    else:
        assert list(missed) == [1] and missed[1] > 20
        assert (kept.keys[kept.track, 0] == 0).all()


def test_anny_keypoint_mirror_exchanges_named_pairs():
    """The 17 joints and 24 keypoints of Anny priors: left <-> right by name, the
    centre line stays; other templates have no names, hence no mirror."""
    import dataclasses

    from colmap_vc.estimators.body import anny_keypoint_mirror, anny_keypoint_names
    from colmap_vc.structs import PersonPrior
    from colmap_vc.synthetic.bodies import load_bodies

    names = anny_keypoint_names(load_bodies())
    base = PersonPrior(
        vertices_cam=np.eye(3) + np.array([0.0, 0.0, 3.0]),
        faces=np.array([[0, 1, 2]]),
        template="anny",
    )
    for k in (17, 24):
        person = dataclasses.replace(base, keypoints_xy=np.zeros((k, 2)))
        perm = anny_keypoint_mirror([person, person])
        assert sorted(perm.tolist()) == list(range(k))
        assert (perm[perm] == np.arange(k)).all()
        for i, j in enumerate(perm.tolist()):
            a, b = names[i], names[j]
            assert a == b if "left" not in a and "right" not in a else a != b
            assert a.replace("left", "right") == b or b.replace("left", "right") == a
    other = dataclasses.replace(base, template="smpl", keypoints_xy=np.zeros((17, 2)))
    person = dataclasses.replace(base, keypoints_xy=np.zeros((17, 2)))
    assert anny_keypoint_mirror([person, other]) is None


def test_the_keypoint_noise_scale_follows_the_image_resolution():
    """16 px on pose2sim's 1920-px frames; the same people in a 640-px image are
    about 5 px off, and a number given wins."""
    from colmap_vc.keypoint_tracks import loss_scale_px

    rec = pycolmap.Reconstruction()
    for width, height in ((640, 480), (640, 480), (1920, 1080)):
        rec.add_camera_with_trivial_rig(
            pycolmap.Camera(
                model="SIMPLE_PINHOLE",
                width=width,
                height=height,
                params=[500.0, width / 2, height / 2],
                camera_id=len(rec.cameras) + 1,
            )
        )
    frac = KeypointBaOptions().loss_scale_frac
    assert loss_scale_px(rec, None, frac) == pytest.approx(16.0 / 3.0)
    assert loss_scale_px(rec, 9.0, frac) == 9.0
    assert loss_scale_px(pycolmap.Reconstruction(), None, frac) == pytest.approx(16.0)


def test_gba_weights_surface_tracks_by_their_noise(dome_scene, mapped, rng):
    """`map --gba`'s refinement: every surface VC joins its track by identity
    (one point per person and template sample, seen by several images) with a
    noise from its spread and its correlation with its neighbours; the keypoints
    keep COLMAP's loss (no noise of their own); the poses come back from a 5 deg
    perturbation as with the keypoint BA."""
    db, rec = mapped
    gt = pycolmap.Reconstruction(dome_scene / "gt" / "sparse")
    perturbed = _turned(rec, rng, 5.0)
    out, summary = keypoint_bundle_adjustment(
        read_vc_records(db), perturbed, KeypointBaOptions(surface_tracks=True)
    )
    assert summary.people is not None and summary.num_surface_observations > 0
    assert summary.tracks is not None
    keypoint_obs = set(
        zip(
            summary.tracks.image_id.tolist(),
            summary.tracks.point2D_idx.tolist(),
            strict=True,
        )
    )
    weighted = {
        (i, int(k))
        for i, v in summary.people.sigma_px.items()
        for k in np.flatnonzero(np.isfinite(v))
    }
    assert len(weighted) >= summary.num_surface_observations
    assert not weighted & keypoint_obs
    sigma = np.concatenate(list(summary.people.sigma_px.values()))
    assert (sigma[np.isfinite(sigma)] > 0).all()
    views = database.read_views(db)
    first_vc = dict(
        zip(views.image_ids.tolist(), views.num_keypoints.tolist(), strict=True)
    )
    lengths = [
        len(p.track.elements)
        for p in out.points3D.values()
        if all(e.point2D_idx >= first_vc[e.image_id] for e in p.track.elements)
    ]
    assert np.median(lengths) > 2  # tracks by identity, not two-view matches
    assert evaluate_reconstruction(out, gt).median_error_deg < 1.0
