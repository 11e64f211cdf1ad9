"""GBA: speed against pycolmap's (Ceres) bundle adjustment, and hard vs soft.

1. Speed: GBA on all inlier VC tuples of a 16-view, 3-person dome scene (realistic
   priors), from ground-truth poses perturbed by 2 degrees / 5 %, against
   ``pycolmap.create_default_bundle_adjuster(...).solve()`` on a problem of the same
   size in the same run: same cameras and start poses, one classic 3D point per VC
   tuple observed by the same two pixels (so the same observations), the same loss
   (Cauchy, 2 px), intrinsics fixed, the same number of iterations (tolerances off).
   Goal: GBA time / Ceres time <= 1.5.
2. Hard vs soft parametrization on the same scene: clean priors from poses perturbed
   by 10 degrees / 10 %, realistic priors from 2 degrees / 5 % (several seeds), and
   the metric prior's scale error; pose errors are the relative-pose errors of all
   pairs (``colmap_vc.evaluation``), so the gauge does not matter.

    .venv/bin/python bench/gba_speed.py [--repeats 3] [--seeds 0 1 2]

Writes bench/out/gba_speed.json and the section `gba-speed` of docs/benchmark.md.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import statistics
import time
from pathlib import Path

import numpy as np
import pycolmap
from common import DOCS, OUT, machine, replace_section, setup_logging, write_json
from scipy.spatial.transform import Rotation

from colmap_vc import augment, database
from colmap_vc.evaluation import evaluate_poses, poses_by_name
from colmap_vc.gba import GbaOptions, GbaProblem, Parametrization, build_problem, solve
from colmap_vc.priors import read_priors
from colmap_vc.synthetic import SynthOptions, generate

logger = logging.getLogger("bench.gba_speed")
LOSS_SCALE_PX = 2.0


def perturbed(
    rec: pycolmap.Reconstruction, rng: np.random.Generator, deg: float, frac: float
) -> pycolmap.Reconstruction:
    """A copy with every pose rotated by ``deg`` about a random axis and its
    translation moved by ``frac`` of its norm in a random direction."""
    out = pycolmap.Reconstruction(rec)
    for image_id in sorted(out.images):
        image = out.images[image_id]
        P = image.cam_from_world().matrix()
        axis = rng.normal(size=3)
        dR = Rotation.from_rotvec(
            np.radians(deg) * axis / np.linalg.norm(axis)
        ).as_matrix()
        direction = rng.normal(size=3)
        t = P[:, 3] + frac * np.linalg.norm(P[:, 3]) * direction / np.linalg.norm(
            direction
        )
        image.frame.set_cam_from_world(
            image.camera_id, pycolmap.Rigid3d(pycolmap.Rotation3d(dR @ P[:, :3]), t)
        )
    return out


def classic_twin(problem: GbaProblem) -> pycolmap.Reconstruction:
    """The same-size classic BA problem: one 3D point per VC tuple (at its initial X1),
    observed by the tuple's two pixels, same cameras and poses."""
    rec = pycolmap.Reconstruction()
    for k, cam in enumerate(problem.cameras):
        rec.add_camera_with_trivial_rig(
            pycolmap.Camera(
                camera_id=k + 1,
                model=cam.model,
                width=cam.width,
                height=cam.height,
                params=cam.params,
            )
        )
    num = problem.num_vcs
    obs_img = np.concatenate([problem.vc_image_idx1, problem.vc_image_idx2])
    obs_xy = np.concatenate([problem.vc_xy1, problem.vc_xy2])
    row = np.zeros(len(obs_img), np.int64)
    for k in range(problem.num_images):
        sel = np.flatnonzero(obs_img == k)
        row[sel] = np.arange(len(sel))
        image = pycolmap.Image(
            name=problem.image_names[k], camera_id=k + 1, image_id=k + 1
        )
        image.points2D = pycolmap.Point2DList(
            [pycolmap.Point2D(xy) for xy in obs_xy[sel]]
        )
        P = problem.cam_from_world[k]
        rec.add_image_with_trivial_frame(
            image, pycolmap.Rigid3d(pycolmap.Rotation3d(P[:, :3]), P[:, 3])
        )
    for t in range(num):
        track = pycolmap.Track()
        track.add_element(int(obs_img[t]) + 1, int(row[t]))
        track.add_element(int(obs_img[num + t]) + 1, int(row[num + t]))
        rec.add_point3D(problem.vc_x1_world[t], track)
    return rec


