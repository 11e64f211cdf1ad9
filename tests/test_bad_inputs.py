"""The bad-input matrix (issue 13): every case is one command line a user might type.

Each case sets up a project (a copy of the 6-view synthetic scene, augmented or
not), breaks one thing, runs ``colmap-vc`` in-process and checks:

- the exit code (README.md: 1 input/file/data, 2 usage, 130 Ctrl-C, 143 SIGTERM);
- one clear line naming what is wrong (a fragment of the expected message);
- no traceback on stdout or stderr (only ``--verbose`` shows one);
- the database is byte-for-byte what it was before the command, and no file of
  the project (images, priors, ground truth) was removed or changed.

The last tests interrupt real processes (SIGTERM) and in-process work (Ctrl-C,
disk full) inside the database transaction.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import signal
import sqlite3
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import pycolmap
import pytest

from colmap_vc import database
from colmap_vc.cli import main


@dataclass(frozen=True)
class Case:
    name: str
    argv: Callable[[Path], list[str]]  # project folder -> command line
    fragment: str  # expected in the output (case-insensitive)
    code: int = 1
    setup: Callable[[Path], None] = lambda project: None
    augmented: bool = False
    changes: tuple[str, ...] = field(default=())  # files the command may change


def _write(path: str, data: bytes | str) -> Callable[[Path], None]:
    def setup(project: Path) -> None:
        target = project / path
        target.parent.mkdir(parents=True, exist_ok=True)
        if isinstance(data, str):
            target.write_text(data)
        else:
            target.write_bytes(data)

    return setup


def _sql(*statements: str) -> Callable[[Path], None]:
    def setup(project: Path) -> None:
        conn = sqlite3.connect(project / "database.db")
        for statement in statements:
            conn.execute(statement)
        conn.commit()
        conn.close()

    return setup


def _renamed_model(src: Path, dst: Path) -> None:
    """The model at ``src`` with every image renamed, written to ``dst``."""
    rec = pycolmap.Reconstruction(src)
    for image in rec.images.values():
        image.name = "other_" + image.name
    dst.mkdir(parents=True)
    rec.write(dst)


def _corrupt_page(project: Path) -> None:
    db = project / "database.db"
    data = bytearray(db.read_bytes())
    page = int.from_bytes(data[16:18], "big") or 65536
    data[page : 3 * page] = b"\xa5" * (2 * page)  # two b-tree pages of garbage
    db.write_bytes(bytes(data))


def _truncate(project: Path) -> None:
    db = project / "database.db"
    db.write_bytes(db.read_bytes()[:5000])


def _priors_json(edit: Callable[[dict], None]) -> Callable[[Path], None]:
    def setup(project: Path) -> None:
        path = project / "priors" / "priors.json"
        doc = json.loads(path.read_text())
        edit(doc)
        path.write_text(json.dumps(doc))

    return setup


def _first_image_file(doc: dict) -> None:
    first = next(iter(doc["images"].values()))
    first["file"] = "images/missing.npz"


def _rematch(project: Path) -> None:
    """The user re-matches after augment: every pair row is rewritten."""
    conn = sqlite3.connect(project / "database.db")
    conn.execute(
        "UPDATE matches SET data = substr(data, 1, 8 * (rows - 1)), "
        "rows = rows - 1 WHERE rows > 1"
    )
    conn.commit()
    conn.close()


def _reextract(project: Path) -> None:
    """The user re-extracts one image's features after augment."""
    conn = sqlite3.connect(project / "database.db")
    conn.execute(
        "UPDATE keypoints SET data = zeroblob(length(data)) WHERE "
        "image_id = (SELECT MIN(image_id) FROM keypoints)"
    )
    conn.commit()
    conn.close()


def _marked_output(project: Path) -> None:
    (project / "sparse" / "0").mkdir(parents=True)


def _augment(p: Path, *extra: str) -> list[str]:
    return ["augment", str(p / "database.db"), "--priors", str(p / "priors"), *extra]


