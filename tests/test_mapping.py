"""Mapping: augmented databases register where classic ones fail; bad input is clear."""

from __future__ import annotations

import shutil
import sqlite3

import pycolmap
import pytest

from colmap_vc import augment, mapping
from colmap_vc.evaluation import evaluate_reconstruction


@pytest.fixture(scope="module")
def augmented(dome_scene, tmp_path_factory):
    db = tmp_path_factory.mktemp("map") / "database.db"
    shutil.copyfile(dome_scene / "database.db", db)
    augment.run(
        db, dome_scene / "gt" / "priors", augment.AugmentOptions(show_progress=False)
    )
    return db


def test_augmented_dome_registers_every_image_accurately(
    dome_scene, augmented, tmp_path
):
    rec, summary = mapping.run(
        augmented,
        dome_scene / "images",
        tmp_path / "sparse",
        mapping.MappingOptions(num_threads=2),
    )
    assert summary.num_registered == 6 and not summary.unregistered
    metrics = evaluate_reconstruction(
        rec, pycolmap.Reconstruction(dome_scene / "gt" / "sparse")
    )
    assert metrics.auc["15"] > 90  # clean priors
    assert (summary.model_dir / "images.bin").exists()


def test_a_plain_database_maps_as_plain_colmap_and_says_why(dome_scene, tmp_path):
    db = tmp_path / "plain.db"
    shutil.copyfile(dome_scene / "database.db", db)
    try:
        rec, summary = mapping.run(db, dome_scene / "images", tmp_path / "sparse")
    except RuntimeError as exc:  # classic matching fails on the dome: say why
        assert "no model" in str(exc) and "cam0" in str(exc)
    else:
        assert summary.num_registered + len(summary.unregistered) == 6
        assert all(isinstance(r, str) and r for r in summary.unregistered.values())


def test_existing_output_is_kept_without_overwrite(dome_scene, augmented, tmp_path):
    out = tmp_path / "sparse"
    out.mkdir()
    (out / "mine.txt").write_text("keep")
    with pytest.raises(FileExistsError, match="overwrite"):
        mapping.run(augmented, dome_scene / "images", out)
    assert (out / "mine.txt").read_text() == "keep"


def test_no_model_raises_with_the_reason(dome_scene, tmp_path):
    db = tmp_path / "nomatch.db"
    shutil.copyfile(dome_scene / "database.db", db)
    with sqlite3.connect(db) as conn:
        conn.execute("DELETE FROM two_view_geometries")
    with pytest.raises(RuntimeError, match="no verified image pair"):
        mapping.run(db, dome_scene / "images", tmp_path / "sparse")


def test_missing_inputs(dome_scene, tmp_path):
    with pytest.raises(FileNotFoundError, match="database"):
        mapping.run(tmp_path / "none.db", dome_scene / "images", tmp_path / "o")
    with pytest.raises(FileNotFoundError, match="image folder"):
        mapping.run(dome_scene / "database.db", tmp_path / "noimages", tmp_path / "o")