def ceres_ba(
    rec: pycolmap.Reconstruction, iterations: int, threads: int
) -> tuple[float, dict]:
    """pycolmap's default bundle adjuster (Ceres) with fixed intrinsics; wall time."""
    rec = pycolmap.Reconstruction(rec)
    options = pycolmap.BundleAdjustmentOptions(
        refine_focal_length=False,
        refine_principal_point=False,
        refine_extra_params=False,
        print_summary=False,
    )
    options.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
    options.ceres.loss_function_scale = LOSS_SCALE_PX
    solver = options.ceres.solver_options
    solver.max_num_iterations = iterations
    solver.num_threads = threads
    solver.function_tolerance = solver.gradient_tolerance = (
        solver.parameter_tolerance
    ) = 0.0
    config = pycolmap.BundleAdjustmentConfig()
    for image_id in rec.images:
        config.add_image(image_id)
    config.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
    t0 = time.perf_counter()
    summary = pycolmap.create_default_bundle_adjuster(options, config, rec).solve()
    elapsed = time.perf_counter() - t0
    cs = summary.ceres_summary
    return elapsed, {
        "time_s": elapsed,
        "initial_cost": cs.initial_cost,
        "final_cost": cs.final_cost,
        "num_iterations": cs.num_successful_steps + cs.num_unsuccessful_steps,
        "num_threads": cs.num_threads_used,
        "linear_solver": str(cs.linear_solver_type_used),
        "num_residuals": cs.num_residuals,
        "num_parameters": cs.num_effective_parameters,
    }


def pose_errors(result, gt: pycolmap.Reconstruction) -> dict:
    pred = dict(zip(result.image_names, result.cam_from_world, strict=True))
    metrics = evaluate_poses(pred, poses_by_name(gt))
    errors = np.array([p.error_deg for p in metrics.pairs])
    return {
        "max_pair_error_deg": float(errors.max()),
        "median_pair_error_deg": float(np.median(errors)),
    }


def scale_ratio(result, gt: pycolmap.Reconstruction) -> float:
    """Median ratio of camera-centre distances, result / ground truth."""
    gtp = poses_by_name(gt)
    c = np.array([-P[:, :3].T @ P[:, 3] for P in result.cam_from_world])
    g = np.array([-gtp[n][:, :3].T @ gtp[n][:, 3] for n in result.image_names])
    iu = np.triu_indices(len(c), 1)
    d = np.linalg.norm(c[:, None] - c[None], axis=2)[iu]
    dg = np.linalg.norm(g[:, None] - g[None], axis=2)[iu]
    return float(np.median(d / dg))


def virtual_correspondences(scene: Path, priors_dir: Path) -> tuple[list, list]:
    views = database.read_views(scene / "database.db")
    vc = augment.compute_virtual_correspondences(
        views, read_priors(priors_dir), augment.AugmentOptions(show_progress=False)
    )
    return vc.keypoints, vc.pairs


