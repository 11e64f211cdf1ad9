"""The command line: every subcommand answers --help, runs, fails with exit codes."""

from __future__ import annotations

import json
import shutil

import pytest

from colmap_vc.cli import COMMANDS, main


@pytest.mark.parametrize("command", [None, *COMMANDS])
def test_help(command, capsys):
    argv = ["--help"] if command is None else [command, "--help"]
    assert main(argv) == 0
    assert "usage" in capsys.readouterr().out.lower()


def test_usage_error_exits_2():
    assert main(["synth"]) == 2
    assert main(["no-such-command"]) == 2


def test_augment_map_eval_strip(dome_scene, tmp_path, capsys):
    db = tmp_path / "database.db"
    shutil.copyfile(dome_scene / "database.db", db)
    assert (
        main(
            [
                "augment",
                str(db),
                "--priors",
                str(dome_scene / "gt" / "priors"),
                "--no-show-progress",
            ]
        )
        == 0
    )
    out = capsys.readouterr().out
    assert "pairs verified" in out and "cam00.jpg" in out
    assert (
        main(
            [
                "map",
                str(db),
                "--image-path",
                str(dome_scene / "images"),
                "--output-path",
                str(tmp_path / "sparse"),
                "--no-gba",
            ]
        )
        == 0
    )
    out = capsys.readouterr().out
    assert "registered 6/6" in out
    # In metres, with the scale's uncertainty: the people's size, 2 people.
    assert (
        "in metres from the people's size" in out
        and "(2 people); see metric_scale.json" in out
    )
    # the output exists: a second run without --overwrite fails (exit 1), nothing lost
    assert (
        main(
            [
                "map",
                str(db),
                "--image-path",
                str(dome_scene / "images"),
                "--output-path",
                str(tmp_path / "sparse"),
                "--no-gba",
            ]
        )
        == 1
    )
    # --gba: the generalized BA instead of the keypoint BA, recorded beside the model
    gba_out = tmp_path / "sparse_gba"
    assert (
        main(
            [
                "map",
                str(db),
                "--image-path",
                str(dome_scene / "images"),
                "--output-path",
                str(gba_out),
                "--gba",
            ]
        )
        == 0
    )
    assert "registered 6/6" in capsys.readouterr().out
    ran = json.loads((gba_out / "0" / "map_options.json").read_text())
    assert ran["options"]["keypoint_ba_options"]["surface_tracks"] is True
    assert sorted(p.name for p in gba_out.iterdir() if p.is_dir()) == ["0"]
    metrics = tmp_path / "m.json"
    plot = tmp_path / "curve.png"
    assert (
        main(
            [
                "eval",
                str(tmp_path / "sparse"),
                str(dome_scene / "gt" / "sparse"),
                "--output",
                str(metrics),
                "--plot",
                str(plot),
            ]
        )
        == 0
    )
    assert json.loads(metrics.read_text())["num_registered"] == 6
    # The synthetic world is metric: the model's size against it, in uncertainties.
    ratio = json.loads(metrics.read_text())["distance_ratio"]
    assert abs(ratio - 1.0) < 0.05
    out = capsys.readouterr().out
    assert f"camera distances / ground truth's: {ratio:.3f} (model in metres" in out
    import cv2

    curve = cv2.imread(str(plot))
    assert curve is not None and curve.shape[0] > 200 and (curve < 250).any()
    assert main(["strip", str(db)]) == 0


def test_eval_writes_strict_json_with_unregistered_images(dome_scene, tmp_path):
    # An unregistered image's pairs have no rotation error: null in the JSON,
    # not NaN (which JSON does not have).
    import pycolmap

    rec = pycolmap.Reconstruction(dome_scene / "gt" / "sparse")
    first = min(rec.images)
    rec.deregister_frame(rec.image(first).frame_id)
    (tmp_path / "pred").mkdir()
    rec.write(tmp_path / "pred")
    out = tmp_path / "m.json"
    argv = ["eval", str(tmp_path / "pred"), str(dome_scene / "gt" / "sparse")]
    assert main([*argv, "--output", str(out)]) == 0

    def strict(constant: str) -> None:
        raise ValueError(f"{constant} in the JSON")

    metrics = json.loads(out.read_text(), parse_constant=strict)
    unregistered = [p for p in metrics["pairs"] if not p["registered"]]
    assert unregistered and all(p["rotation_deg"] is None for p in unregistered)
    assert metrics["num_registered"] == len(rec.images) - 1


def test_runtime_errors_exit_1(tmp_path):
    assert main(["eval", str(tmp_path / "nope"), str(tmp_path / "nope2")]) == 1
    assert (
        main(["augment", str(tmp_path / "missing.db"), "--priors", str(tmp_path)]) == 1
    )


def test_summaries_group_images_that_share_a_reason() -> None:
    """A static camera's 19 other instants are one line, not 19; a reason of its
    own keeps its image's name; a long list is counted with its ends."""
    from colmap_vc.cli import MAX_LISTED, _by_reason, _people_links

    why = "static camera cam01: its people are in cam01_f000.jpg's view"
    reasons = {f"cam01_f{k:03d}.jpg": why for k in range(1, 20)}
    reasons["odd.jpg"] = "no person found"
    reasons |= {"a.jpg": "too small", "b.jpg": "too small"}
    lines = dict((reason, names) for names, reason in _by_reason(reasons))
    assert len(lines) == 3
    assert lines[why] == "19 images (cam01_f001.jpg ... cam01_f019.jpg)"
    assert lines["no person found"] == "odd.jpg"
    assert lines["too small"] == "2 images (a.jpg, b.jpg)"
    few = [(0, 1), (1, 0)]
    assert _people_links(few) == "[(0, 1), (1, 0)]"
    many = [(k, k) for k in range(MAX_LISTED + 1)]
    assert _people_links(many) == f"{MAX_LISTED + 1} people linked"
