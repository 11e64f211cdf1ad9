"""The generalized BA's engine (COLMAP's Ceres problem with weighted observations)
and its noise model."""

from __future__ import annotations

import dataclasses

import numpy as np
import pycolmap
import pytest

from colmap_vc.evaluation import evaluate_reconstruction
from colmap_vc.gba import repeats
from colmap_vc.gba.ceres import PeopleNoise, bundle_adjust_inplace, weighted_points
from colmap_vc.gba.correlated import correlated_noise
from colmap_vc.gba.noise import cluster_noise, reprojection_residuals
from colmap_vc.gba.repeats import repeat_design
from colmap_vc.keypoint_tracks import KeypointTracks, triangulate_tracks


def _observed(gt: pycolmap.Reconstruction, X: np.ndarray, noise: dict[int, float], rng):
    """A copy of ``gt`` whose points are X, seen by every image with Gaussian pixel
    noise of noise[image_id] (default 0.3 px); -> (model, tracks)."""
    rec = pycolmap.Reconstruction(gt)
    for point_id in list(rec.point3D_ids()):
        rec.delete_point3D(point_id)
    track, image_id, xy = [], [], []
    for i in sorted(rec.reg_image_ids()):
        image = rec.image(i)
        T = image.cam_from_world().matrix()
        uv = np.asarray(
            rec.camera(image.camera_id).img_from_cam(X @ T[:, :3].T + T[:, 3])
        )
        uv = uv + rng.normal(0, noise.get(i, 0.3), uv.shape)
        image.points2D = pycolmap.Point2DList([pycolmap.Point2D(p) for p in uv])
        track.append(np.arange(len(X)))
        image_id.append(np.full(len(X), i))
        xy.append(uv)
    for k in range(len(X)):
        t = pycolmap.Track()
        for i in sorted(rec.reg_image_ids()):
            t.add_element(i, k)
        rec.add_point3D(X[k], t)
    t, im, p = (np.concatenate(a) for a in (track, image_id, xy))
    order = np.argsort(t, kind="stable")
    tracks = KeypointTracks(
        track=t[order],
        image_id=im[order],
        point2D_idx=t[order],
        xy_img=p[order],
        keys=np.stack([np.zeros(len(X), np.int64), np.arange(len(X))], axis=1),
    )
    return rec, tracks


def _other_residuals(rec, tracks, bad: int) -> np.ndarray:
    X = np.array([rec.point3D(k + 1).xyz for k in range(tracks.num_tracks)])
    res = np.linalg.norm(reprojection_residuals(rec, tracks, X), axis=1)
    return res[tracks.image_id != bad]


def test_weighted_observations_follow_their_noise(dome_scene, rng):
    """One image's observations are 12 px off: weighted by that noise they no
    longer drag the points, and the other images keep their sub-pixel fit; under
    one (near least-squares) loss they drag them."""
    gt = pycolmap.Reconstruction(dome_scene / "gt" / "sparse")
    X = rng.normal(0, 0.4, (80, 3)) * [1, 2, 1] + [0, -0.9, 0]
    bad = sorted(gt.reg_image_ids())[0]
    rec, tracks = _observed(gt, X, {bad: 12.0}, rng)
    plain = pycolmap.Reconstruction(rec)
    bundle_adjust_inplace(plain, 1000.0)
    sigma = {
        i: np.full(rec.image(i).num_points2D(), 12.0 if i == bad else 0.3)
        for i in rec.reg_image_ids()
    }
    weighted = pycolmap.Reconstruction(rec)
    people = PeopleNoise(sigma_px=sigma, robust_px={i: 3 * v for i, v in sigma.items()})
    bundle_adjust_inplace(weighted, 1000.0, people)
    r_plain = np.median(_other_residuals(plain, tracks, bad))
    r_weighted = np.median(_other_residuals(weighted, tracks, bad))
    assert r_weighted < 0.6 and r_weighted < 0.5 * r_plain
    assert evaluate_reconstruction(weighted, gt).median_error_deg < 0.1