def _strip(p: Path, *extra: str) -> list[str]:
    return ["strip", str(p / "database.db"), *extra]


def _map(p: Path, *extra: str) -> list[str]:
    return [
        "map",
        str(p / "database.db"),
        "--image-path",
        str(p / "images"),
        "--output-path",
        str(p / "sparse"),
        *extra,
    ]


CASES = [
    # ------------------------------------------------------------ usage (exit 2)
    Case("no command", lambda p: [], "", code=2),
    Case("unknown command", lambda p: ["mapp"], "", code=2),
    Case("unknown option", lambda p: [*_augment(p), "--no-such"], "", code=2),
    Case("map without paths", lambda p: ["map", str(p / "database.db")], "", code=2),
    Case("bad enum", lambda p: [*_map(p), "--mapper", "magic"], "", code=2),
    # ------------------------------------------------------------ the database
    Case(
        "augment: no database",
        lambda p: ["augment", str(p / "nope.db"), "--priors", str(p / "priors")],
        "database not found",
    ),
    Case(
        "augment: database is a folder",
        lambda p: ["augment", str(p / "images"), "--priors", str(p / "priors")],
        "database not found",
    ),
    Case(
        "augment: text file",
        _augment,
        "not a SQLite database",
        setup=_write("database.db", "id,name\n1,cam00.jpg\n"),
    ),
    Case(
        "augment: empty file",
        _augment,
        "not a COLMAP database",
        setup=_write("database.db", b""),
    ),
    Case(
        "augment: SQLite but not COLMAP",
        _augment,
        "not a COLMAP database",
        setup=lambda p: (
            (p / "database.db").unlink(),
            sqlite3.connect(p / "database.db").execute("CREATE TABLE t (x)").close(),
        ),
    ),
    Case("augment: truncated database", _augment, "database.db", setup=_truncate),
    Case("augment: corrupt page", _augment, "damaged", setup=_corrupt_page),
    Case(
        "augment: no keypoints",
        _augment,
        "no keypoints",
        setup=_sql("DELETE FROM keypoints"),
    ),
    Case(
        "augment: images table dropped",
        _augment,
        "not a COLMAP database",
        setup=_sql("DROP TABLE images"),
    ),
    Case(
        "augment: a colmap-vc backup table dropped",
        _augment,
        "colmap_vc_backup_features are missing",
        augmented=True,
        setup=_sql("DROP TABLE colmap_vc_backup_features"),
    ),
    Case(
        "strip: a colmap-vc table dropped",
        _strip,
        "colmap_vc_images are missing",
        augmented=True,
        setup=_sql("DROP TABLE colmap_vc_images"),
    ),
    Case(
        "augment: re-matched after augment",
        _augment,
        "strip --force",
        augmented=True,
        setup=_rematch,
    ),
    # ------------------------------------------------------------ the priors
    Case(
        "augment: no priors",
        lambda p: [*_augment(p)[:2], "--priors", str(p / "none")],
        "none",
    ),
    Case(
        "augment: priors folder without priors.json",
        _augment,
        "priors.json",
        setup=lambda p: (p / "priors" / "priors.json").unlink(),
    ),
    Case(
        "augment: priors.json not JSON",
        _augment,
        "priors.json",
        setup=_write("priors/priors.json", "{not json"),
    ),
    Case(
        "augment: priors version",
        _augment,
        "version",
        setup=_priors_json(lambda d: d.update(version=99)),
    ),
    Case(
        "augment: priors array file missing",
        _augment,
        "missing.npz",
        setup=_priors_json(_first_image_file),
    ),
    Case(
        "augment: priors of no database image",
        _augment,
        "not in the database",
        setup=_priors_json(
            lambda d: d.update(images={f"ghost/{k}": v for k, v in d["images"].items()})
        ),
    ),
    Case(
        "augment: image path nowhere",
        lambda p: [*_augment(p), "--image-path", str(p / "nowhere")],
        "image folder not found",
    ),
    Case(
        "augment: static-cameras bad regex",
        lambda p: [*_augment(p), "--static-cameras", "(cam"],
        "static",
    ),
    Case(
        "augment: static-cameras without group",
        lambda p: [*_augment(p), "--static-cameras", "cam"],
        "group",
    ),
    Case(
        "augment: static-cameras matches nothing",
        lambda p: [*_augment(p), "--static-cameras", "(xyz)"],
        "static",
    ),
    Case(
        "augment: dask without a scheduler",
        lambda p: [*_augment(p), "--executor", "dask"],
        "--scheduler",
    ),
    Case(
        "augment: dask scheduler that does not answer",
        lambda p: [
            *_augment(p),
            "--executor",
            "dask",
            "--scheduler",
            "tcp://127.0.0.1:9",
        ],
        "no dask.distributed scheduler answers",
    ),
    Case(
        "augment: zero workers",
        lambda p: [*_augment(p), "--workers", "0"],
        "at least 1",
    ),
    Case("augment: database locked", _augment, "locked"),  # see test below
    # ------------------------------------------------------------ map
    Case(
        "map: no database",
        lambda p: [
            "map",
            str(p / "nope.db"),
            "--image-path",
            str(p / "images"),
            "--output-path",
            str(p / "sparse"),
        ],
        "not found",
    ),
    Case(
        "map: no image folder",
        lambda p: [
            "map",
            str(p / "database.db"),
            "--image-path",
            str(p / "nowhere"),
            "--output-path",
            str(p / "sparse"),
        ],
        "image folder not found",
    ),
    Case(
        "map: an image folder without the database's images",
        lambda p: [*_map(p)[:3], str(p / "gt"), *_map(p)[4:]],
        "none of the database's",
    ),
    Case(
        "map: output is a file",
        _map,
        "is a file",
        setup=_write("sparse", "not a folder"),
    ),
    Case(
        "map: output not empty",
        _map,
        "--overwrite",
        setup=_write("sparse/notes.txt", "mine"),
    ),
    Case(
        "map: --overwrite a folder map did not write",
        lambda p: [*_map(p), "--overwrite"],
        "not written by colmap-vc",
        setup=_write("sparse/notes.txt", "mine"),
    ),
    Case(
        "map: --overwrite the project folder",
        lambda p: [*_map(p)[:5], str(p), "--overwrite"],
        "holds the input",
    ),
    Case(
        "map: --overwrite the image folder",
        lambda p: [*_map(p)[:5], str(p / "images"), "--overwrite"],
        "holds the input",
    ),
    Case(
        "map: priors missing", lambda p: [*_map(p), "--priors", str(p / "none")], "none"
    ),
    # ------------------------------------------------------------ strip
    Case("strip: no database", lambda p: ["strip", str(p / "nope.db")], "not found"),
    Case(
        "strip: plain database",
        lambda p: ["strip", str(p / "database.db")],
        "nothing to strip",
        code=0,
    ),
    Case(
        "strip: re-matched after augment",
        lambda p: ["strip", str(p / "database.db")],
        "strip --force",
        augmented=True,
        setup=_rematch,
    ),
    Case(
        "strip: re-extracted after augment",
        lambda p: ["strip", str(p / "database.db")],
        "keypoints of 1 image(s) changed",
        augmented=True,
        setup=_reextract,
    ),
    Case(
        "strip: corrupt page",
        lambda p: ["strip", str(p / "database.db")],
        "damaged",
        setup=_corrupt_page,
    ),
    # ------------------------------------------------------------ eval, report
    Case(
        "eval: no model",
        lambda p: ["eval", str(p / "none"), str(p / "gt" / "sparse")],
        "model folder not found",
    ),
    Case(
        "eval: no model in folder",
        lambda p: ["eval", str(p / "images"), str(p / "gt" / "sparse")],
        "no COLMAP model",
    ),
    Case(
        "eval: output folder missing",
        lambda p: [
            "eval",
            str(p / "gt" / "sparse"),
            str(p / "gt" / "sparse"),
            "--output",
            str(p / "no" / "m.json"),
        ],
        "no/m.json",
    ),
    Case(
        "eval: output is a folder",
        lambda p: [
            "eval",
            str(p / "gt" / "sparse"),
            str(p / "gt" / "sparse"),
            "--output",
            str(p / "images"),
        ],
        "is a folder",
    ),
    Case(
        "eval: a model of other images",
        lambda p: ["eval", str(p / "other"), str(p / "gt" / "sparse")],
        "none of the",
        setup=lambda p: _renamed_model(p / "gt" / "sparse", p / "other"),
    ),
    Case(
        "report: no database",
        lambda p: ["report", str(p / "nope.db"), "--image-path", str(p / "images")],
        "not found",
    ),
    Case(
        "report: model missing",
        lambda p: [
            "report",
            str(p / "database.db"),
            "--image-path",
            str(p / "images"),
            "--model-path",
            str(p / "none"),
            "--output",
            str(p / "r.html"),
        ],
        "none",
    ),
    # ------------------------------------------------------------ priors, synth
    Case(
        "priors: no image folder",
        lambda p: ["priors", str(p / "nowhere"), "--output", str(p / "p2")],
        "does not exist",
    ),
    Case(
        "priors: into the image folder",
        lambda p: ["priors", str(p / "images"), "--output", str(p / "images")],
        "inside the image folder",
    ),
    Case(
        "priors: over existing priors",
        lambda p: ["priors", str(p / "images"), "--output", str(p / "priors")],
        "holds priors already",
    ),
    Case(
        "priors: into a folder of other files",
        lambda p: ["priors", str(p / "images"), "--output", str(p / "gt")],
        "holds no priors.json",
    ),
    Case(
        "priors: empty folder",
        lambda p: ["priors", str(p / "empty"), "--output", str(p / "p2")],
        "no images",
        setup=lambda p: (p / "empty").mkdir(),
    ),
    Case(
        "priors: only a 0-byte image",
        lambda p: ["priors", str(p / "zero"), "--output", str(p / "p2")],
        "can be read",
        setup=_write("zero/a.jpg", b""),
    ),
    Case(
        "priors: database missing",
        lambda p: [
            "priors",
            str(p / "images"),
            "--output",
            str(p / "p2"),
            "--database",
            str(p / "nope.db"),
        ],
        "does not exist",
    ),
    Case(
        "synth: unknown preset",
        lambda p: ["synth", "cathedral", str(p / "s")],
        "cathedral",
    ),
    Case("synth: into the project", lambda p: ["synth", "dome", str(p)], "--overwrite"),
    Case(
        "synth: --overwrite the project",
        lambda p: ["synth", "dome", str(p), "--overwrite"],
        "not written by colmap-vc synth",
    ),
    Case(
        "demo: --overwrite the project",
        lambda p: ["demo", str(p), "--overwrite"],
        "not written by colmap-vc demo",
    ),
    Case(
        "frames: no video",
        lambda p: ["frames", str(p / "none.mp4"), "--output", str(p / "f")],
        "none.mp4",
    ),
    Case(
        "frames: not a video",
        lambda p: ["frames", str(p / "gt" / "persons.json"), "--output", str(p / "f")],
        "persons.json",
    ),
]


