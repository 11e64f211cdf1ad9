"""The surface weight from the errors the keypoints and the surface share: a GLS model.

`map` weighs a person's surface points in an image as 6 keypoint observations
together (`KeypointBaOptions.surface_per_image`). Issue 12 asks for weights set
by a noise model. The models tried before (docs/gba.md, "Not done") read each
kind's errors on its own. This one reads the two kinds together.

What moves a camera is the error a person's observations share in its image: a
similarity (shift, scale, turn) that a small motion of the camera explains and no
number of samples averages out. Per person and image it is fitted to the errors
of the keypoints (o) and of the surface samples (O) against the projections of
their tracks triangulated with the true cameras (the tracks by identity of
`map --gba`). Over a row's person-images, per component: a = var(o), b = var(O),
c = cov(o, O). The keypoint BA counts a person's K keypoints as K observations;
surface points weighing W of them make the camera's estimate the weighted mean
at r = W / K, whose variance is (a + r^2 b + 2 r c) / (1 + r)^2. Each row's own
W minimises it (averaged over the four components, each over its keypoints-alone
value); the weight all rows share minimises the worst row's excess over its own
least. Rows: the models `bench/realdata.py` (pose2sim, each instant on its own)
and `bench/gba_seeds.py` (one- and three-person domes) left.

The truth is needed. Where one person is all an image holds, its camera absorbs
the similarity the person's keypoints and surface share, and only o - O is left
in the model's residuals; the second table (the same at `map`'s poses) shows it.

    .venv/bin/python bench/surface_offsets.py [--no-docs]   (under 1 min)

Writes bench/out/surface_offsets.json and the section surface-offsets of docs/gba.md.
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

import numpy as np
import pycolmap
from common import DOCS, OUT, machine, replace_section, setup_logging, write_json
from gba_bound import projections, similarity_design
from realdata import INSTANTS, SHARED, load_calibration
from static_ceiling import posed_copy

from colmap_vc import keypoint_tracks as kt
from colmap_vc.keypoint_ba import KeypointBaOptions
from colmap_vc.vc_records import read_vc_records

logger = logging.getLogger("bench.surface_offsets")

CLIP = 10.0
"""Observations beyond CLIP times the keypoints' median error are left out (a
person turned front to back, a false detection): gross errors, not the noise."""
TRIM = 3.0
"""Person-images whose shared error is beyond TRIM robust standard deviations are
left out of the variances: an identity the association mixed up is not noise."""
BOOTSTRAP = 500
WEIGHTS = (3, 6, 12, 24, 48)
"""The weights per image the docs' sweep measured (docs/gba.md)."""
SIX = KeypointBaOptions().surface_per_image
"""The constant this bench tests (6)."""


def errors(rec: pycolmap.Reconstruction, tracks: kt.KeypointTracks) -> np.ndarray:
    """(O, 2) pixel minus the projection of its track, triangulated by ``rec``."""
    keep = np.ones(len(tracks.track), dtype=bool)
    return tracks.xy_img - projections(rec, tracks, keep)


