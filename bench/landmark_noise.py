"""Noise of the bundled estimator's landmarks on pose2sim, against its calibration.

The constants of the synthetic `fitted` level (colmap_vc.synthetic.fitted:
LANDMARK_SIGMA, SHARED_SIGMA) come from here. For every person view of every
instant of pose2sim_single and pose2sim_multi (the keypoint tracks by identity
that `augment` wrote into bench/realdata.py's databases), the keypoints are
triangulated with the ground-truth cameras and each observation's residual is
divided by sqrt(1 - 3 / (2n)) (what a point fitted to its own n views leaves of
the noise) and by the person's landmark height in that image (the extent in y of
its valid keypoints). Per landmark: the robust spread per coordinate around each
view's median offset; per person view: the spread of that median offset. The
composited avatar of pose2sim_multi (its landmarks within 0.2 % of its height:
a render, not a photo) is left out. Also printed: how much a surface sample's
error follows the keypoints around it (correlation with the keypoint residuals
interpolated at its pixel, Gaussian weights of 16 px), the reason the `fitted`
level exists, and the same on the accuracy bench's synthetic scenes at the
`realistic` and `fitted` levels when they are there.

    .venv/bin/python bench/landmark_noise.py  # after realdata.py (and accuracy.py)

Writes bench/out/landmark_noise.json and the table of docs/synthetic.md.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import cv2
import numpy as np
import pycolmap
from common import DOCS, OUT, machine, replace_section, setup_logging, write_json
from realdata import load_calibration

from colmap_vc import database
from colmap_vc.estimators import blazepose
from colmap_vc.estimators.body import (
    anny_keypoint_names,
    landmark_index,
    load_template,
)
from colmap_vc.gba.noise import MAD_TO_SIGMA, reprojection_residuals
from colmap_vc.keypoint_tracks import (
    KeypointTracks,
    keypoint_tracks,
    surface_tracks,
    triangulate_tracks,
)
from colmap_vc.matching import MatchingOptions
from colmap_vc.synthetic.fitted import (
    CORRELATION_2D_3D,
    LANDMARK_SIGMA,
    LANDMARK_SIGMA_3D,
    SHARED_SIGMA,
)
from colmap_vc.vc_records import read_vc_records

logger = logging.getLogger("bench.landmark_noise")

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
INSTANTS = ("t010", "t030", "t050", "t070", "t090")
SYNTHETIC = [
    f"acc_{preset}_s{seed}"
    for preset in ("dome_p1", "dome_p3", "dense_p1")
    for seed in (0, 1)
]
"""The accuracy bench's scenes whose surface-keypoint correlation is compared."""
AVATAR_FRACTION = 0.002
"""Person views whose median residual is below this fraction of their height are
a render (pose2sim_multi's composited avatar), not a detector's output."""
MIN_3D_LANDMARKS = 15
"""Person views with fewer landmarks that three calibrated views triangulate are
left out of the 3D measurement (their extent, the unit, would be a part's)."""


def gt_model(db: Path, data: Path) -> pycolmap.Reconstruction:
    """The database's images with their ground-truth poses and calibration."""
    cameras, poses = load_calibration(data)
    views = database.read_views(db)
    rec = pycolmap.Reconstruction()
    for image_id, name in zip(views.image_ids.tolist(), views.image_names, strict=True):
        c = cameras[name]
        camera = pycolmap.Camera(
            camera_id=image_id,
            model=c.model,
            width=c.width,
            height=c.height,
            params=c.params,
        )
        rec.add_camera_with_trivial_rig(camera)
        pose = poses[name]
        rec.add_image_with_trivial_frame(
            pycolmap.Image(name=name, camera_id=image_id, image_id=image_id),
            pycolmap.Rigid3d(pycolmap.Rotation3d(pose[:, :3]), pose[:, 3]),
        )
    return rec


def residuals(rec: pycolmap.Reconstruction, tracks: KeypointTracks) -> np.ndarray:
    """(O, 2) residuals against the tracks' points, corrected for their own fit."""
    X, views = triangulate_tracks(rec, tracks)
    r = reprojection_residuals(rec, tracks, X)
    n = views[tracks.track].astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        r /= np.sqrt(1.0 - 3.0 / (2.0 * n))[:, None]
    r[n < 2] = np.nan
    return r