def speed(
    scene: Path, gt: pycolmap.Reconstruction, repeats: int, iterations: int
) -> dict:
    keypoints, pairs = virtual_correspondences(scene, scene / "priors")
    start = perturbed(gt, np.random.default_rng(0), 2.0, 0.05)
    problem = build_problem(start, keypoints, pairs)
    twin = classic_twin(problem)
    common = {
        "loss_scale_px": LOSS_SCALE_PX,
        "max_iterations": iterations,
        "function_tolerance": 0.0,
        "gradient_tolerance": 0.0,
        "parameter_tolerance": 0.0,
    }
    runs: dict[str, list] = {"ceres": [], "ceres_1_thread": [], "hard": [], "soft": []}
    for _ in range(repeats):  # interleaved, so machine noise hits all alike
        runs["ceres"].append(ceres_ba(twin, iterations, -1)[1])
        runs["ceres_1_thread"].append(ceres_ba(twin, iterations, 1)[1])
        for par in (Parametrization.HARD, Parametrization.SOFT):
            result = solve(problem, GbaOptions(parametrization=par, **common))
            runs[str(par)].append(dataclasses.asdict(result.summary))
    med = {k: statistics.median(r["time_s"] for r in v) for k, v in runs.items()}
    return {
        "num_images": problem.num_images,
        "num_vcs": problem.num_vcs,
        "iterations": iterations,
        "median_time_s": med,
        "ratio_hard": med["hard"] / med["ceres"],
        "ratio_soft": med["soft"] / med["ceres"],
        "ratio_hard_1_thread": med["hard"] / med["ceres_1_thread"],
        "runs": runs,
    }


SETTINGS = (  # (parametrization, coplanarity weight, metric prior weight)
    (Parametrization.HARD, 1.0, 0.0),
    (Parametrization.SOFT, 1.0, 0.0),
    (Parametrization.SOFT, 10.0, 0.0),
    (Parametrization.HARD, 1.0, 10.0),
    (Parametrization.SOFT, 1.0, 10.0),
)


def accuracy(
    scene: Path, gt: pycolmap.Reconstruction, seeds: list[int], max_vcs: int
) -> list[dict]:
    rows = []
    for priors, deg, frac in (("clean", 10.0, 0.1), ("realistic", 2.0, 0.05)):
        sub = "gt/priors" if priors == "clean" else "priors"
        keypoints, pairs = virtual_correspondences(scene, scene / sub)
        for seed in seeds:
            start = perturbed(gt, np.random.default_rng(seed), deg, frac)
            problem = build_problem(start, keypoints, pairs, max_vcs_per_pair=max_vcs)
            for par, coplanarity, weight in SETTINGS:
                options = GbaOptions(
                    parametrization=par,
                    coplanarity_weight=coplanarity,
                    metric_prior_weight=weight,
                    max_iterations=100,
                )
                result = solve(problem, options)
                s = result.summary
                rows.append(
                    {
                        "priors": priors,
                        "seed": seed,
                        "start_deg": deg,
                        "parametrization": str(par),
                        "coplanarity_weight": coplanarity if par == "soft" else None,
                        "metric_prior_weight": weight,
                        **pose_errors(result, gt),
                        "scale_ratio": scale_ratio(result, gt),
                        "final_rms_px": s.final_rms_px,
                        "final_median_px": s.final_median_px,
                        "num_outliers": s.num_outliers,
                        "iterations": s.num_iterations,
                        "termination": s.termination,
                        "time_s": s.time_s,
                        "num_vcs": s.num_vcs,
                    }
                )
                logger.info("%s", rows[-1])
    return rows


def _row(*cells: object) -> str:
    return "| " + " | ".join(str(c) for c in cells) + " |"


def summarize(rows: list[dict]) -> list[str]:
    """Medians over seeds, one line per setting."""
    lines = [
        _row(
            "priors (start)",
            "parametrization",
            "metric prior",
            "max pair err. (deg)",
            "median pair err. (deg)",
            "scale error (%)",
            "median reproj. (px)",
            "outliers",
            "iterations",
            "time (s)",
        ),
        "|---|---|---|---|---|---|---|---|---|---|",
    ]

    def key(r: dict) -> tuple:
        return (
            r["priors"],
            r["start_deg"],
            r["metric_prior_weight"],
            r["parametrization"],
            r["coplanarity_weight"] or 0.0,
        )

    for k in sorted({key(r) for r in rows}):
        sel = [r for r in rows if key(r) == k]
        priors, deg, weight, par, coplanarity = k

        def med(name: str, sel: list[dict] = sel) -> float:
            return statistics.median(r[name] for r in sel)

        scale = f"{100 * abs(med('scale_ratio') - 1):.1f}" if weight > 0 else "-"
        label = par if par == "hard" else f"soft (coplanarity weight {coplanarity:g})"
        lines.append(
            _row(
                f"{priors} ({deg:g} deg)",
                label,
                f"{weight:g}",
                f"{med('max_pair_error_deg'):.3f}",
                f"{med('median_pair_error_deg'):.3f}",
                scale,
                f"{med('final_median_px'):.3f}",
                f"{med('num_outliers'):.0f}",
                f"{med('iterations'):.0f}",
                f"{med('time_s'):.2f}",
            )
        )
    return lines


