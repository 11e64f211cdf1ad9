"""Output folders: `--overwrite` replaces only what the same command wrote."""

from __future__ import annotations

from pathlib import Path

import pytest

from colmap_vc.outputs import marker_name, prepare_output_dir


def test_a_folder_the_command_wrote_is_replaced(tmp_path: Path) -> None:
    out = prepare_output_dir(tmp_path / "out", "synth", overwrite=False)
    (out / "old.txt").write_text("from the last run")
    prepare_output_dir(out, "synth", overwrite=True)
    assert sorted(p.name for p in out.iterdir()) == [marker_name("synth")]


@pytest.mark.parametrize("overwrite", [False, True])
def test_a_foreign_folder_is_never_removed(tmp_path: Path, overwrite: bool) -> None:
    (tmp_path / "photo.jpg").write_bytes(b"\xff\xd8")
    with pytest.raises(FileExistsError, match="overwrite"):
        prepare_output_dir(tmp_path, "map", overwrite=overwrite)
    assert (tmp_path / "photo.jpg").read_bytes() == b"\xff\xd8"


def test_another_commands_folder_is_not_removed(tmp_path: Path) -> None:
    out = prepare_output_dir(tmp_path / "out", "demo", overwrite=False)
    (out / "kept.txt").write_text("x")
    with pytest.raises(FileExistsError, match="not written by colmap-vc synth"):
        prepare_output_dir(out, "synth", overwrite=True)
    assert (out / "kept.txt").is_file()


def test_a_folder_holding_an_input_is_not_removed(tmp_path: Path) -> None:
    out = prepare_output_dir(tmp_path / "out", "map", overwrite=False)
    (out / "database.db").write_bytes(b"db")
    with pytest.raises(FileExistsError, match="holds the input"):
        prepare_output_dir(out, "map", overwrite=True, inputs=[out / "database.db"])
    assert (out / "database.db").read_bytes() == b"db"


def test_a_file_is_not_a_folder(tmp_path: Path) -> None:
    (tmp_path / "out").write_text("x")
    with pytest.raises(FileExistsError, match="is a file"):
        prepare_output_dir(tmp_path / "out", "map", overwrite=True)
    assert (tmp_path / "out").read_text() == "x"
