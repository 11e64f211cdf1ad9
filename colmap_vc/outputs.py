"""Output folders: colmap-vc replaces only a folder it wrote itself.

Every command that writes a folder (``map``, ``synth``, ``demo``) leaves a marker file
in it. ``--overwrite`` removes an existing, non-empty folder only when it holds that
command's marker and none of the command's inputs; anything else is refused with
nothing removed (docs/database.md, "What colmap-vc never does").
"""

from __future__ import annotations

import math
import shutil
from collections.abc import Sequence
from os import PathLike
from pathlib import Path

__all__ = ["jsonable", "marker_name", "prepare_output_dir"]


def marker_name(command: str) -> str:
    """File name of the marker ``command`` writes into its output folder."""
    return f".colmap-vc-{command}"


def prepare_output_dir(
    out_dir: str | PathLike[str],
    command: str,
    *,
    overwrite: bool,
    inputs: Sequence[str | PathLike[str]] = (),
) -> Path:
    """Make ``out_dir`` an empty folder holding ``command``'s marker.

    Raises:
        FileExistsError: ``out_dir`` is a file; or it is not empty and ``overwrite``
            is False, it holds one of ``inputs``, or ``command`` did not write it.
            Nothing is removed in any of these cases.
    """
    out = Path(out_dir)
    option = "--output-path" if command == "map" else "the output folder"
    if out.exists() and not out.is_dir():
        raise FileExistsError(f"{option} {out} is a file, not a folder")
    # A folder holding only the marker is what a failed run of ``command`` left.
    if out.is_dir() and any(p.name != marker_name(command) for p in out.iterdir()):
        if not overwrite:
            raise FileExistsError(f"{out} exists and is not empty (use --overwrite)")
        resolved = out.resolve()
        for path in inputs:
            p = Path(path).resolve()
            if p == resolved or resolved in p.parents:
                raise FileExistsError(
                    f"--overwrite refused: {out} holds the input {path}; choose "
                    "another output folder (nothing was removed)"
                )
        marker = marker_name(command)
        if not (out / marker).is_file():
            raise FileExistsError(
                f"--overwrite refused: {out} was not written by colmap-vc {command} "
                f"(no {marker} marker); remove it yourself or choose another output "
                "folder (nothing was removed)"
            )
        shutil.rmtree(out)
    out.mkdir(parents=True, exist_ok=True)
    (out / marker_name(command)).write_text(
        f"written by colmap-vc {command}; `colmap-vc {command} --overwrite` may "
        "replace this folder\n"
    )
    return out


def jsonable(value: object) -> object:
    """``value`` (dicts, lists, numbers, text; anything else as text) for json.dump;
    a NaN or infinite float is None (JSON has neither)."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if isinstance(value, (str, int, float, bool)) or value is None:
        return value
    return str(value)