def _view(
    tracks: KeypointTracks, res: np.ndarray, image_id: int, person: int | None
) -> tuple[np.ndarray, np.ndarray]:
    """Observations of ``person`` (None: anyone) in ``image_id`` with a residual,
    and the identity of every observation."""
    assert tracks.keys is not None
    who = tracks.keys[tracks.track, 0]
    sel = (tracks.image_id == image_id) & np.isfinite(res).all(axis=1)
    return (sel if person is None else sel & (who == person)), who[sel]


def measure(models: list[tuple[Path, pycolmap.Reconstruction]]) -> dict:
    """Landmark spreads, shared offset and the surface's correlation with the
    keypoints, over databases each with its true model (same image ids)."""
    names = anny_keypoint_names(load_template().model)
    landmarks, errors, offsets, follow = [], [], [], []
    avatar = 0
    for db, rec in models:
        ids = np.array(sorted(rec.reg_image_ids()), dtype=np.int64)
        records = read_vc_records(db)
        kp, sf = keypoint_tracks(records, ids), surface_tracks(records, ids)
        assert kp.keys is not None
        rk, rs = residuals(rec, kp), residuals(rec, sf)
        landmark = kp.keys[kp.track, 1] - MatchingOptions().num_samples
        for image_id in ids.tolist():  # loop over images
            for person in np.unique(_view(kp, rk, image_id, None)[1]).tolist():
                k = _view(kp, rk, image_id, person)[0]
                if k.sum() < 8:
                    continue
                height = float(np.ptp(kp.xy_img[k, 1]))
                r = rk[k] / height
                if np.median(np.abs(r)) < AVATAR_FRACTION:
                    avatar += 1
                    continue
                offsets.append(np.median(r, axis=0))
                landmarks.append(landmark[k])
                errors.append(r - offsets[-1])
                s = _view(sf, rs, image_id, person)[0]
                if s.sum() < 20:
                    continue
                d2 = ((sf.xy_img[s, None] - kp.xy_img[None, k]) ** 2).sum(axis=-1)
                w = np.exp(-d2 / (2.0 * 16.0**2))
                near = w.sum(axis=1) > 0.3
                interp = (w[near] @ rk[k]) / w[near].sum(axis=1)[:, None]
                follow.append(np.c_[rs[s][near], interp] / height)
    lm, err = np.concatenate(landmarks), np.concatenate(errors)
    spread, counts = {}, {}
    for k in np.unique(lm).tolist():  # loop over a few dozen landmarks
        spread[names[k]] = float(MAD_TO_SIGMA * np.median(np.abs(err[lm == k])))
        counts[names[k]] = int((lm == k).sum())
    off = np.asarray(offsets)
    median_of_independent = float(
        np.median(list(spread.values())) * 1.2533 / np.sqrt(len(spread))
    )
    pairs = np.concatenate(follow)
    inl = (np.abs(pairs) < 3 * MAD_TO_SIGMA * np.median(np.abs(pairs), axis=0)).all(1)
    a, b = pairs[inl, :2].ravel(), pairs[inl, 2:].ravel()
    return {
        "landmark_sigma": spread,
        "landmark_count": counts,
        "person_views": len(off),
        "avatar_views_left_out": avatar,
        "offset_sigma": float(MAD_TO_SIGMA * np.median(np.abs(off))),
        "offset_from_independent": median_of_independent,
        "surface_follows_keypoints": float(np.corrcoef(a, b)[0, 1]),
    }


