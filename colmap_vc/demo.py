"""`colmap-vc demo`: the main job on the bundled default scene.

Generates the default dome scene (seed 0, one person, realistic priors), runs classic
COLMAP on it and prints the accuracy table. Later stages (augment, map with virtual
correspondences) join this table as they land.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass
from pathlib import Path

from .baselines import run_classic
from .evaluation import Metrics, format_table
from .synthetic import SynthOptions, generate

logger = logging.getLogger(__name__)

DEFAULT_SCENE = {"preset": "dome", "seed": 0, "num_people": 1, "noise": "realistic"}


@dataclass(frozen=True, kw_only=True, slots=True)
class DemoSummary:
    """What the demo did."""

    scene_dir: Path
    table: str
    metrics: dict[str, Metrics]
    elapsed_s: float


def run(out_dir: Path, *, overwrite: bool = False) -> DemoSummary:
    """Run the demo into ``out_dir``; returns the table it printed."""
    t0 = time.perf_counter()
    scene_dir = out_dir / "scene"
    logger.info("1/2 generating the default dome scene into %s", scene_dir)
    generate(
        DEFAULT_SCENE["preset"],
        scene_dir,
        SynthOptions(
            seed=DEFAULT_SCENE["seed"],
            num_people=DEFAULT_SCENE["num_people"],
            noise=DEFAULT_SCENE["noise"],
            overwrite=overwrite,
        ),
    )
    logger.info("2/2 classic COLMAP (SIFT, exhaustive matching, incremental mapping)")
    _, classic = run_classic(scene_dir, out_dir / "classic")
    metrics = {"classic COLMAP": classic}
    table = format_table(metrics)
    (out_dir / "metrics.json").write_text(
        json.dumps({k: m.to_dict() for k, m in metrics.items()}, indent=1)
    )
    return DemoSummary(
        scene_dir=scene_dir, table=table, metrics=metrics, elapsed_s=time.perf_counter() - t0
    )
