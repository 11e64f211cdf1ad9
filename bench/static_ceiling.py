"""What limits static cameras on pose2sim: the keypoints' own optimum, not the search.

Reads the databases and `map --no-gravity` models `bench/static_cameras.py` left
(static cameras, all instants; `map`'s own up directions from the scene's vertical
lines are what this bench shows the need for) and bundle-adjusts the same keypoint
tracks by identity (COLMAP's BA, the keypoint BA's Cauchy loss, no surface VCs, no
camera check) from two starts: that model and the calibration itself. When both
converge to the same poses, the error left is where the keypoints' least-squares
optimum lies: no mapper, initialisation or solver change can remove it; only other
evidence or another weighting can. The same two with the keypoints weighted by
their repeated errors, as `map` weighs them (colmap_vc/gba/repeats.py: a person
who stood still counts about once). Then the same from the calibration with one
camera left out, with groups of landmarks left out (which kinds of landmark pull
the optimum away), and with one labelled person's keypoints alone, left out, or at
one of the instants only (tests/data/pose2sim_people.json: the real man, on
pose2sim_multi the composited avatar, and the bystander of cam01 and cam02).

Also reported: each camera's rotation residual after the best common rotation of
the model onto the calibration, in the camera's own axes (x right, y down, z
forward), and the keypoints' median reprojection error at the optimum and at the
calibration.

    .venv/bin/python bench/static_ceiling.py   # after bench/static_cameras.py

Writes bench/out/static_ceiling.json and the "ceiling" section of docs/results.md.
"""

from __future__ import annotations

import argparse
import json
import logging
from collections import Counter
from pathlib import Path

import numpy as np
import pycolmap
from common import DOCS, OUT, machine, replace_section, setup_logging, write_json
from realdata import LABELS, SHARED, load_calibration, person_labels
from scipy.spatial.transform import Rotation

from colmap_vc import database
from colmap_vc.estimators.blazepose import FEET_NAMES
from colmap_vc.estimators.body import anny_keypoint_names
from colmap_vc.evaluation import evaluate_poses
from colmap_vc.gba.ceres import bundle_adjust_inplace
from colmap_vc.gba.repeats import keypoint_sigma_px, repeat_noise
from colmap_vc.keypoint_ba import KeypointBaOptions, with_loss_scale
from colmap_vc.keypoint_tracks import (
    KeypointTracks,
    add_keypoint_points,
    keypoint_tracks,
    subset,
    triangulate_tracks,
)
from colmap_vc.mapping.inputs import read_inputs
from colmap_vc.mapping.options import MappingOptions
from colmap_vc.priors import read_priors
from colmap_vc.static_cameras import parse_static_cameras
from colmap_vc.synthetic import bodies
from colmap_vc.vc_records import person_identities, read_vc_records

logger = logging.getLogger("bench.static_ceiling")

FROM_GT = "keypoint tracks, from the calibration"
GROUPS = {
    "face (nose, ears)": ("nose", "left_ear", "right_ear"),
    "hips": ("left_hip", "right_hip"),
    "shoulders": ("left_shoulder", "right_shoulder"),
    "elbows and wrists": ("left_elbow", "right_elbow", "left_wrist", "right_wrist"),
    "knees": ("left_knee", "right_knee"),
    "ankles and feet": FEET_NAMES,
}
PEOPLE = {  # rows: a hand label's keypoints alone, all but theirs, or one instant
    "the man's keypoints alone": ("man", "alone"),
    "the avatar's keypoints alone": ("woman", "alone"),
    "without the avatar": ("woman", "without"),
    "the man at one instant only": ("man", "once"),
    "the avatar at one instant only": ("woman", "once"),
    "the bystander at one instant only": ("bystander", "once"),
}
PATTERN = r"(cam\d+)_"  # bench/static_cameras.py's


def camera_of(name: str) -> str:
    return name.split("_")[0]


def posed_copy(
    rec: pycolmap.Reconstruction,
    keep: set[int],
    poses: dict[str, np.ndarray] | None,
) -> pycolmap.Reconstruction:
    """``rec`` with only the images ``keep`` registered and no points; their poses
    from ``poses`` (by image name) when given."""
    out = pycolmap.Reconstruction(rec)
    for point_id in list(out.point3D_ids()):
        out.delete_point3D(point_id)
    for image_id in list(out.reg_image_ids()):
        if image_id not in keep:
            out.deregister_frame(out.image(image_id).frame_id)
    for image_id in keep if poses is not None else ():
        T = poses[out.image(image_id).name]  # type: ignore[index]
        out.frame(out.image(image_id).frame_id).rig_from_world = pycolmap.Rigid3d(
            pycolmap.Rotation3d(T[:, :3]), T[:, 3]
        )
    return out