def _snapshot(project: Path) -> dict[str, str]:
    """Digest of every file of the project (what a run must never lose)."""
    return {
        str(f.relative_to(project)): hashlib.sha256(f.read_bytes()).hexdigest()
        for f in sorted(project.rglob("*"))
        if f.is_file()
    }


@pytest.fixture(scope="module")
def projects(dome_scene: Path, tmp_path_factory: pytest.TempPathFactory) -> dict:
    """The scene as a user's project, plain and augmented (made once)."""
    root = tmp_path_factory.mktemp("projects")
    out = {}
    for kind in ("plain", "augmented"):
        project = root / kind
        project.mkdir()
        shutil.copyfile(dome_scene / "database.db", project / "database.db")
        shutil.copytree(dome_scene / "images", project / "images")
        shutil.copytree(dome_scene / "priors", project / "priors")
        shutil.copytree(dome_scene / "gt" / "sparse", project / "gt" / "sparse")
        shutil.copyfile(
            dome_scene / "gt" / "persons.json", project / "gt" / "persons.json"
        )
        if kind == "augmented":
            assert main(_augment(project)) == 0
        out[kind] = project
    return out


def _project(projects: dict, case: Case, tmp_path: Path) -> Path:
    project = tmp_path / "project"
    shutil.copytree(projects["augmented" if case.augmented else "plain"], project)
    return project