def test_a_point_is_the_peoples_only_when_every_view_has_a_noise(dome_scene, rng):
    """A point with one observation without a noise (NaN: a classic keypoint in
    one view) stays under COLMAP's loss; one in an image without noises too; the
    others are weighted, in id order."""
    gt = pycolmap.Reconstruction(dome_scene / "gt" / "sparse")
    X = rng.normal(0, 0.4, (40, 3)) * [1, 2, 1] + [0, -0.9, 0]
    rec, _ = _observed(gt, X, {}, rng)
    ids = sorted(rec.reg_image_ids())
    sigma = {i: np.full(rec.image(i).num_points2D(), 0.3) for i in ids[1:]}
    sigma[ids[1]][4] = np.nan  # point 5's view in the second image
    people = PeopleNoise(sigma_px=sigma, robust_px=sigma)
    assert weighted_points(rec, people) == []  # the first image has no noises
    sigma[ids[0]] = np.full(rec.image(ids[0]).num_points2D(), 0.3)
    assert weighted_points(rec, people) == [k for k in range(1, 41) if k != 5]
    bundle_adjust_inplace(rec, 1.0, people)
    assert evaluate_reconstruction(rec, gt).median_error_deg < 0.2


def test_weighted_bundle_adjustment_recovers_perturbed_poses(dome_scene, rng):
    """Poses turned by 2 deg come back through the weighted costs (the model's pose
    blocks, shared with COLMAP's problem by address): to the optimum the same
    adjustment reaches from the true poses."""
    gt = pycolmap.Reconstruction(dome_scene / "gt" / "sparse")
    X = rng.normal(0, 0.4, (60, 3)) * [1, 2, 1] + [0, -0.9, 0]
    rec, _ = _observed(gt, X, {}, rng)
    sigma = {i: np.full(rec.image(i).num_points2D(), 0.3) for i in rec.reg_image_ids()}
    people = PeopleNoise(sigma_px=sigma, robust_px={i: 3 * v for i, v in sigma.items()})
    optimum = pycolmap.Reconstruction(rec)
    bundle_adjust_inplace(optimum, 1.0, people)
    for image in rec.images.values():
        w = rng.normal(size=3)
        dR = pycolmap.Rotation3d(w / np.linalg.norm(w) * np.deg2rad(2.0)).matrix()
        T = image.cam_from_world().matrix()
        rec.frame(image.frame_id).rig_from_world = pycolmap.Rigid3d(
            pycolmap.Rotation3d(dR @ T[:, :3]), T[:, 3]
        )
    assert evaluate_reconstruction(rec, gt).median_error_deg > 1.0
    bundle_adjust_inplace(rec, 1.0, people)
    assert evaluate_reconstruction(rec, optimum).p80_error_deg < 0.01
    assert evaluate_reconstruction(rec, gt).median_error_deg < 0.2


def _behind(rec: pycolmap.Reconstruction) -> int:
    """The observations behind their camera."""
    behind = 0
    for point in rec.points3D.values():
        for el in point.track.elements:
            behind += (rec.image(el.image_id).cam_from_world() * point.xyz)[2] < 0
    return int(behind)


@pytest.mark.parametrize("weighted", [False, True])
def test_a_model_behind_its_cameras_comes_back_in_front(dome_scene, rng, weighted):
    """The point reflection of a model (points and camera centres through the
    origin, rotations kept) has the same reprojection errors with every point
    behind every camera: a bundle adjustment ending there (as one did from a poor
    start on pose2sim) reflects it back, both through COLMAP's costs and through
    the weighted ones; the poses are the truth's, translations included."""
    gt = pycolmap.Reconstruction(dome_scene / "gt" / "sparse")
    X = rng.normal(0, 0.4, (60, 3)) * [1, 2, 1] + [0, -0.9, 0]
    rec, _ = _observed(gt, X, {}, rng)
    total, before = rec.compute_num_observations(), _behind(rec)
    rec.transform(pycolmap.Sim3d(-1.0, pycolmap.Rotation3d(), np.zeros(3)))
    assert _behind(rec) == total - before > total / 2
    assert evaluate_reconstruction(rec, gt).median_error_deg > 170  # translations
    sigma = {i: np.full(rec.image(i).num_points2D(), 0.3) for i in rec.reg_image_ids()}
    people = PeopleNoise(sigma_px=sigma, robust_px={i: 3 * v for i, v in sigma.items()})
    bundle_adjust_inplace(rec, 1.0, people if weighted else None)
    assert _behind(rec) == before
    assert evaluate_reconstruction(rec, gt).median_error_deg < 0.2


