"""`colmap-vc demo`: the whole pipeline on the bundled default scene.

1. synth: the default dome scene (seed 0, one person, realistic priors);
2. classic COLMAP on its SIFT database (the baseline that fails on such views);
3. augment: virtual correspondences from the priors into a copy of the database;
4. map: pycolmap incremental mapping of the augmented database and the keypoint
   bundle adjustment (``colmap-vc map``); for comparison, the mapper alone (COLMAP's
   BA only) and ``map --gba`` (the generalized bundle adjustment instead);
5. eval: pose AUC@15/30/45 of every method against ground truth, side by side, and
   the HTML report (report.html).
"""

from __future__ import annotations

import json
import logging
import shutil
import time
from dataclasses import dataclass
from pathlib import Path

import pycolmap

from . import augment, mapping, outputs
from .baselines import mesh_alignment_poses, run_classic
from .evaluation import (
    Metrics,
    evaluate_poses,
    evaluate_reconstruction,
    format_table,
    poses_by_name,
)
from .keypoint_ba import KeypointBaOptions
from .priors import read_priors
from .synthetic import NoiseLevel, SynthOptions, generate

logger = logging.getLogger(__name__)


DEFAULT_PRESET = "dome"
DEFAULT_SCENE = SynthOptions(seed=0, num_people=1, noise=NoiseLevel.REALISTIC)
"""The bundled default scene: ``synthetic.generate(DEFAULT_PRESET, ...)`` with these
options."""


@dataclass(frozen=True, kw_only=True, slots=True)
class DemoSummary:
    """What the demo did."""

    scene_dir: Path
    table: str
    metrics: dict[str, Metrics]
    timings_s: dict[str, float]
    model_dir: Path | None
    report_path: Path | None
    elapsed_s: float


def run(out_dir: Path, *, overwrite: bool = False) -> DemoSummary:
    """Run the demo into ``out_dir``; returns the table it printed."""
    t_start = time.perf_counter()
    timings: dict[str, float] = {}
    out_dir = Path(out_dir)
    scene_dir = out_dir / "scene"
    outputs.prepare_output_dir(out_dir, "demo", overwrite=overwrite)
    logger.info("1/5 synth: the default dome scene into %s", scene_dir)
    t0 = time.perf_counter()
    generate(DEFAULT_PRESET, scene_dir, DEFAULT_SCENE)
    timings["synth"] = time.perf_counter() - t0
    gt = pycolmap.Reconstruction(scene_dir / "gt" / "sparse")

    logger.info("2/5 classic COLMAP (SIFT, exhaustive matching, incremental mapping)")
    t0 = time.perf_counter()
    _, classic = run_classic(scene_dir, out_dir / "classic")
    timings["classic"] = time.perf_counter() - t0
    priors = read_priors(scene_dir / "priors")
    mesh = evaluate_poses(
        mesh_alignment_poses(priors, poses_by_name(gt)), poses_by_name(gt)
    )

    logger.info("3/5 augment: virtual correspondences into a copy of the database")
    db = out_dir / "database.db"
    shutil.copyfile(scene_dir / "database.db", db)
    t0 = time.perf_counter()
    aug = augment.run(
        db, scene_dir / "priors", augment.AugmentOptions(show_progress=False)
    )
    timings["augment"] = time.perf_counter() - t0

    logger.info("4/5 map: pycolmap incremental mapping of the augmented database")
    t0 = time.perf_counter()
    try:
        rec, summary = mapping.run(db, scene_dir / "images", out_dir / "sparse")
        model_dir = summary.model_dir
    except RuntimeError as exc:
        logger.error("%s", exc)
        rec, model_dir = None, None
    timings["map"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    gba, _ = mapping.run_incremental(
        db,
        scene_dir / "images",
        out_dir / "sparse_gba",
        mapping.MappingOptions(
            keypoint_ba_options=KeypointBaOptions(surface_tracks=True)
        ),
    )
    timings["map --gba"] = time.perf_counter() - t0
    # The mapper alone, without the keypoint BA: what that pass adds.
    plain, _ = mapping.run_incremental(
        db,
        scene_dir / "images",
        out_dir / "sparse_colmap_ba",
        mapping.MappingOptions(keypoint_ba=False),
    )

    logger.info("5/5 eval against ground truth")
    metrics = {
        "classic COLMAP": classic,
        "mesh alignment": mesh,
        "colmap-vc, COLMAP BA only": evaluate_reconstruction(plain, gt),
        "colmap-vc (augment + map)": evaluate_reconstruction(rec, gt),
        "colmap-vc (augment + map --gba)": evaluate_reconstruction(gba, gt),
    }
    table = format_table(metrics)
    from .report import ReportInputs, build_report

    report_path = build_report(
        ReportInputs(
            database_path=db,
            image_dir=scene_dir / "images",
            model_path=model_dir,
            gt_model_path=scene_dir / "gt" / "sparse",
            timings_s=timings,
            metrics=metrics,
            title="colmap-vc demo: default dome scene",
        ),
        out_dir / "report.html",
    )
    (out_dir / "metrics.json").write_text(
        json.dumps(
            {
                "metrics": {k: m.to_dict() for k, m in metrics.items()},
                "timings_s": timings,
                "augment_pairs": len(aug.pairs),
                "augment_verified_pairs": aug.num_verified_pairs,
            },
            indent=1,
        )
    )
    return DemoSummary(
        scene_dir=scene_dir,
        table=table,
        metrics=metrics,
        timings_s=timings,
        model_dir=model_dir,
        report_path=report_path,
        elapsed_s=time.perf_counter() - t_start,
    )