def reprojection_px(rec: pycolmap.Reconstruction, tracks: KeypointTracks) -> float:
    """Median reprojection error of the tracks, triangulated with ``rec``'s poses."""
    X, _ = triangulate_tracks(rec, tracks)
    errors = []
    for image_id in np.unique(tracks.image_id):  # loop over images
        if not rec.image(int(image_id)).has_pose:
            continue
        sel = tracks.image_id == image_id
        image = rec.image(int(image_id))
        Xw = X[tracks.track[sel]]
        ok = np.isfinite(Xw).all(axis=1)
        Xc = Xw[ok] @ image.cam_from_world().matrix()[:, :3].T
        Xc += image.cam_from_world().matrix()[:, 3]
        xy = np.asarray(rec.camera(image.camera_id).img_from_cam(Xc))
        errors.append(np.linalg.norm(xy - tracks.xy_img[sel][ok], axis=1))
    return float(np.median(np.concatenate(errors)))


def pose_errors(rec: pycolmap.Reconstruction, gt: dict[str, np.ndarray]) -> dict:
    """AUC@15 and median over the camera pairs (one instant: the poses are shared)."""
    pred = {
        camera_of(im.name): im.cam_from_world().matrix()
        for im in rec.images.values()
        if im.has_pose
    }
    truth = {camera_of(n): gt[n] for n in gt if camera_of(n) in pred}
    m = evaluate_poses(pred, {k: truth[k] for k in sorted(truth)})
    return {
        "auc15": m.auc["15"],
        "median_deg": m.median_error_deg,
        "pairs": [round(p.error_deg, 2) for p in m.pairs],
    }


def camera_rotation_residuals(
    rec: pycolmap.Reconstruction, gt: dict[str, np.ndarray]
) -> dict[str, list[float]]:
    """Each camera's rotation residual (deg, rotation vector in its own axes) after
    the mean rotation that best takes the model's world onto the calibration's."""
    names = sorted(im.name for im in rec.images.values() if im.has_pose)
    R = {n: rec.find_image_with_name(n).cam_from_world().matrix()[:, :3] for n in names}
    align = Rotation.from_matrix(np.array([R[n].T @ gt[n][:, :3] for n in names]))
    mean = align.mean().as_matrix()
    out = {}
    for n in names:
        delta = R[n] @ mean @ gt[n][:, :3].T
        out[camera_of(n)] = np.degrees(Rotation.from_matrix(delta).as_rotvec()).round(2)
    return {k: v.tolist() for k, v in sorted(out.items())}


def orbited(
    rec: pycolmap.Reconstruction, images: set[int], centre: np.ndarray, rotvec_deg
) -> pycolmap.Reconstruction:
    """Every camera of ``images`` turned about the point ``centre`` by the same
    rotation, given in each camera's own axes: all cameras move on a sphere about
    the people by the same angle, still looking at them."""
    out = pycolmap.Reconstruction(rec)
    turn = Rotation.from_rotvec(np.radians(rotvec_deg)).as_matrix()
    for image_id in images:  # loop over cameras
        image = out.image(image_id)
        T = image.cam_from_world().matrix()
        c = T[:, :3] @ centre + T[:, 3]  # the centre in the camera
        out.frame(image.frame_id).rig_from_world = pycolmap.Rigid3d(
            pycolmap.Rotation3d(turn @ T[:, :3]), turn @ (T[:, 3] - c) + c
        )
    return out


def adjusted(
    rec: pycolmap.Reconstruction,
    tracks: KeypointTracks,
    keep: set[int],
    poses: dict[str, np.ndarray] | None,
    loss_px: float,
    instant_of: dict[int, str] | None = None,
) -> pycolmap.Reconstruction:
    """The keypoint tracks' bundle adjustment from ``poses`` (None: ``rec``'s);
    with ``instant_of``, weighted by their repeated errors as `map` weighs them."""
    out = posed_copy(rec, keep, poses)
    add_keypoint_points(out, tracks, 2)
    noise = None
    if instant_of:
        sigma = keypoint_sigma_px(loss_px)
        noise, _ = repeat_noise(out, tracks, instant_of, sigma, loss_px)
    bundle_adjust_inplace(out, loss_px, noise)
    return out