@pytest.mark.parametrize("turn_deg", [0.0, 1.5])
def test_cluster_noise_separates_shared_and_own_error(dome_scene, rng, turn_deg):
    """Pixels = the projection by a camera turned by ``turn_deg`` (the shared
    error of a body predicted turned: every point of the person moves together)
    + independent noise sigma, against points triangulated from them: both come
    back per cluster."""
    gt = pycolmap.Reconstruction(dome_scene / "gt" / "sparse")
    X = rng.normal(0, 0.2, (400, 3)) * [1, 2, 1] + [0, -0.9, 0]  # a body
    sigma = 2.0
    rec, tracks = _observed(gt, X, dict.fromkeys(gt.reg_image_ids(), 0.0), rng)
    xy = tracks.xy_img.copy()
    moved_all = xy.copy()
    for i in np.unique(tracks.image_id):
        sel = tracks.image_id == i
        image = rec.image(int(i))
        w = rng.normal(size=3)
        dR = pycolmap.Rotation3d(w / np.linalg.norm(w) * np.deg2rad(turn_deg))
        T = image.cam_from_world().matrix()
        Xc = X[tracks.track[sel]] @ T[:, :3].T + T[:, 3]
        moved = np.asarray(rec.camera(image.camera_id).img_from_cam(Xc @ dR.matrix().T))
        moved_all[sel] = moved
        xy[sel] = moved + rng.normal(0, sigma, moved.shape)

    def with_pixels(pixels: np.ndarray) -> KeypointTracks:
        return dataclasses.replace(tracks, xy_img=pixels)

    noisy = with_pixels(xy)
    noise = cluster_noise(rec, noisy, triangulate_tracks(rec, noisy)[0])
    assert len(noise.count) == rec.num_reg_images()
    # With turned cameras the points carry the other views' turns, which no motion
    # of one camera explains: a little of it stays in the spread.
    assert np.allclose(noise.sigma_px, sigma, rtol=0.2 if turn_deg == 0 else 0.25)
    if turn_deg == 0:
        assert (noise.tau_px < 0.3 * sigma).all()
    else:
        # The shared error against the points all views triangulate: the field
        # of the turns alone, measured the same way without noise.
        turned = with_pixels(moved_all)
        alone = cluster_noise(rec, turned, triangulate_tracks(rec, turned)[0])
        assert np.median(alone.tau_px) > 2 * sigma
        assert np.allclose(noise.tau_px, alone.tau_px, rtol=0.15, atol=0.5)
    per_obs = noise.observation_sigma_px(0.5)
    expected = np.sqrt(noise.sigma_px**2 + noise.count * noise.tau_px**2)
    assert np.allclose(per_obs, expected[noise.cluster])


def _smooth_field(xy: np.ndarray, wavelength_px: float, rng) -> np.ndarray:
    """(N, 2) a random smooth error field at the pixels ``xy``, unit standard
    deviation per coordinate: 16 plane waves of the given wavelength."""
    k = 16
    out = np.zeros_like(xy)
    for c in range(2):  # loop over the two coordinates
        u = rng.normal(size=(k, 2))
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        phase = rng.uniform(0, 2 * np.pi, k)
        out[:, c] = np.sqrt(2.0 / k) * np.cos(
            2 * np.pi / wavelength_px * xy @ u.T + phase
        ).sum(axis=1)
    return out


def _with_error(tracks: KeypointTracks, error) -> KeypointTracks:
    """``tracks`` with ``error(image_xy)`` (N, 2) added image by image."""
    xy = tracks.xy_img.copy()
    for i in np.unique(tracks.image_id):
        sel = tracks.image_id == i
        xy[sel] += error(xy[sel])
    return dataclasses.replace(tracks, xy_img=xy)


