"""Hard or soft coplanarity: how `map`'s surface VCs enter its bundle adjustment.

A VC says two rays meet in 3D, so they are coplanar with the baseline (the
paper's Eq. 4). `map` makes that constraint hard: each surface VC of the mapper's
model is a 3D point that both rays must reach, and its residuals are the point's
reprojection errors (weighted to the surface budget, docs/gba.md). The soft form
has no point: one Sampson residual per pair of views of the track, the first-order
distance of the two pixels from satisfying the epipolar constraint, whitened by
the same noises and under the same Cauchy loss. To first order the two cost the
same (a free point's reprojection error at its optimum is the Sampson distance);
they differ in the multi-view tracks (a point ties three views, pairs do not) and
in cheirality (a point lies in front of its cameras or the mapper drops it;
coplanar rays may meet behind a camera).

This bench maps the same databases both ways, the soft arm by replacing, for
every bundle adjustment `map` runs, the weighted points' reprojection residuals
(`colmap_vc.gba.ceres._add_weighted`) with Sampson residuals (one block per image
pair, in Python, numeric derivatives). pose2sim per instant with seeds 0-2 of
augment and the mapper (the databases of `bench/realdata.py --seeds`), and the
twelve 1-person domes of `bench/gba_seeds.py` per prior level.

    .venv/bin/python bench/coplanarity.py [--seeds 0 1 2] [--levels realistic fitted]
        [--gba]

Writes bench/out/coplanarity.json and the "coplanarity" section of docs/gba.md
(with ``--gba``, `map --gba` with its surface tracks by identity both ways:
coplanarity_gba.json and "coplanarity-gba").
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import shutil
import sys
import time
from collections.abc import Iterator

import numpy as np
import pyceres
import pycolmap
from common import DOCS, OUT, machine, replace_section, setup_logging, write_json
from evidence import run_seed

from colmap_vc import mapping
from colmap_vc.evaluation import evaluate_reconstruction, pose_auc
from colmap_vc.gba import ceres
from colmap_vc.keypoint_ba import KeypointBaOptions
from colmap_vc.verification import skew

logger = logging.getLogger("bench.coplanarity")


def _rotation(q: np.ndarray) -> np.ndarray:
    """R of a quaternion (x, y, z, w), normalised first (the numeric derivatives
    step off the unit sphere; the pose manifold keeps only the tangent part)."""
    return pycolmap.Rotation3d(q / np.linalg.norm(q)).matrix()


class PairSampsonCost(pyceres.CostFunction):
    """The Sampson residuals of one image pair's VCs on the two pose blocks
    ([qx qy qz qw tx ty tz], cam_from_world): e = b2' E b1 over its gradient in
    pixels, robustified (sign(d) sqrt(rho(d^2)), Cauchy at ``loss_px``) and
    divided by the noise of the pair's pixels along that gradient."""

    def __init__(
        self,
        rays: tuple[np.ndarray, np.ndarray],
        focal: tuple[np.ndarray, np.ndarray],
        sigma: tuple[np.ndarray, np.ndarray],
        loss_px: float,
        weight: np.ndarray,
    ) -> None:
        super().__init__()
        self.rays, self.focal, self.sigma = rays, focal, sigma
        self.loss_px, self.weight = loss_px, weight
        self.set_num_residuals(len(weight))
        self.set_parameter_block_sizes([7, 7])

    def residuals(self, pose1: np.ndarray, pose2: np.ndarray) -> np.ndarray:
        R = _rotation(pose2[:4]) @ _rotation(pose1[:4]).T
        E = skew(pose2[4:] - R @ pose1[4:]) @ R
        b1, b2 = self.rays
        Eb1, Etb2 = b1 @ E.T, b2 @ E
        e = np.sum(b2 * Eb1, axis=1)
        g1 = (Etb2[:, 0] ** 2 + Etb2[:, 1] ** 2) / self.focal[0] ** 2
        g2 = (Eb1[:, 0] ** 2 + Eb1[:, 1] ** 2) / self.focal[1] ** 2
        d = e / np.sqrt(g1 + g2)
        noise = np.sqrt((self.sigma[0] ** 2 * g1 + self.sigma[1] ** 2 * g2) / (g1 + g2))
        c = self.loss_px
        robust = np.sign(d) * c * np.sqrt(np.log1p((d / c) ** 2))
        return self.weight * robust / noise

    def Evaluate(
        self,
        parameters: list[np.ndarray],
        residuals: np.ndarray,
        jacobians: list[np.ndarray | None] | None,
    ) -> bool:
        poses = [np.array(p, dtype=np.float64) for p in parameters]
        residuals[:] = self.residuals(*poses)
        if jacobians is None:
            return True
        for k in (0, 1):  # loop over the two pose blocks
            out = jacobians[k]
            if out is None:
                continue
            J = np.empty((len(self.weight), 7))
            for a in range(7):  # central differences per parameter
                h = 1e-7 * max(1.0, abs(poses[k][a]))
                plus, minus = [p.copy() for p in poses], [p.copy() for p in poses]
                plus[k][a] += h
                minus[k][a] -= h
                J[:, a] = (self.residuals(*plus) - self.residuals(*minus)) / (2 * h)
            out[:] = J.ravel()
        return True