def identity_labels(ds: str, db: Path) -> dict[int, str]:
    """Each person identity of ``db`` (static cameras: a camera's people of every
    instant are persons of its representative image) -> its hand label, by a
    majority of its views (tests/data/pose2sim_people.json)."""
    labels = json.loads(LABELS.read_text()).get(f"pose2sim_{ds}", {})
    priors = read_priors(OUT / "static_cameras" / ds / "priors")
    views = database.read_views(db)
    ids = dict(zip(views.image_names, views.image_ids.tolist(), strict=True))
    static = parse_static_cameras(PATTERN, views.image_names)
    identity = person_identities(database.read_person_associations(db))
    votes: dict[int, Counter] = {}
    for rep in sorted(static.representative.values()):  # as merge_priors orders
        k = 0  # the person's index in the representative image
        for name in static.members(rep):
            if name not in priors.images:
                continue
            persons = priors.images[name].persons
            label_of = person_labels(persons, labels.get(name, []))
            for j in range(len(persons)):
                ident = identity.get((ids[rep], k), -1)
                if ident >= 0 and j in label_of:
                    votes.setdefault(ident, Counter())[label_of[j]] += 1
                k += 1
    return {i: v.most_common(1)[0][0] for i, v in votes.items()}


def run(ds: str) -> dict:
    work = OUT / "static_cameras" / ds
    db = work / "database.db"
    rec = pycolmap.Reconstruction(work / "sparse_no-gravity" / "0")
    _, gt = load_calibration(SHARED / f"pose2sim_{ds}")
    registered = np.array(sorted(rec.reg_image_ids()), dtype=np.int64)
    tracks = keypoint_tracks(read_vc_records(db), registered)
    assert tracks.keys is not None
    reps = set(np.unique(tracks.image_id).tolist())  # one image per camera
    name = {i: rec.image(i).name for i in reps}
    loss_px = with_loss_scale(KeypointBaOptions(), rec).loss_scale_px
    assert loss_px is not None
    offset = int(database.read_run_info(db)["options"]["matching"]["num_samples"])
    landmark = np.array(anny_keypoint_names(bodies.load_bodies()))
    kind = landmark[np.clip(tracks.keys[tracks.track, 1] - offset, 0, None)]

    rows: dict[str, dict] = {}
    rows["`map --no-gravity`'s model"] = pose_errors(rec, gt)
    from_model = adjusted(rec, tracks, reps, None, loss_px)
    rows["keypoint tracks, from that model"] = pose_errors(from_model, gt)
    from_gt = adjusted(rec, tracks, reps, gt, loss_px)
    rows[FROM_GT] = pose_errors(from_gt, gt)
    instant_of = read_inputs(
        db, MappingOptions(static_cameras=PATTERN), None
    ).instant_of
    rows["keypoint tracks weighted by their repeats, from that model"] = pose_errors(
        adjusted(rec, tracks, reps, None, loss_px, instant_of), gt
    )
    rows["keypoint tracks weighted by their repeats, from the calibration"] = (
        pose_errors(adjusted(rec, tracks, reps, gt, loss_px, instant_of), gt)
    )
    at_gt = posed_copy(rec, reps, gt)
    reprojection = {
        "at the optimum": reprojection_px(from_gt, tracks),
        "at the calibration": reprojection_px(at_gt, tracks),
    }
    X, _ = triangulate_tracks(from_gt, tracks)
    centre = np.nanmedian(X, axis=0)
    orbits = {}
    for axis, label in ((0, "x"), (1, "y")):
        for sign in (-1.0, 1.0):
            turned = orbited(from_gt, reps, centre, sign * np.eye(3)[axis])
            orbits[f"{sign:+.0f} deg about {label}"] = {
                "reprojection_px": reprojection_px(turned, tracks),
                **pose_errors(turned, gt),
            }
    for left in sorted({camera_of(n) for n in name.values()}):
        keep = {i for i in reps if camera_of(name[i]) != left}
        sub = subset(tracks, np.isin(tracks.image_id, sorted(keep)))
        rows[f"from the calibration, without {left}"] = pose_errors(
            adjusted(rec, sub, keep, gt, loss_px), gt
        )
    for group, members in GROUPS.items():
        sub = subset(tracks, ~np.isin(kind, members))
        rows[f"from the calibration, without {group}"] = pose_errors(
            adjusted(rec, sub, reps, gt, loss_px), gt
        )
    label_of = identity_labels(ds, db)
    person = np.array([label_of.get(int(i), "") for i in tracks.keys[:, 0]])
    person = person[tracks.track]
    identity = tracks.keys[tracks.track, 0]
    for row, (label, how) in PEOPLE.items():
        mine = person == label
        if not mine.any():
            continue
        first = identity == identity[mine].min()  # the person at one instant
        keep = {"alone": mine, "without": ~mine, "once": ~mine | first}[how]
        rows[f"from the calibration, {row}"] = pose_errors(
            adjusted(rec, subset(tracks, keep), reps, gt, loss_px), gt
        )
    for label, r in rows.items():
        logger.info(
            "%s %s: AUC@15 %.1f, median %.2f deg",
            ds,
            label,
            r["auc15"],
            r["median_deg"],
        )
    return {
        "rows": rows,
        "reprojection_px": reprojection,
        "orbits": orbits,
        "rotation_residuals_deg": camera_rotation_residuals(from_gt, gt),
        "num_tracks": tracks.num_tracks,
        "num_observations": len(tracks.track),
        "loss_scale_px": loss_px,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--datasets", nargs="+", default=["single", "multi"])
    args = parser.parse_args()
    setup_logging()
    results = {ds: run(ds) for ds in args.datasets}
    write_json("static_ceiling.json", {"machine": machine(), "results": results})
    labels = list(dict.fromkeys(k for r in results.values() for k in r["rows"]))
    head = " | ".join(f"pose2sim_{ds}" for ds in results)
    lines = [
        f"| bundle adjustment of the keypoint tracks | {head} |",
        "|---|" + "---|" * len(results),
    ]
    for label in labels:
        cells = [
            f"{r['rows'][label]['auc15']:.1f} / {r['rows'][label]['median_deg']:.2f}"
            if label in r["rows"]
            else "-"
            for r in results.values()
        ]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    lines.append("")
    ds0 = next(iter(results))
    pooled = json.loads((OUT / "static_cameras.json").read_text())["results"]
    once = results[ds0]["rows"]["`map --no-gravity`'s model"]["auc15"]
    lines.append(
        "Cells: AUC@15 / median pair error (deg), the 6 camera pairs once (the poses "
        "are shared by the instants; the static-cameras table pools the five "
        "instants' copies of them, which the trapezoid rule of the AUC scores lower "
        f"for the same poses: {pooled[ds0]['map --no-gravity']['auc']['15']:.1f} "
        f"against {once:.1f} on pose2sim_{ds0}). Keypoints' "
        "median reprojection error at the "
        "optimum and at the calibration: "
        + "; ".join(
            f"{ds} {r['reprojection_px']['at the optimum']:.1f} px and "
            f"{r['reprojection_px']['at the calibration']:.1f} px"
            for ds, r in results.items()
        )
        + ". Each camera's rotation residual from the calibration start, after the "
        "best common rotation (deg, rotation vector in the camera's axes: x right, "
        "y down, z forward): "
        + "; ".join(
            f"{ds} "
            + ", ".join(f"{c} {v}" for c, v in r["rotation_residuals_deg"].items())
            for ds, r in results.items()
        )
        + "."
    )
    lines.append("")
    lines.append(
        "How little the keypoints see of a common turn of all cameras about the "
        "people (each camera turned by 1 deg about its own x or y axis, through the "
        "people's centre, from the optimum): median reprojection error, then the "
        "median pair error against the calibration:"
    )
    lines.append("")
    lines.append("| turn | " + head + " |")
    lines.append("|---|" + "---|" * len(results))
    lines.append(
        "| none (the optimum) | "
        + " | ".join(
            f"{r['reprojection_px']['at the optimum']:.2f} px, "
            f"{r['rows'][FROM_GT]['median_deg']:.2f} deg"
            for r in results.values()
        )
        + " |"
    )
    for turn in next(iter(results.values()))["orbits"]:
        lines.append(
            f"| {turn} | "
            + " | ".join(
                f"{r['orbits'][turn]['reprojection_px']:.2f} px, "
                f"{r['orbits'][turn]['median_deg']:.2f} deg"
                for r in results.values()
            )
            + " |"
        )
    lines.append("")
    lines.append(
        f"Measured at commit {machine()['commit']} by `.venv/bin/python "
        "bench/static_ceiling.py` on the databases and models of "
        "`bench/static_cameras.py`."
    )
    replace_section(
        DOCS / "results.md",
        "ceiling",
        "## Static cameras: where the keypoints' optimum lies\n\n" + "\n".join(lines),
    )
    print("\n".join(lines))


if __name__ == "__main__":
    main()