def test_correlated_noise_counts_the_neighbours_that_share_an_error(dome_scene, rng):
    """Independent pixel noise: the spread comes back and each observation counts
    about once. Errors that slide neighbouring pixels together: the correlation
    falls with distance, and each observation counts as a share of its
    neighbourhood, the larger the longer the error's wavelength."""
    gt = pycolmap.Reconstruction(dome_scene / "gt" / "sparse")
    X = rng.normal(0, 0.15, (400, 3)) * [1, 3, 1] + [0, -0.9, 0]  # a body
    rec, clean = _observed(gt, X, dict.fromkeys(gt.reg_image_ids(), 0.0), rng)
    design = {}
    for name, error in (
        ("independent", lambda xy: rng.normal(0, 2.0, xy.shape)),
        ("short", lambda xy: 2.0 * _smooth_field(xy, 40.0, rng)),
        ("long", lambda xy: 2.0 * _smooth_field(xy, 400.0, rng)),
    ):
        noisy = _with_error(clean, error)
        noise = correlated_noise(rec, noisy, triangulate_tracks(rec, noisy)[0])
        assert len(noise.sigma_px) == rec.num_reg_images()
        assert (noise.cluster >= 0).all()
        assert noise.rho[0] == 1.0 and (np.diff(noise.rho) <= 0).all()
        design[name] = float(np.median(noise.design))
        if name == "independent":
            assert np.allclose(noise.sigma_px, 2.0, rtol=0.2)
            # bins of a few close pairs read as the closest (1); measured ones ~0
            assert noise.rho[noise.bin_edges_px[:-1] >= 8.0].max() < 0.1
        per_obs = noise.observation_sigma_px(0.5)
        spread = noise.observation_spread_px(0.5)
        assert np.allclose(per_obs, spread * np.sqrt(noise.design))
    assert design["independent"] < 3.0
    assert design["short"] > 2 * design["independent"]
    assert design["long"] > 2 * design["short"]
    assert design["long"] > 0.3 * len(X)


def test_shared_errors_weighted_by_their_correlation_move_no_camera(dome_scene, rng):
    """In every image all surface samples slide by one 6 px vector of their own
    (a body map shifted as a whole), the 17 keypoints are right to 0.5 px:
    weighted as independent observations the samples pull the cameras; weighted
    by their design effect, relative to the keypoints as the GBA does, each
    image's samples count as about one observation and the cameras stay where
    the keypoints alone put them."""
    gt = pycolmap.Reconstruction(dome_scene / "gt" / "sparse")
    body = rng.normal(0, 0.15, (417, 3)) * [1, 3, 1] + [0, -0.9, 0]
    rec, clean = _observed(gt, body, dict.fromkeys(gt.reg_image_ids(), 0.5), rng)
    surface = clean.track >= 17  # 17 keypoints, 400 surface samples
    shifts = {i: rng.normal(size=2) for i in rec.reg_image_ids()}
    shift = np.array(
        [6.0 * shifts[i] / np.linalg.norm(shifts[i]) for i in clean.image_id]
    )
    shift[~surface] = 0.0
    for i in rec.reg_image_ids():  # the model's pixels carry the shift too
        sel = clean.image_id == i
        for idx, xy in zip(
            clean.point2D_idx[sel].tolist(), clean.xy_img[sel] + shift[sel], strict=True
        ):
            rec.image(i).points2D[idx].xy = xy
    tracks = KeypointTracks(
        track=clean.track[surface] - 17,
        image_id=clean.image_id[surface],
        point2D_idx=clean.point2D_idx[surface],
        xy_img=clean.xy_img[surface] + shift[surface],
        keys=clean.keys[17:],
    )
    noise = correlated_noise(rec, tracks, triangulate_tracks(rec, tracks)[0])
    assert np.median(noise.design) > 0.5 * 400
    errors = {}
    for name, sigma_obs in (
        ("independent", np.full(len(tracks.track), 0.5)),
        ("correlated", noise.observation_sigma_px(0.5)),
        ("keypoints alone", np.full(len(tracks.track), 1e3)),
    ):
        sigma = {
            i: np.full(rec.image(i).num_points2D(), np.nan) for i in rec.reg_image_ids()
        }
        for i in sigma:
            sel = tracks.image_id == i
            sigma[i][tracks.point2D_idx[sel]] = sigma_obs[sel] / 0.5  # keypoint units
        robust = {i: np.where(np.isfinite(v), 100.0, np.nan) for i, v in sigma.items()}
        adjusted = pycolmap.Reconstruction(rec)
        bundle_adjust_inplace(
            adjusted, 1000.0, PeopleNoise(sigma_px=sigma, robust_px=robust)
        )
        errors[name] = evaluate_reconstruction(adjusted, gt).median_error_deg
    alone = errors["keypoints alone"]
    assert errors["independent"] > 1.3 * alone
    assert abs(errors["correlated"] - alone) < 0.1 * alone