def _track_pairs(row: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every pair (a, b), a < b, of observations of one point (``row``: each
    observation's point), and a weight per pair that makes a track of n views
    count its 2n - 3 constraints, not its n(n-1)/2 pairs."""
    order = np.argsort(row, kind="stable")
    starts = np.flatnonzero(np.r_[True, np.diff(row[order]) != 0])
    sizes = np.diff(np.r_[starts, len(order)])
    n_of = np.repeat(sizes, sizes)
    end_of = np.repeat(starts + sizes, sizes)
    k = np.arange(len(order))
    count = end_of - k - 1
    first = np.repeat(k, count)
    offset = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
    second = first + 1 + offset
    n = n_of[first]
    weight = np.sqrt((2 * n - 3) / (n * (n - 1) / 2))
    return order[first], order[second], weight


def _add_sampson(
    problem: pyceres.Problem,
    work: pycolmap.Reconstruction,
    observed: ceres._Observations,
    X: np.ndarray,
    people: ceres.PeopleNoise,
) -> list:
    """Stands in for ``ceres._add_weighted``: the weighted points' observations as
    Sampson residuals per image pair, no point blocks (``X`` unused)."""
    del X
    image_of, idx_of = observed.image_id, observed.point2D_idx
    rays = np.ones((len(image_of), 3))
    focal = np.empty(len(image_of))
    sigma = np.empty(len(image_of))
    robust = np.empty(len(image_of))
    posed = np.zeros(len(image_of), dtype=bool)
    for image_id in np.unique(image_of).tolist():  # loop over images
        sel = np.flatnonzero(image_of == image_id)
        image = work.image(image_id)
        camera = work.camera(image.camera_id)
        xy = np.array([image.points2D[k].xy for k in idx_of[sel].tolist()])
        rays[sel, :2] = camera.cam_from_img(xy)
        focal[sel] = camera.mean_focal_length()
        sigma[sel] = people.sigma_px[image_id][idx_of[sel]]
        robust[sel] = people.robust_px[image_id][idx_of[sel]]
        posed[sel] = problem.has_parameter_block(ceres._pose_block(work, image))
    a, b, weight = _track_pairs(observed.row)
    keep = posed[a] & posed[b] & (image_of[a] != image_of[b])
    a, b, weight = a[keep], b[keep], weight[keep]
    swap = image_of[a] > image_of[b]
    a, b = np.where(swap, b, a), np.where(swap, a, b)
    pairs, pair_of = np.unique(
        np.stack([image_of[a], image_of[b]], axis=1), axis=0, return_inverse=True
    )
    alive = []
    for p, (i, j) in enumerate(pairs.tolist()):  # loop over image pairs
        sel = np.flatnonzero(pair_of.ravel() == p)
        cost = PairSampsonCost(
            (rays[a[sel]], rays[b[sel]]),
            (focal[a[sel]], focal[b[sel]]),
            (sigma[a[sel]], sigma[b[sel]]),
            float(np.median(robust[a[sel]])),
            weight[sel],
        )
        blocks = [ceres._pose_block(work, work.image(k)) for k in (i, j)]
        problem.add_residual_block(cost, None, blocks)
        alive.append(cost)
    return alive


def _retriangulate(rec: pycolmap.Reconstruction, point_ids: list[int]) -> None:
    """The soft arm's points, which the solve left where they were, triangulated
    again from all their views with the new poses (linear)."""
    for point_id in point_ids:  # loop over the weighted points
        point = rec.point3D(point_id)
        rows = []
        for el in point.track.elements:  # loop over the point's views
            image = rec.image(el.image_id)
            camera = rec.camera(image.camera_id)
            x, y = camera.cam_from_img(np.array([image.points2D[el.point2D_idx].xy]))[0]
            P = image.cam_from_world().matrix()
            rows += [x * P[2] - P[0], y * P[2] - P[1]]
        Xh = np.linalg.svd(np.array(rows))[2][-1]
        if abs(Xh[3]) > 1e-12:
            point.xyz = Xh[:3] / Xh[3]


@contextlib.contextmanager
def soft_coplanarity() -> Iterator[None]:
    """Within: every bundle adjustment's weighted points enter as Sampson
    residuals."""
    original_add = ceres._add_weighted
    original_ba = ceres.bundle_adjust_inplace

    def adjust(rec, loss_scale_px, people=None, up=None):  # type: ignore[no-untyped-def]
        if people is None:
            return original_ba(rec, loss_scale_px, people, up)
        point_ids = ceres.weighted_points(rec, people)
        ceres._add_weighted = _add_sampson
        try:
            summary = original_ba(rec, loss_scale_px, people, up)
        finally:
            ceres._add_weighted = original_add
        _retriangulate(rec, point_ids)
        return summary

    import colmap_vc.cli  # noqa: F401  (every module that adjusts, imported)

    modules = [  # every module that imported the function by name
        module
        for name, module in sorted(sys.modules.items())
        if name.startswith("colmap_vc")
        and getattr(module, "bundle_adjust_inplace", None) is original_ba
    ]
    logger.info("soft coplanarity in %s", ", ".join(m.__name__ for m in modules))
    for module in modules:
        module.bundle_adjust_inplace = adjust  # type: ignore[attr-defined]
    try:
        yield
    finally:
        for module in modules:
            module.bundle_adjust_inplace = original_ba  # type: ignore[attr-defined]


def dome(level: str, seed: int, arm: str, gba: bool) -> float:
    """AUC@15 of `map` (``gba``: `map --gba`) on one of `bench/gba_seeds.py`'s
    1-person domes."""
    name = f"seeds_dome_p1_s{seed}_{level}"
    scene = OUT / "scenes" / name
    augmented = OUT / "runs" / "gba_seeds" / name / "augmented.db"
    if not augmented.exists():
        raise SystemExit(f"{augmented} missing: run bench/gba_seeds.py first")
    run = OUT / "coplanarity" / (f"{arm}_gba" if gba else arm) / name
    shutil.rmtree(run, ignore_errors=True)
    run.mkdir(parents=True)
    shutil.copyfile(augmented, run / "database.db")
    rec, _ = mapping.run_incremental(
        run / "database.db",
        scene / "images",
        run / "sparse",
        mapping.MappingOptions(
            keypoint_ba_options=KeypointBaOptions(surface_tracks=gba),
            show_progress=False,
        ),
    )
    gt = pycolmap.Reconstruction(scene / "gt" / "sparse")
    errors = np.array([p.error_deg for p in evaluate_reconstruction(rec, gt).pairs])
    return 100 * float(pose_auc(errors, [15.0])[0])


def _paired(soft: list[float], hard: list[float]) -> str:
    d = np.asarray(soft) - np.asarray(hard)
    se = d.std(ddof=1) / np.sqrt(len(d)) if len(d) > 1 else 0.0
    return f"{d.mean():+.1f} ± {se:.1f} ({int((d > 0).sum())}-{int((d < 0).sum())})"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--levels", nargs="+", default=["realistic", "fitted"])
    parser.add_argument("--domes", type=int, default=12, help="domes per level")
    parser.add_argument(
        "--gba",
        action="store_true",
        help="`map --gba` (its surface tracks by identity) instead of `map`",
    )
    parser.add_argument("--no-docs", action="store_true")
    args = parser.parse_args()
    refinement = "`map --gba`" if args.gba else "`map`"
    setup_logging()
    logging.getLogger("colmap_vc").setLevel(logging.WARNING)
    results: dict[str, dict] = {}
    elapsed: dict[str, float] = {}
    for arm in ("hard", "soft"):
        t0 = time.perf_counter()
        context = soft_coplanarity() if arm == "soft" else contextlib.nullcontext()
        with context:
            for ds in ("single", "multi"):
                for seed in args.seeds:
                    logger.info("%s: pose2sim_%s, seed %d", arm, ds, seed)
                    where = f"{arm}_gba" if args.gba else arm
                    work = OUT / "coplanarity" / where / ds / f"seed{seed}"
                    results.setdefault(f"pose2sim_{ds}", {}).setdefault(arm, {})[
                        str(seed)
                    ] = run_seed(ds, ["--gba"] if args.gba else [], seed, work)
            for level in args.levels:
                logger.info("%s: 1-person domes, %s priors", arm, level)
                results.setdefault(f"domes_{level}", {})[arm] = {
                    str(s): dome(level, s, arm, args.gba) for s in range(args.domes)
                }
        elapsed[arm] = time.perf_counter() - t0
    write_json(
        "coplanarity_gba.json" if args.gba else "coplanarity.json",
        {"machine": machine(), "results": results, "elapsed_s": elapsed},
    )
    lines = [
        f"| data | units | mean AUC@15: hard ({refinement}) / soft | soft - hard "
        "| per unit, hard | per unit, soft |",
        "|---|---|---|---|---|---|",
    ]
    for key, arms in results.items():
        units = sorted(arms["hard"], key=int)
        if key.startswith("pose2sim"):  # a seed's score: its instants' mean
            hard = [float(np.mean(arms["hard"][u])) for u in units]
            soft = [float(np.mean(arms["soft"][u])) for u in units]
            label, what = key, f"{len(units)} seed(s), 5 instants each"
        else:
            hard = [arms["hard"][u] for u in units]
            soft = [arms["soft"][u] for u in units]
            label = f"1-person domes, `{key.removeprefix('domes_')}` priors"
            what = f"{len(units)} dome(s)"
        lines.append(
            f"| {label} | {what} | {np.mean(hard):.1f} / {np.mean(soft):.1f} "
            f"| {_paired(soft, hard)} | {' '.join(f'{x:.1f}' for x in hard)} "
            f"| {' '.join(f'{x:.1f}' for x in soft)} |"
        )
    seeds = " ".join(map(str, args.seeds))
    lines += [
        "",
        f"Measured at commit {machine()['commit']} by `.venv/bin/python "
        f"bench/coplanarity.py --seeds {seeds}{' --gba' if args.gba else ''}` "
        f"({sum(elapsed.values()) / 60:.0f} min; the soft arm "
        f"{elapsed['soft'] / elapsed['hard']:.1f} times the hard arm's time, its "
        f"residuals in Python): {refinement} on the same databases, the surface "
        f"VCs as 3D points (hard, {refinement} as it is) or as Sampson residuals "
        "per pair of views (soft). pose2sim: each instant's 4 images mapped on "
        "their own with the seed's databases (`bench/realdata.py --seeds`), a "
        "seed's score the mean of its five instants' AUC@15; domes: "
        "`bench/gba_seeds.py`'s. Differences paired per unit, ± one standard "
        "error, (won - lost).",
    ]
    body = "\n".join(lines)
    print(body)
    if not args.no_docs:
        section = "coplanarity-gba" if args.gba else "coplanarity"
        replace_section(DOCS / "gba.md", section, body)


if __name__ == "__main__":
    main()
