"""Shared helpers of the benchmark scripts: output folders, JSON and Markdown."""

from __future__ import annotations

import argparse
import json
import logging
import os
import platform
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "bench" / "out"
DOCS = ROOT / "docs"


def add_pose2sim_run_args(
    parser: argparse.ArgumentParser, out: str, out_help: str
) -> None:
    """The pose2sim benches' shared options: extra `map` arguments, the output
    folder under bench/out (and JSON name), and whether to write docs."""
    parser.add_argument(
        "--map-args", default="", help="extra `colmap-vc map` arguments"
    )
    parser.add_argument("--out", default=out, help=out_help)
    parser.add_argument(
        "--no-docs", action="store_true", help="do not write docs/results.md"
    )


WRONG_DEG = 30.0
"""A registered camera is wrong when the median error of its pairs is above this
(evaluation only: a camera that far off is not a noisy camera but a wrong one)."""


def wrong_cameras(pairs: list, posed: set[str]) -> list[str]:
    """The posed images whose pairs with other posed images have a median error
    above :data:`WRONG_DEG` (``pairs``: :class:`colmap_vc.evaluation.PairError`)."""
    return sorted(
        n
        for n in posed
        if np.median(
            [
                p.error_deg
                for p in pairs
                if n in (p.image_name1, p.image_name2)
                and {p.image_name1, p.image_name2} <= posed
            ]
            or [0.0]
        )
        > WRONG_DEG
    )


def setup_logging() -> None:
    logging.basicConfig(
        level=logging.INFO,
        format="[%(asctime)s %(name)s] %(message)s",
        datefmt="%H:%M:%S",
    )
    import pycolmap

    pycolmap.logging.minloglevel = 2


def machine() -> dict:
    """Where the numbers were measured."""
    commit = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"],
        cwd=ROOT,
        capture_output=True,
        text=True,
    ).stdout.strip()
    return {
        "python": sys.version.split()[0],
        "platform": platform.platform(),
        "cpus": os.cpu_count(),
        "commit": commit,
    }


def write_json(name: str, payload: dict) -> Path:
    OUT.mkdir(parents=True, exist_ok=True)
    path = OUT / name
    path.write_text(json.dumps(payload, indent=1))
    return path


def replace_section(doc: Path, marker: str, body: str) -> None:
    """Replace the text between <!-- marker:begin --> and <!-- marker:end --> in doc."""
    begin, end = f"<!-- {marker}:begin -->", f"<!-- {marker}:end -->"
    text = doc.read_text() if doc.exists() else ""
    block = f"{begin}\n{body.rstrip()}\n{end}"
    if begin in text and end in text:
        text = text[: text.index(begin)] + block + text[text.index(end) + len(end) :]
    else:
        text = text.rstrip() + "\n\n" + block + "\n"
    doc.write_text(text)


def scene_is_current(path: Path) -> bool:
    """Whether the synthetic scene at ``path`` was made with today's noise models
    (its scene.json's ``noise_models`` and ``noise_revision``): a scene made before
    a change to docs/synthetic.md's noise, or to the code that draws it, is stale,
    and a bench makes it again rather than measure the old noise."""
    from dataclasses import asdict

    from colmap_vc.synthetic.noise import NOISE_LEVELS, NOISE_REVISION, NoiseLevel

    spec = path / "scene.json"
    if not spec.exists():
        return False
    scene = json.loads(spec.read_text())
    models = scene.get("noise_models")
    if not models or scene.get("noise_revision", 1) != NOISE_REVISION:
        return False
    return all(
        model == json.loads(json.dumps(asdict(NOISE_LEVELS[NoiseLevel(level)])))
        for level, model in models.items()
    )


def speed_scene() -> Path:
    """The 16-view, 3-person dome of the speed benchmarks (made once, seed 100)."""
    from colmap_vc.synthetic import SynthOptions, generate

    scene = OUT / "scenes" / "speed_dome16"
    if not ((scene / "database.db").exists() and scene_is_current(scene)):
        generate(
            "dome",
            scene,
            SynthOptions(seed=100, num_cameras=16, num_people=3, overwrite=True),
        )
    return scene


def variant_dir(parent: Path, name: str, extra_args: list[str]) -> Path:
    """The output folder of one variant of a run: ``name`` with the extra CLI
    arguments appended (``sparse``, ``sparse_no-gravity``)."""
    return parent / "_".join([name, *(a.strip("-") for a in extra_args)])