def _run(argv: list[str], capfd: pytest.CaptureFixture[str]) -> tuple[int, str]:
    code = main(argv)
    out, err = capfd.readouterr()
    return code, out + err


@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_bad_input(
    case: Case, projects: dict, tmp_path: Path, capfd, monkeypatch
) -> None:
    project = _project(projects, case, tmp_path)
    case.setup(project)
    before = _snapshot(project)
    capfd.readouterr()
    holder = None
    if case.name == "augment: database locked":
        holder = sqlite3.connect(project / "database.db", isolation_level=None)
        holder.execute("BEGIN IMMEDIATE")
    try:
        code, output = _run(case.argv(project), capfd)
    finally:
        if holder is not None:
            holder.execute("ROLLBACK")
            holder.close()
    assert code == case.code, output
    assert "Traceback" not in output, output
    if case.code != 2:
        assert case.fragment.lower() in output.lower(), output
        if case.code == 1:
            errors = [line for line in output.splitlines() if " ERROR]" in line]
            assert len(errors) == 1, output
    after = _snapshot(project)
    lost_or_changed = {k for k, v in before.items() if after.get(k) != v}
    assert not lost_or_changed, lost_or_changed


def test_map_names_the_users_database_and_runs_again(
    projects: dict, tmp_path: Path, capfd
) -> None:
    # map works on a copy of the database; its errors name the user's file, and
    # the output folder a failed run left (only its marker) takes the next run
    # without --overwrite.
    project = _project(projects, CASES[0], tmp_path)
    _sql("DELETE FROM keypoints")(project)
    for _ in range(2):
        code, output = _run(_map(project), capfd)
        assert code == 1, output
        assert f"{project / 'database.db'} has no keypoints" in output, output
        assert ".work-" not in output and "--overwrite" not in output, output