def speed_table(sp: dict, iterations: int, repeats: int) -> list[str]:
    med, runs = sp["median_time_s"], sp["runs"]
    ceres = runs["ceres"][0]

    def line(label: str, key: str, ratio: str) -> str:
        return _row(
            label,
            f"{med[key]:.2f}",
            f"{med[key] / iterations:.3f}",
            f"{runs[key][0]['final_cost']:.4g}",
            ratio,
        )

    return [
        _row(
            "solver (same problem, same iterations)",
            "wall time (s)",
            "per iteration (s)",
            "final cost",
            "GBA / Ceres",
        ),
        "|---|---|---|---|---|",
        line(
            f"pycolmap BA, Ceres {ceres['linear_solver']}, "
            f"{ceres['num_threads']} threads",
            "ceres",
            "1",
        ),
        line("pycolmap BA, Ceres, 1 thread", "ceres_1_thread", ""),
        line(
            "GBA hard (numpy LM + Schur, 1 thread)",
            "hard",
            f"**{sp['ratio_hard']:.2f}** ({sp['ratio_hard_1_thread']:.2f} vs 1 thread)",
        ),
        line("GBA soft", "soft", f"{sp['ratio_soft']:.2f}"),
        "",
        f"{sp['num_images']} images, {sp['num_vcs']} VC tuples (all inliers, realistic "
        f"priors) = {2 * sp['num_vcs']} observations; Ceres gets one classic point per "
        f"tuple. {iterations} iterations each, tolerances off, Cauchy loss "
        f"{LOSS_SCALE_PX:g} px, median of {repeats} interleaved runs. "
        "Goal: ratio <= 1.5.",
    ]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--iterations", type=int, default=10)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--max-vcs-per-pair", type=int, default=500)
    parser.add_argument(
        "--skip-accuracy",
        action="store_true",
        help="measure speed only; keep the accuracy rows of bench/out/gba_speed.json",
    )
    args = parser.parse_args()
    setup_logging()
    scene = OUT / "scenes" / "speed_dome16"
    if not (scene / "database.db").exists():
        options = SynthOptions(seed=100, num_cameras=16, num_people=3, overwrite=True)
        generate("dome", scene, options)
    gt = pycolmap.Reconstruction(scene / "gt" / "sparse")
    sp = speed(scene, gt, args.repeats, args.iterations)
    rows = []
    previous = OUT / "gba_speed.json"
    if not args.skip_accuracy:
        rows = accuracy(scene, gt, args.seeds, args.max_vcs_per_pair)
    elif previous.exists():  # keep the last accuracy table
        rows = json.loads(previous.read_text()).get("accuracy", [])
        logger.info("kept %d accuracy rows from %s", len(rows), previous)
    write_json("gba_speed.json", {"machine": machine(), "speed": sp, "accuracy": rows})
    body = speed_table(sp, args.iterations, args.repeats)
    if rows:
        seeds = " ".join(map(str, args.seeds))
        body += [
            "",
            "Hard vs soft (16-view dome, 3 people, "
            f"{args.max_vcs_per_pair} VC tuples per pair, medians over seeds {seeds}; "
            "clean priors start 10 deg / 10 % off, "
            "realistic priors 2 deg / 5 % off):",
            "",
            *summarize(rows),
        ]
    body += [
        "",
        f"Measured at commit {machine()['commit']} by "
        "`.venv/bin/python bench/gba_speed.py`; raw numbers in "
        "`bench/out/gba_speed.json`.",
    ]
    text = "\n".join(body)
    replace_section(DOCS / "benchmark.md", "gba-speed", text)
    logger.info("\n%s", text)


if __name__ == "__main__":
    main()
