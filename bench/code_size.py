"""The bundle-adjustment code's size, now and at a reference revision.

Issue 12 asks that the BA code shrink below the 2.8k lines it had when the GBA was
the package's own numpy Levenberg-Marquardt. A physical line count (`wc -l`)
counts docstrings and comments too, and this package's docstrings carry the
measurements behind its constants. So this counts both: every line, and the lines
that hold code (a token that is not a comment, a docstring or layout).

Two sets of files, at two revisions:

- ``proper``: the adjustment itself (`gba/`, `keypoint_ba.py`,
  `keypoint_tracks.py`; at the reference also `refine.py`, which held the
  refinement's flow).
- ``with checks``: also the camera check and what split from it
  (`camera_check.py`, `label_check.py`, `people_check.py`).
- ``with the up step``: also the cameras' up directions in the refinement
  (`mapping/up.py`, `mapping/people_up.py`), a feature the reference did not have.

    .venv/bin/python bench/code_size.py [--reference REV]

The reference defaults to the parent of f34312d, the last revision with the numpy
GBA (`refine.py` and gba/'s own solver). Writes bench/out/code_size.json and the
section "code-size" of docs/gba.md.
"""

from __future__ import annotations

import argparse
import io
import logging
import subprocess
import tokenize
from collections.abc import Iterable

from common import DOCS, ROOT, replace_section, setup_logging, write_json

logger = logging.getLogger("bench.code_size")

REFERENCE = "f34312d^"
"""The parent of the commit that retired the numpy GBA for COLMAP's Ceres problem."""

SETS = {
    "proper": [
        "colmap_vc/gba/",
        "colmap_vc/keypoint_ba.py",
        "colmap_vc/keypoint_tracks.py",
        "colmap_vc/refine.py",
    ],
    "with checks": [
        "colmap_vc/camera_check.py",
        "colmap_vc/label_check.py",
        "colmap_vc/people_check.py",
    ],
    "with the up step": ["colmap_vc/mapping/up.py", "colmap_vc/mapping/people_up.py"],
}
"""Each set adds its files to the ones before it."""

_LAYOUT = {
    tokenize.COMMENT,
    tokenize.NL,
    tokenize.NEWLINE,
    tokenize.INDENT,
    tokenize.DEDENT,
    tokenize.ENDMARKER,
}


def code_lines(source: str) -> int:
    """Lines holding a token other than a comment, layout or a string statement (a
    docstring, or a bare string between statements)."""
    lines: set[int] = set()
    starts_statement = True
    for tok in tokenize.generate_tokens(io.StringIO(source).readline):
        if tok.type in _LAYOUT:
            starts_statement = starts_statement or tok.type in (
                tokenize.NEWLINE,
                tokenize.INDENT,
                tokenize.DEDENT,
            )
            continue
        if tok.type == tokenize.STRING and starts_statement:
            continue  # a string statement; its own NEWLINE follows
        lines.update(range(tok.start[0], tok.end[0] + 1))
        starts_statement = False
    return len(lines)


def _git(*args: str) -> str:
    return subprocess.run(
        ["git", *args], cwd=ROOT, check=True, capture_output=True, text=True
    ).stdout


def files_at(rev: str, prefixes: Iterable[str]) -> dict[str, str]:
    """The Python files under ``prefixes`` at ``rev`` -> their text."""
    names = _git("ls-tree", "-r", "--name-only", rev, "colmap_vc").split()
    wanted = [
        n
        for n in names
        if n.endswith(".py")
        and any(n == p or (p.endswith("/") and n.startswith(p)) for p in prefixes)
    ]
    return {n: _git("show", f"{rev}:{n}") for n in wanted}


def count(rev: str) -> dict:
    """Per set (cumulative): files, physical lines and code lines at ``rev``."""
    out, prefixes = {}, []
    for name, extra in SETS.items():
        prefixes += extra
        files = files_at(rev, prefixes)
        out[name] = {
            "files": sorted(files),
            "lines": sum(t.count("\n") for t in files.values()),
            "code_lines": sum(code_lines(t) for t in files.values()),
        }
    return out


def table(rows: dict[str, dict]) -> str:
    """Markdown: one row per set, both revisions' counts side by side."""
    (ref, a), (now, b) = rows.items()
    head = (
        f"| files | lines at {ref} | at {now} | code lines at {ref} | at {now} |\n"
        "|---|---|---|---|---|\n"
    )
    body = "".join(
        f"| {name} | {a[name]['lines']} | {b[name]['lines']} | "
        f"{a[name]['code_lines']} | {b[name]['code_lines']} |\n"
        for name in SETS
    )
    return head + body


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--reference", default=REFERENCE)
    parser.add_argument("--no-docs", action="store_true")
    args = parser.parse_args()
    setup_logging()
    ref = _git("rev-parse", "--short", args.reference).strip()
    now = _git("rev-parse", "--short", "HEAD").strip()
    dirty = bool(_git("status", "--porcelain", "colmap_vc").strip())
    if dirty:
        logger.warning("colmap_vc/ has uncommitted changes; counting HEAD as committed")
    rows = {ref: count(ref), now: count(now)}
    write_json("code_size.json", {"revisions": rows})
    text = table(rows)
    logger.info("\n%s", text)
    if not args.no_docs:
        replace_section(
            DOCS / "gba.md",
            "code-size",
            f"`bench/code_size.py` (reference {ref}, the last revision with the "
            "numpy GBA; sets cumulative, as in its docstring):\n\n" + text,
        )


if __name__ == "__main__":
    main()