def test_matrix_is_large_enough() -> None:
    assert len(CASES) >= 40


def test_verbose_shows_the_traceback(projects: dict, tmp_path: Path, capfd) -> None:
    project = _project(projects, CASES[0], tmp_path)
    _write("database.db", b"")(project)
    code, output = _run([*_augment(project), "--verbose"], capfd)
    assert code == 1 and "Traceback" in output and "not a COLMAP database" in output


def test_read_only_database_refused_before_the_work(
    projects: dict, tmp_path: Path, capfd, monkeypatch
) -> None:
    """A read-only database is refused at once, not after the VCs were computed.

    Runs as any user: the permission check is os.access, patched here because root
    (CI containers) may write read-only files.
    """
    project = _project(projects, CASES[0], tmp_path)
    db = project / "database.db"
    real_access = os.access
    monkeypatch.setattr(
        os,
        "access",
        lambda path, mode, **kw: (
            False
            if Path(path) == db and mode == os.W_OK
            else real_access(path, mode, **kw)
        ),
    )
    before = _snapshot(project)
    start = time.perf_counter()
    code, output = _run(_augment(project), capfd)
    assert code == 1 and "read-only" in output and "Traceback" not in output
    assert time.perf_counter() - start < 2.0  # no VC computed first
    # SQLite's read-only connection to a WAL database leaves its -wal/-shm side
    # files (it may not delete them); the database itself is byte-identical.
    after = {
        k: v for k, v in _snapshot(project).items() if not k.endswith(("-wal", "-shm"))
    }
    assert after == before


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes read-only files")
def test_read_only_database_real_permissions(
    projects: dict, tmp_path: Path, capfd
) -> None:
    project = _project(projects, CASES[0], tmp_path)
    (project / "database.db").chmod(0o444)
    code, output = _run(_augment(project), capfd)
    assert code == 1 and "read-only" in output


