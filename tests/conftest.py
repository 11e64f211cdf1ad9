"""Shared fixtures: a seeded rng and small synthetic scenes from colmap_vc.synthetic."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(0)


@pytest.fixture(scope="session")
def dome_scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 6-view dome around two people: images, GT, clean/realistic priors, database.

    The predicted priors carry the true ids (``with_ids``): the tests that use them
    check VCs, verification and mapping, not the association of anonymous people.
    """
    from colmap_vc.synthetic import SynthOptions, generate

    out = tmp_path_factory.mktemp("dome") / "scene"
    generate(
        "dome",
        out,
        SynthOptions(
            seed=7,
            num_cameras=6,
            num_people=2,
            noise="realistic",
            num_threads=2,
            with_ids=True,
        ),
    )
    return out
