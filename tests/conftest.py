"""Shared fixtures: a seeded rng and small synthetic scenes from colmap_vc.synthetic."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pycolmap
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


def extract_database(
    image_dir: Path, names: list[str], cameras: dict[str, pycolmap.Camera], db: Path
) -> Path:
    """SIFT (known intrinsics) of ``names`` in this order, then exhaustive matching:
    the order is the image ids COLMAP gives."""
    for name in names:
        cam = cameras[name]
        pycolmap.extract_features(
            db,
            image_dir,
            image_names=[name],
            camera_mode=pycolmap.CameraMode.PER_IMAGE,
            reader_options=pycolmap.ImageReaderOptions(
                camera_model=cam.model.name,
                camera_params=",".join(f"{p:.17g}" for p in cam.params),
            ),
            extraction_options=pycolmap.FeatureExtractionOptions(num_threads=1),
            device=pycolmap.Device.cpu,
        )
    pycolmap.match_exhaustive(
        db,
        matching_options=pycolmap.FeatureMatchingOptions(num_threads=1),
        device=pycolmap.Device.cpu,
    )
    return db
