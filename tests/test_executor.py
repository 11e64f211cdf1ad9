"""The per-pair stage on every executor gives the same database (issue 14).

Local processes and a dask.distributed LocalCluster of two workers must write the
same VCs, inliers and two-view geometries as this process alone.
"""

from __future__ import annotations

import shutil
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pytest

from colmap_vc import augment, database
from colmap_vc.executor import (
    ExecutorKind,
    ExecutorOptions,
    ProcessExecutor,
    SerialExecutor,
    open_executor,
)


def _scaled_sums(shared: dict[str, float], chunk: Sequence[int]) -> list[float]:
    return [shared["scale"] * i + shared["offset"] for i in chunk]


def _wrong_length(shared: object, chunk: Sequence[int]) -> list[int]:
    return list(chunk)[:-1]


def test_results_come_back_in_item_order() -> None:
    items = list(range(37))
    shared = {"scale": 2.0, "offset": 0.5}
    want = [2.0 * i + 0.5 for i in items]
    assert SerialExecutor().map(_scaled_sums, shared, items) == want
    ex = ProcessExecutor(workers=2, chunks_per_worker=3)
    try:
        assert ex.map(_scaled_sums, shared, items) == want
        assert ex.map(_scaled_sums, {"scale": -1.0, "offset": 0.0}, items[:5]) == [
            0.0,
            -1.0,
            -2.0,
            -3.0,
            -4.0,
        ]  # a second shared object replaces the first one
        assert ex.map(_scaled_sums, shared, []) == []
    finally:
        ex.close()
    with pytest.raises(RuntimeError, match="returned 3 results for 4 items"):
        SerialExecutor().map(_wrong_length, None, [1, 2, 3, 4])


def test_auto_runs_small_jobs_here_and_dask_needs_a_scheduler() -> None:
    with open_executor(ExecutorOptions(workers=2), num_items=10) as ex:
        assert isinstance(ex, SerialExecutor)
    with open_executor(ExecutorOptions(workers=2), num_items=500) as ex:
        assert isinstance(ex, ProcessExecutor)
    with (
        pytest.raises(ValueError, match="needs --scheduler"),
        open_executor(ExecutorOptions(executor=ExecutorKind.DASK), num_items=1),
    ):
        pass


def _database_content(db: Path) -> dict[str, object]:
    views = database.read_views(db)
    name = dict(zip(views.image_ids.tolist(), views.image_names, strict=True))
    geometries = database.read_two_view_geometries(db)
    return {
        "keypoints": {
            name[int(i)]: database.read_keypoints(db, int(i)).round(6).tolist()
            for i in views.image_ids
        },
        "matches": {
            (name[a], name[b]): m.tolist()
            for (a, b), m in database.read_matches(db).items()
        },
        "inliers": {
            (name[a], name[b]): g.inlier_matches.tolist()
            for (a, b), g in geometries.items()
        },
    }


def test_every_executor_writes_the_same_database(
    dome_scene: Path, tmp_path: Path
) -> None:
    distributed = pytest.importorskip("distributed")
    contents = {}
    runs: dict[str, dict[str, object]] = {
        "serial": {"executor": ExecutorKind.SERIAL},
        "processes": {"executor": ExecutorKind.PROCESSES, "workers": 2},
    }
    with distributed.LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None
    ) as cluster:
        runs["dask"] = {
            "executor": ExecutorKind.DASK,
            "scheduler": cluster.scheduler_address,
        }
        for label, kw in runs.items():
            db = tmp_path / f"{label}.db"
            shutil.copy(dome_scene / "database.db", db)
            summary = augment.run(
                db,
                dome_scene / "priors",
                augment.AugmentOptions(show_progress=False, **kw),  # type: ignore[arg-type]
            )
            assert summary.num_verified_pairs >= 5
            contents[label] = _database_content(db)
    assert contents["processes"] == contents["serial"]
    assert contents["dask"] == contents["serial"]
    assert np.sum([len(v) for v in contents["serial"]["inliers"].values()]) > 0  # type: ignore[union-attr]


def test_auto_stays_here_under_an_unguarded_script(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Spawned workers import __main__: a script that calls augment at top level
    would run again in each of them, so auto does not spawn from such a script."""
    import sys
    import types

    script = tmp_path / "user_script.py"
    script.write_text("from colmap_vc import augment\naugment.run('db', 'priors')\n")
    fake = types.ModuleType("__main__")
    fake.__file__ = str(script)
    monkeypatch.setitem(sys.modules, "__main__", fake)
    with open_executor(ExecutorOptions(workers=2), num_items=500) as ex:
        assert isinstance(ex, SerialExecutor)
    script.write_text(script.read_text() + "if __name__ == '__main__':\n    pass\n")
    with open_executor(ExecutorOptions(workers=2), num_items=500) as ex:
        assert isinstance(ex, ProcessExecutor)