def shared_errors(
    tracks: kt.KeypointTracks,
    err: np.ndarray,
    clip_px: float,
    frame: dict[tuple[int, int], tuple[np.ndarray, float]],
) -> dict[tuple[int, int], tuple[np.ndarray, int]]:
    """Per (image, person): the similarity (shift x, y; scale; turn) that best
    explains the observations' errors, scale and turn times the person's radius
    (pixels at its keypoints' spread, about its keypoints' centre: ``frame``),
    and the number of observations."""
    person = tracks.keys[tracks.track, 0]
    ok = np.isfinite(err).all(axis=1) & (np.linalg.norm(err, axis=1) < clip_px)
    key = tracks.image_id.astype(np.int64) * 1_000_000 + person
    out = {}
    for k in np.unique(key[ok]):  # loop over person-images
        group = (int(k // 1_000_000), int(k % 1_000_000))
        m = ok & (key == k)
        if group not in frame or m.sum() < 4:
            continue
        centre, radius = frame[group]
        A = similarity_design((tracks.xy_img[m] - centre) / radius)
        p, *_ = np.linalg.lstsq(A, err[m].ravel(), rcond=None)
        out[group] = (p, int(m.sum()))
    return out


def frames(
    tracks: kt.KeypointTracks,
) -> dict[tuple[int, int], tuple[np.ndarray, float]]:
    """Per (image, person): its keypoints' centre and RMS radius (pixels)."""
    person = tracks.keys[tracks.track, 0]
    out = {}
    pairs = zip(tracks.image_id.tolist(), person.tolist(), strict=True)
    for i, p in sorted(set(pairs)):
        xy = tracks.xy_img[(tracks.image_id == i) & (person == p)]
        centre = np.median(xy, axis=0)
        out[(i, p)] = (centre, float(np.sqrt(np.mean(np.sum((xy - centre) ** 2, 1)))))
    return out


def person_images(
    db: Path, model: Path, poses: dict[str, np.ndarray] | None
) -> np.ndarray:
    """Rows (keypoints' similarity (4), surface's similarity (4), K) for the
    person-images of one model's registered images with both keypoints and surface
    samples, at ``poses`` (by image name; None: the model's own)."""
    base = pycolmap.Reconstruction(model)
    registered = sorted(base.reg_image_ids())
    rec = posed_copy(base, set(registered), poses)
    records = read_vc_records(db)
    ids = np.array(registered, dtype=np.int64)
    keypoints = kt.keypoint_tracks(records, ids)
    surface = kt.surface_tracks(records, ids)
    ek, es = errors(rec, keypoints), errors(rec, surface)
    clip = CLIP * float(np.nanmedian(np.linalg.norm(ek, axis=1)))
    frame = frames(keypoints)
    gk = shared_errors(keypoints, ek, clip, frame)
    gs = shared_errors(surface, es, clip, frame)
    rows = [(*gk[k][0], *gs[k][0], gk[k][1]) for k in sorted(gk.keys() & gs.keys())]
    return np.array(rows, dtype=float).reshape(-1, 9)


def trimmed(rows: np.ndarray) -> np.ndarray:
    """The person-images whose similarity errors are within TRIM robust standard
    deviations (1.4826 MAD per component) of zero, both kinds."""
    size = np.abs(rows[:, 0:8])
    scale = 1.4826 * np.median(size, axis=0)
    return rows[(size <= TRIM * scale).all(axis=1)]


def moments(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per component (shift x, y, scale, turn): the keypoints' and the surface's
    similarity errors' second moments a, b and their cross moment c."""
    o, shared = rows[:, 0:4], rows[:, 4:8]
    return np.mean(o**2, 0), np.mean(shared**2, 0), np.mean(o * shared, 0)


def variance_ratio(rows: np.ndarray, ratio: np.ndarray) -> np.ndarray:
    """Per weight ratio r (surface : keypoints), the variance of the weighted mean
    of the two kinds' similarity errors over that of the keypoints alone, the mean
    over the four components (shift x, y, scale, turn)."""
    a, b, c = moments(rows)
    r = ratio[:, None]
    return np.mean((a + r**2 * b + 2 * r * c) / ((1 + r) ** 2 * a), axis=1)


GRID = np.exp(np.linspace(np.log(0.01), np.log(100.0), 401))
WEIGHT_GRID = np.exp(np.linspace(np.log(1.0), np.log(100.0), 201))
"""Weights per image (keypoint observations) at which each row's excess variance
over its own optimum is read, for the one weight all rows share."""


def excess(rows: np.ndarray) -> np.ndarray:
    """Over WEIGHT_GRID: the variance at each weight per image over the row's least."""
    rows = trimmed(rows)
    curve = variance_ratio(rows, GRID)
    keypoints = float(np.median(rows[:, 8]))
    return np.interp(WEIGHT_GRID / keypoints, GRID, curve) / curve.min()


def summary(rows: np.ndarray) -> dict:
    """The row's shared errors, its own weight and its variance at the swept weights."""
    kept = trimmed(rows)
    a, b, c = moments(kept)
    keypoints = float(np.median(kept[:, 8]))
    return {
        "person_images": len(rows),
        "kept": len(kept),
        "keypoints": keypoints,
        "sd_keypoints_px": [float(x) for x in np.sqrt(a)],
        "sd_surface_px": [float(x) for x in np.sqrt(b)],
        "correlation": [float(x) for x in c / np.sqrt(a * b)],
        "W": float(keypoints * GRID[np.argmin(variance_ratio(kept, GRID))]),
        "variance_at": {
            str(w): float(v)
            for w, v in zip(
                WEIGHTS,
                variance_ratio(kept, np.array(WEIGHTS) / keypoints),
                strict=True,
            )
        },
    }


def shared_weight(rows: dict[str, np.ndarray]) -> tuple[float, np.ndarray]:
    """The one weight whose worst row's excess variance is least, and that excess
    per row at it."""
    ex = np.array([excess(r) for r in rows.values()])
    best = int(np.argmin(ex.max(axis=0)))
    return float(WEIGHT_GRID[best]), ex[:, best]


def resampled(
    rows: dict[str, np.ndarray], rng: np.random.Generator
) -> dict[str, np.ndarray]:
    """Each row's person-images drawn again with replacement."""
    return {k: r[rng.integers(0, len(r), len(r))] for k, r in rows.items()}


def pose2sim_rows(truth: bool) -> dict[str, np.ndarray]:
    """Per dataset, the person-images of its five instants' models, at the
    calibration (``truth``) or at the model's poses."""
    out = {}
    for dataset in ("single", "multi"):
        _, poses = load_calibration(SHARED / f"pose2sim_{dataset}")
        rows = []
        for instant in INSTANTS:
            work = OUT / "realdata" / dataset / instant / "order0"
            if not (work / "sparse" / "0").exists():
                raise SystemExit(f"{work} has no model: run bench/realdata.py first")
            rows.append(
                person_images(
                    work / "database.db",
                    work / "sparse" / "0",
                    poses if truth else None,
                )
            )
        out[f"pose2sim_{dataset}, 5 instants"] = np.vstack(rows)
    return out


def dome_rows(people: int, truth: bool) -> dict[str, np.ndarray]:
    """Per prior level, the person-images of `bench/gba_seeds.py`'s twelve domes."""
    out = {}
    for level in ("realistic", "fitted"):
        rows = []
        for seed in range(12):
            scene = f"seeds_dome_p{people}_s{seed}_{level}"
            work = OUT / "runs" / "gba_seeds" / scene / "default"
            if not (work / "sparse" / "0").exists():
                raise SystemExit(f"{work} has no model: run bench/gba_seeds.py first")
            gt = pycolmap.Reconstruction(OUT / "scenes" / scene / "gt" / "sparse")
            poses = {im.name: im.cam_from_world().matrix() for im in gt.images.values()}
            rows.append(
                person_images(
                    work / "database.db",
                    work / "sparse" / "0",
                    poses if truth else None,
                )
            )
        label = "1-person" if people == 1 else f"{people}-person"
        out[f"twelve {label} domes, `{level}`"] = np.vstack(rows)
    return out


OPTIMUM = {
    "pose2sim_single, 5 instants": "6-24",
    "pose2sim_multi, 5 instants": "3-12",
    "twelve 1-person domes, `realistic`": "6-12",
    "twelve 1-person domes, `fitted`": "3-6",
    "twelve 3-person domes, `realistic`": "-",
    "twelve 3-person domes, `fitted`": "-",
}
"""The weights per image at the top of each row's measured curve (docs/gba.md,
"The default's surface budget", at 3 / 6 / 12 / 24 / 48)."""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--no-docs", action="store_true")
    args = parser.parse_args()
    setup_logging()
    t0 = time.perf_counter()
    rng = np.random.default_rng(0)
    rows = {**pose2sim_rows(True), **dome_rows(1, True), **dome_rows(3, True)}
    at_model = {**pose2sim_rows(False), **dome_rows(1, False), **dome_rows(3, False)}
    results = {name: summary(r) for name, r in rows.items()}
    for name, r in results.items():
        r["at_model"] = summary(at_model[name])
    weight, at_weight = shared_weight(rows)
    draws = [resampled(rows, rng) for _ in range(BOOTSTRAP)]  # loop over resamples
    own = np.array([[summary(r)["W"] for r in d.values()] for d in draws])
    shared = np.array([shared_weight(d)[0] for d in draws])
    at_six = np.array([np.interp(SIX, WEIGHT_GRID, excess(r)) for r in rows.values()])
    for k, r in enumerate(results.values()):
        r["W_16"], r["W_84"] = (float(x) for x in np.percentile(own[:, k], [16, 84]))
        r["excess_at_shared"] = float(at_weight[k])
        r["excess_at_6"] = float(at_six[k])
    shared_16, shared_84 = (float(x) for x in np.percentile(shared, [16, 84]))
    table = [
        "| data | person-images (kept of all) | K | shared shift, keypoints / surface "
        "(px) | correlation: shift x, y / scale / turn | the row's own W (16-84 %) "
        "| variance at W = "
        + " / ".join(str(w) for w in WEIGHTS)
        + " (keypoints alone: 1) | excess at the shared W / at 6 "
        "| the measured optimum |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for name, r in results.items():
        sk, ss, rho = r["sd_keypoints_px"], r["sd_surface_px"], r["correlation"]
        table.append(
            f"| {name} | {r['kept']} of {r['person_images']} | {r['keypoints']:.0f} "
            f"| {np.hypot(sk[0], sk[1]):.1f} / {np.hypot(ss[0], ss[1]):.1f} "
            f"| {rho[0]:.2f}, {rho[1]:.2f} / {rho[2]:.2f} / {rho[3]:.2f} "
            f"| {r['W']:.1f} ({r['W_16']:.1f}-{r['W_84']:.1f}) "
            f"| {' / '.join(f'{v:.2f}' for v in r['variance_at'].values())} "
            f"| {100 * (r['excess_at_shared'] - 1):.1f} % / "
            f"{100 * (r['excess_at_6'] - 1):.1f} % | {OPTIMUM[name]} |"
        )
    table.append(
        f"\n**The one weight for every row: {weight:.1f}** ({shared_16:.1f}-"
        f"{shared_84:.1f} over the resamples), where the worst row's variance is "
        f"{100 * (at_weight.max() - 1):.1f} % above its own least; at {SIX:g}, "
        f"{100 * (at_six.max() - 1):.1f} %."
    )
    table += [
        "",
        "| data | the shared shift at the true poses: keypoints / surface (px), "
        "correlation x, y | at `map`'s poses |",
        "|---|---|---|",
    ]
    for name, r in results.items():
        cells = []
        for at in (r, r["at_model"]):
            sk, ss, rho = at["sd_keypoints_px"], at["sd_surface_px"], at["correlation"]
            cells.append(
                f"{np.hypot(sk[0], sk[1]):.1f} / {np.hypot(ss[0], ss[1]):.1f}, "
                f"{rho[0]:.2f}, {rho[1]:.2f}"
            )
        table.append(f"| {name} | {cells[0]} | {cells[1]} |")
    commit = machine()["commit"]
    table.append(
        f"\nMeasured at commit {commit} by `.venv/bin/python bench/surface_offsets.py` "
        f"({time.perf_counter() - t0:.0f} s) on the models of "
        "`bench/realdata.py` and `bench/gba_seeds.py` (`map`'s default). Per person "
        "and image, the similarity (shift, scale, turn) that best explains the "
        "errors of its keypoints, and that of its surface samples, against their "
        "tracks triangulated with the true cameras (scale and turn in pixels at "
        "the keypoints' radius); person-images beyond "
        f"{TRIM:.0f} robust standard deviations left out. The surface at W keypoint "
        "observations against the K keypoints weighs r = W / K; the variance of "
        "the weighted mean, (a + r^2 b + 2 r c) / (1 + r)^2 per component (a, b "
        "the two kinds' variances, c their covariance), over a, averaged over the "
        "four components. *The row's own W* minimises it; *the shared W* minimises "
        "the largest excess over every row's own least. Intervals: "
        f"{BOOTSTRAP} resamples of each row's person-images. *The measured "
        "optimum*: the weights at the top of each row's AUC@15 curve (\"The "
        "default's surface budget\" above). The second table: the keypoints' and "
        "the surface's shift, and their correlation, at the true poses and at "
        "`map`'s."
    )
    text = "\n".join(table)
    logger.info("\n%s", text)
    payload = {
        "results": results,
        "shared_weight": {"W": weight, "W_16": shared_16, "W_84": shared_84},
        "machine": machine(),
    }
    write_json("surface_offsets", payload)
    if not args.no_docs:
        replace_section(DOCS / "gba.md", "surface-offsets", text)


if __name__ == "__main__":
    main()