def test_map_and_report_never_write_the_database(
    projects: dict, tmp_path: Path, capfd
) -> None:
    """Reading never writes: byte-identical database after map, report and eval."""
    project = _project(projects, Case("", _map, "", augmented=True), tmp_path)
    before = _snapshot(project)
    code, output = _run(_map(project), capfd)
    assert code == 0, output
    report = tmp_path / "report.html"
    assert (
        main(
            [
                "report",
                str(project / "database.db"),
                "--image-path",
                str(project / "images"),
                "--model-path",
                str(project / "sparse" / "0"),
                "--output",
                str(report),
            ]
        )
        == 0
    )
    after = _snapshot(project)
    assert {k: after[k] for k in before} == before
    with sqlite3.connect(project / "database.db") as conn:
        tables = {r[0] for r in conn.execute("SELECT name FROM sqlite_master")}
    assert not any(t.startswith("sqlite_stat") for t in tables)
    assert not [p for p in (project / "sparse").iterdir() if p.name.startswith(".work")]


@pytest.mark.parametrize("failure", ["ctrl-c", "disk full"])
def test_failure_inside_the_write_leaves_the_database(
    failure: str, projects: dict, tmp_path: Path, capfd, monkeypatch
) -> None:
    """Ctrl-C or a full disk in the middle of augment's transaction: rolled back,
    one line saying so, exit 130 / 1."""
    from colmap_vc import database_write

    project = _project(projects, CASES[0], tmp_path)
    before = _snapshot(project)
    exc = (
        KeyboardInterrupt()
        if failure == "ctrl-c"
        else OSError(28, "No space left on device", str(project / "database.db"))
    )

    def fail(*args, **kwargs):
        raise exc

    monkeypatch.setattr(database_write, "write_metadata", fail)
    code, output = _run(_augment(project), capfd)
    assert "Traceback" not in output
    if failure == "ctrl-c":
        assert code == 130 and "is unchanged" in output
    else:
        assert code == 1 and "no space left" in output
    assert _snapshot(project) == before
    assert not database.COMMITTED or all(
        p.resolve() != (project / "database.db").resolve() for p in database.COMMITTED
    )


def test_sigterm_leaves_the_database_and_says_so(
    projects: dict, tmp_path: Path
) -> None:
    """A real process gets SIGTERM mid-augment: exit 143, one line, no stack dump."""
    project = _project(projects, CASES[0], tmp_path)
    before = _snapshot(project)
    proc = subprocess.Popen(
        [sys.executable, "-m", "colmap_vc.cli", *_augment(project)],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
    )
    assert proc.stdout is not None
    seen = b""
    while b"observe" not in seen:  # imports done, the VCs being computed
        chunk = os.read(proc.stdout.fileno(), 4096)
        assert chunk, seen.decode()
        seen += chunk
    proc.send_signal(signal.SIGTERM)
    rest, _ = proc.communicate(timeout=60)
    output = (seen + rest).decode()
    assert proc.returncode == 143, output
    assert "SIGTERM" in output and "unchanged" in output, output
    assert "Traceback" not in output and "@ 0x" not in output, output
    assert _snapshot(project) == before