def test_the_adjustment_stops_once_the_cost_no_longer_changes(monkeypatch):
    """COLMAP's options set no function tolerance, so its adjustments iterate until
    the gradient tolerance or 100 iterations; colmap-vc's stop when an iteration
    gains less than FUNCTION_TOLERANCE of the cost, at poses the full solve moves
    by far less than their noise (1 px at f = 1280 over 600 points, ~0.003 deg)."""
    from colmap_vc.gba import ceres

    pycolmap.set_random_seed(0)
    options = pycolmap.SyntheticDatasetOptions(
        num_rigs=1,
        num_cameras_per_rig=1,
        num_frames_per_rig=12,
        num_points3D=600,
        camera_model_id=pycolmap.CameraModelId.PINHOLE,
        camera_params=[1280.0, 1280.0, 512.0, 384.0],
    )
    rec = pycolmap.synthesize_dataset(options)
    rng = np.random.default_rng(0)
    for image in rec.images.values():  # loop over images: 1 px of noise
        for p in image.points2D:
            p.xy = p.xy + rng.normal(0.0, 1.0, 2)
    for frame in rec.frames.values():  # loop over frames: perturbed poses
        T = frame.rig_from_world
        turn = pycolmap.Rotation3d(rng.normal(0.0, 0.01, 3))
        frame.rig_from_world = pycolmap.Rigid3d(
            turn * T.rotation, T.translation + rng.normal(0.0, 0.05, 3)
        )
    solved = {}
    for tolerance in (ceres.FUNCTION_TOLERANCE, 0.0):
        monkeypatch.setattr(ceres, "FUNCTION_TOLERANCE", tolerance)
        r = pycolmap.Reconstruction(rec)
        summary = bundle_adjust_inplace(r, 2.0)
        solved[tolerance] = (r, summary)
    (early, stop), (full, run) = solved.values()
    assert stop.message.startswith("Function tolerance reached"), stop.message
    iterations = stop.num_successful_steps + stop.num_unsuccessful_steps
    assert 2 * iterations < run.num_successful_steps + run.num_unsuccessful_steps
    assert stop.final_cost <= run.final_cost * (1 + 1e-5)
    for image_id in rec.reg_image_ids():  # loop over images
        a = early.image(image_id).cam_from_world()
        b = full.image(image_id).cam_from_world()
        assert np.degrees((a.rotation * b.rotation.inverse()).angle()) < 1e-3


def _landmarks(
    xy: np.ndarray, identity: np.ndarray, landmark: np.ndarray
) -> KeypointTracks:
    """One image's keypoints: row k is ``landmark[k]`` of ``identity[k]``."""
    keys, track = np.unique(
        np.stack([identity, landmark], axis=1), axis=0, return_inverse=True
    )
    order = np.argsort(track.ravel(), kind="stable")
    return KeypointTracks(
        track=track.ravel()[order],
        image_id=np.ones(len(xy), np.int64),
        point2D_idx=np.arange(len(xy))[order],
        xy_img=xy[order],
        keys=keys,
    )