def _kabsch(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The rotation R minimising |R a_i - b_i| (points as rows)."""
    u, _, vt = np.linalg.svd(b.T @ a)
    d = np.sign(np.linalg.det(u @ vt))
    return u @ np.diag([1.0, 1.0, d]) @ vt


def measure_3d(dbs: list[tuple[Path, Path]]) -> dict:
    """MediaPipe's 3D ("world") landmarks against the landmarks the calibrated
    cameras triangulate, in each camera's frame with the hips' midpoint as origin
    (the frame the fit reads them in): spread per landmark and axis (x, y, depth)
    as a fraction of the view's landmark extent, and how much of it one rotation
    per view explains. BlazePose runs again on each image; its person is the one
    whose 2D landmarks lie on the database person's keypoints."""
    names = anny_keypoint_names(load_template().model)
    errors: dict[str, list[np.ndarray]] = {}
    angles, turned_out, pairs_2d_3d = [], [], []
    views = avatar = 0
    with blazepose.BlazePose() as model:
        for db, data in dbs:
            rec = gt_model(db, data)
            ids = np.array(sorted(rec.reg_image_ids()), dtype=np.int64)
            kp = keypoint_tracks(read_vc_records(db), ids)
            assert kp.keys is not None
            X, seen_by = triangulate_tracks(rec, kp)
            rk = residuals(rec, kp)
            who = kp.keys[kp.track, 0]
            landmark = kp.keys[kp.track, 1] - MatchingOptions().num_samples
            for image_id in ids.tolist():  # loop over images
                image = rec.image(image_id)
                bgr = cv2.imread(str(data / "images" / image.name))
                found = blazepose.find_people(
                    model, cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
                )
                T = image.cam_from_world().matrix()
                for person in np.unique(who[kp.image_id == image_id]).tolist():
                    sel = (kp.image_id == image_id) & (who == person)
                    height = float(np.ptp(kp.xy_img[sel, 1]))
                    if np.nanmedian(np.abs(rk[sel])) / height < AVATAR_FRACTION:
                        avatar += 1
                        continue
                    sel &= seen_by[kp.track] >= 3
                    nm = [names[k] for k in landmark[sel]]
                    if len(nm) < MIN_3D_LANDMARKS or not {
                        "left_hip",
                        "right_hip",
                    } <= set(nm):
                        continue
                    idx = np.array([landmark_index(n) for n in nm])
                    gap = [
                        float(
                            np.median(
                                np.linalg.norm(
                                    r.landmarks.xy_img[idx] - kp.xy_img[sel], axis=1
                                )
                            )
                        )
                        for r in found
                    ]
                    if not gap or min(gap) > 0.05 * height:
                        continue
                    hips = [nm.index("left_hip"), nm.index("right_hip")]
                    world = X[kp.track[sel]] @ T[:, :3].T + T[:, 3]  # camera frame
                    truth = world - world[hips].mean(axis=0)
                    match = found[int(np.argmin(gap))].landmarks
                    mp = match.points_3d[idx] - match.points_3d[idx][hips].mean(axis=0)
                    extent = float(np.ptp(truth, axis=0).max())
                    R = _kabsch(mp, truth)
                    angles.append(
                        float(
                            np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1)))
                        )
                    )
                    turned_out.append((mp @ R.T - truth) / extent)
                    # The same landmarks' 2D error (against the truth projected),
                    # beside the 3D one across the image: each less its view's median.
                    projected = rec.camera(image.camera_id).img_from_cam(world)
                    e2 = (match.xy_img[idx] - projected) / height
                    e3 = (mp - truth)[:, :2] / extent
                    pairs_2d_3d.append(
                        np.c_[e2 - np.median(e2, axis=0), e3 - np.median(e3, axis=0)]
                    )
                    for n, e in zip(nm, (mp - truth) / extent, strict=True):
                        errors.setdefault(n, []).append(e)
                    views += 1
    spread = {
        n: (MAD_TO_SIGMA * np.median(np.abs(np.array(e)), axis=0)).tolist()
        for n, e in errors.items()
    }
    every = np.concatenate([np.array(e) for e in errors.values()])
    both = np.concatenate(pairs_2d_3d)
    spreads = MAD_TO_SIGMA * np.median(np.abs(both), axis=0)
    inl = (np.abs(both) <= 3.0 * spreads).all(axis=1)  # a wild landmark is not noise
    follow = [float(np.corrcoef(both[inl, a], both[inl, 2 + a])[0, 1]) for a in (0, 1)]
    rotated = np.concatenate(turned_out)
    return {
        "landmark_sigma_3d": spread,
        "landmark_count_3d": {n: len(e) for n, e in errors.items()},
        "person_views_3d": views,
        "avatar_views_left_out_3d": avatar,
        "sigma_3d_all": (MAD_TO_SIGMA * np.median(np.abs(every), axis=0)).tolist(),
        "sigma_3d_after_rotation": (
            MAD_TO_SIGMA * np.median(np.abs(rotated), axis=0)
        ).tolist(),
        "rotation_deg_quartiles": np.quantile(angles, [0.25, 0.5, 0.75]).tolist(),
        "correlation_2d_3d": follow,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--runs", type=Path, default=OUT / "realdata")
    parser.add_argument("--no-docs", action="store_true")
    args = parser.parse_args()
    setup_logging()
    dbs = []
    for ds in ("single", "multi"):
        for t in INSTANTS:
            db = args.runs / ds / t / "order0" / "database.db"
            if not db.exists():
                raise SystemExit(f"{db} is missing: run bench/realdata.py first")
            dbs.append((db, args.data / f"pose2sim_{ds}"))
    out = measure([(db, gt_model(db, data)) for db, data in dbs])
    out.update(measure_3d(dbs))
    synthetic = {}
    for level in ("realistic", "fitted"):
        scenes = [
            (
                OUT / "runs" / "accuracy" / s / level / "augmented_classic0.db",
                OUT / "scenes" / s / "gt" / "sparse",
            )
            for s in SYNTHETIC
        ]
        if all(db.exists() for db, _ in scenes):
            synthetic[level] = measure(
                [(db, pycolmap.Reconstruction(gt)) for db, gt in scenes]
            )["surface_follows_keypoints"]
    out["synthetic_surface_follows_keypoints"] = synthetic
    shared = float(
        np.sqrt(max(out["offset_sigma"] ** 2 - out["offset_from_independent"] ** 2, 0))
    )
    out["shared_sigma"] = shared
    write_json("landmark_noise.json", {"machine": machine(), **out})
    rows = [
        "| landmark | 2D measured | `LANDMARK_SIGMA` | views "
        "| 3D measured (x / y / depth) | `LANDMARK_SIGMA_3D` | views |",
        "|---|---|---|---|---|---|---|",
    ]

    def xyz(v: list[float] | tuple[float, ...] | None) -> str:
        return "-" if v is None else " / ".join(f"{100 * a:.1f}%" for a in v)

    for name, s in out["landmark_sigma"].items():
        rows.append(
            f"| {name} | {100 * s:.1f}% | {100 * LANDMARK_SIGMA.get(name, np.nan):.1f}%"
            f" | {out['landmark_count'][name]}"
            f" | {xyz(out['landmark_sigma_3d'].get(name))}"
            f" | {xyz(LANDMARK_SIGMA_3D.get(name))}"
            f" | {out['landmark_count_3d'].get(name, 0)} |"
        )
    body = "\n".join(
        [
            f"Measured by `.venv/bin/python bench/landmark_noise.py` at commit "
            f"{machine()['commit']} over {out['person_views']} person views of "
            f"pose2sim_single and pose2sim_multi ({out['avatar_views_left_out']} "
            "views of the composited avatar left out). 2D: spread per coordinate, "
            "as a fraction of the person's landmark height in the image. 3D: "
            "MediaPipe's world landmarks against the landmarks the calibrated "
            "cameras triangulate (three views or more), per camera axis with the "
            "hips' midpoint as origin, as a fraction of the view's landmark extent "
            f"({out['person_views_3d']} person views with at least "
            f"{MIN_3D_LANDMARKS} such landmarks):",
            "",
            *rows,
            "",
            f"Per person view, the median offset of its landmarks spreads "
            f"{100 * out['offset_sigma']:.2f}%, of which independent landmark "
            f"errors explain {100 * out['offset_from_independent']:.2f}%: a shared "
            f"offset of {100 * shared:.2f}% (`SHARED_SIGMA` = "
            f"{100 * SHARED_SIGMA:.2f}%). A surface sample's error correlates "
            f"{out['surface_follows_keypoints']:.2f} with the keypoint errors "
            "interpolated at its pixel (16 px Gaussian weights)"
            + (
                "; on the accuracy bench's domes and dense scenes (seeds 0 and 1) "
                + " and ".join(
                    f"{v:.2f} with `{k}` priors" for k, v in synthetic.items()
                )
                if synthetic
                else ""
            )
            + ".",
            "",
            "In 3D, all landmarks together spread "
            f"{xyz(out['sigma_3d_all'])} (x / y / depth); the rotation that "
            "best aligns each view's world landmarks with the truth (median "
            f"{out['rotation_deg_quartiles'][1]:.0f} deg, quartiles "
            f"{out['rotation_deg_quartiles'][0]:.0f}-"
            f"{out['rotation_deg_quartiles'][2]:.0f}) leaves "
            f"{xyz(out['sigma_3d_after_rotation'])}: the error is the landmarks' "
            "own, mostly in depth, not one turn of the body. Across the image it "
            "follows the same landmark's 2D error: correlation "
            f"{out['correlation_2d_3d'][0]:.2f} in x and "
            f"{out['correlation_2d_3d'][1]:.2f} in y (each view's median "
            "offset taken out; `CORRELATION_2D_3D` = "
            f"{CORRELATION_2D_3D[0]:.2f}, {CORRELATION_2D_3D[1]:.2f}).",
        ]
    )
    print(body)
    if not args.no_docs:
        replace_section(DOCS / "synthetic.md", "landmark-noise", body)


if __name__ == "__main__":
    main()