def test_a_person_who_stood_still_counts_once_and_one_who_moved_fully():
    """Identity 0-2: one still person at three instants (the same pixels);
    identity 3-4: a person who moved 100 px between two instants; identity 5: a
    second person at the first instant on the first's pixels; identity 6: not a
    static camera's."""
    rng = np.random.default_rng(0)
    base = rng.uniform(0, 500, (4, 2))
    xy = np.concatenate([base, base, base, base + 300, base + 400, base, base])
    identity = np.repeat(np.arange(7), 4)
    instant_of = {0: "t1", 1: "t2", 2: "t3", 3: "t1", 4: "t2", 5: "t1"}
    landmark = np.tile(np.arange(4), 7)
    tracks = _landmarks(xy, identity, landmark)
    m = repeat_design(tracks, instant_of, sigma_px=10.0)
    who = tracks.keys[tracks.track, 0]
    # The still person's 3 instants: m = 3 (and the same-instant person 5 adds
    # to instants 1 and 2 only: person 0's instant is its own).
    assert np.allclose(m[who == 0], 3.0)
    assert np.allclose(m[np.isin(who, [1, 2])], 4.0)
    assert np.allclose(m[who == 5], 3.0)
    assert np.allclose(m[np.isin(who, [3, 4, 6])], 1.0)
    # Two instants at distance d: 1 + (1 - d^2 / (4 sigma^2)).
    two = _landmarks(
        np.array([[0.0, 0.0], [0, 0], [0, 0], [0, 0], [6, 8], [0, 0], [0, 0], [0, 0]]),
        np.repeat([0, 1], 4),
        np.tile(np.arange(4), 2),
    )
    m2 = repeat_design(two, {0: "a", 1: "b"}, sigma_px=10.0)
    assert np.isclose(m2[two.point2D_idx == 0][0], 1.0 + 1.0 - 100.0 / 400.0)
    # The same keypoints in another order: the same design effect each.
    perm = rng.permutation(len(xy))
    again = _landmarks(xy[perm], identity[perm], landmark[perm])
    m_again = repeat_design(again, instant_of, sigma_px=10.0)
    by_row = dict(zip(perm[again.point2D_idx].tolist(), m_again.tolist(), strict=True))
    assert np.allclose([by_row[k] for k in tracks.point2D_idx.tolist()], m)


def test_repeats_compared_in_chunks_give_the_same_design(monkeypatch):
    """Many instants are compared a chunk of (image, landmark) groups at a time:
    the same design effects as all at once."""
    rng = np.random.default_rng(2)
    n = 300
    xy = rng.uniform(0, 60, (n, 2))
    identity = rng.integers(0, 40, n)
    landmark = rng.integers(0, 3, n)
    tracks = _landmarks(xy, identity, landmark)
    instant_of = {i: f"t{i % 7}" for i in range(40)}
    whole = repeat_design(tracks, instant_of, sigma_px=10.0)
    monkeypatch.setattr(repeats, "MAX_PAIRS", 50)
    assert np.allclose(repeat_design(tracks, instant_of, sigma_px=10.0), whole)
    assert (whole > 1.5).any()


@pytest.mark.parametrize(("sd_b", "sd_u"), [(9.0, 3.0), (5.0, 5.0), (0.0, 5.0)])
def test_the_correlation_from_distance_is_the_bias_share_of_the_noise(sd_b, sd_u):
    """Errors e_t = b + u_t of a still person's landmark: two instants' errors
    correlate by rho = var(b) / sigma^2, what 1 - d^2 / (4 sigma^2) estimates
    from their pixel distance d (module doc of gba.repeats). Clipped at 0, its
    mean is 1 - (1 - rho)(1 - exp(-1 / (1 - rho))): rho where the bias dominates,
    above it where the jitter does (1/e for independent errors, which then
    weigh less than they could, none wrongly)."""
    rng = np.random.default_rng(1)
    n = 4000
    sigma = np.hypot(sd_b, sd_u)
    b = rng.normal(0, sd_b, (n, 2))
    xy = np.concatenate(
        [b + rng.normal(0, sd_u, (n, 2)), b + rng.normal(0, sd_u, (n, 2))]
    )
    # Landmark per row: n landmarks of two identities (two instants).
    keys = np.stack([np.repeat([0, 1], n), np.tile(np.arange(n), 2)], axis=1)
    order = np.argsort(np.arange(2 * n), kind="stable")
    tracks = KeypointTracks(
        track=order,
        image_id=np.ones(2 * n, np.int64),
        point2D_idx=order,
        xy_img=xy,
        keys=keys,
    )
    m = repeat_design(tracks, {0: "a", 1: "b"}, sigma_px=float(sigma))
    rho = sd_b**2 / sigma**2
    expected = 1.0 - (1.0 - rho) * (1.0 - np.exp(-1.0 / (1.0 - rho)))
    assert abs(np.mean(m - 1.0) - expected) < 0.015
