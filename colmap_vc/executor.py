"""Where the per-pair work runs: this process, local worker processes, or Dask.

A stage hands :meth:`Executor.map` a function ``fn(shared, chunk) -> list`` (a
module-level function, so it pickles), the data every task needs (``shared``: the
observations of every image, say) and its items (image pairs). Items are cut into
chunks; results come back in item order whatever worker ran them, so every executor
gives the same output. ``shared`` is shipped once per worker, not once per task:

- ``processes``: pickled once to a temporary file that each worker loads on first
  use (the machine's cores, :class:`concurrent.futures.ProcessPoolExecutor`);
- ``dask``: scattered once to every worker of a ``dask.distributed`` cluster
  (``pip install "colmap-vc[dask]"``; docs/scaling.md says how to start one).

``auto`` (the default) runs small jobs in this process, where starting workers
(each imports pycolmap: about 2 s) would cost more than it saves.
"""

from __future__ import annotations

import enum
import functools
import itertools
import logging
import multiprocessing
import os
import pickle
import re
import sys
import tempfile
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Future, ProcessPoolExecutor, as_completed
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, TypeVar

from tqdm import tqdm

logger = logging.getLogger(__name__)

S = TypeVar("S")
T = TypeVar("T")
R = TypeVar("R")


class ExecutorKind(enum.StrEnum):
    AUTO = "auto"
    SERIAL = "serial"
    PROCESSES = "processes"
    DASK = "dask"


@dataclass(frozen=True, kw_only=True, slots=True)
class ExecutorOptions:
    """Where the per-pair stages (person links, verification) run."""

    executor: ExecutorKind = ExecutorKind.AUTO
    """auto (local processes for large jobs, this process for small ones), serial,
    processes, or dask (a dask.distributed cluster at --scheduler)."""
    workers: int | None = None
    """Local worker processes (default: the machine's cores)."""
    scheduler: str | None = None
    """Address of a dask.distributed scheduler (e.g. tcp://10.0.0.1:8786), with
    --executor dask."""
    min_parallel_items: int = 200
    """auto: fewer items than this run in this process. Starting a worker imports
    pycolmap (about 2 s); a verified image pair takes about 30 ms, so below a few
    hundred pairs the workers cost more than they save (bench/scale.py)."""
    chunks_per_worker: int = 4
    """Chunks per worker: enough to balance uneven pairs, few enough that the
    per-task overhead stays small."""


class Executor(Protocol):
    def map(
        self,
        fn: Callable[[S, Sequence[T]], list[R]],
        shared: S,
        items: Sequence[T],
        desc: str = "",
    ) -> list[R]: ...


def _chunks(items: Sequence[T], num_chunks: int) -> list[Sequence[T]]:
    num_chunks = max(1, min(num_chunks, len(items)))
    bounds = [round(i * len(items) / num_chunks) for i in range(num_chunks + 1)]
    return [items[a:b] for a, b in itertools.pairwise(bounds)]


def _flatten(parts: list[list[R]], sizes: list[int]) -> list[R]:
    out: list[R] = []
    for part, size in zip(parts, sizes, strict=True):
        if len(part) != size:
            raise RuntimeError(f"a task returned {len(part)} results for {size} items")
        out += part
    return out


@dataclass
class SerialExecutor:
    """Everything in this process (small jobs, debugging)."""

    show_progress: bool = False

    def map(
        self,
        fn: Callable[[S, Sequence[T]], list[R]],
        shared: S,
        items: Sequence[T],
        desc: str = "",
    ) -> list[R]:
        chunks = _chunks(items, max(1, len(items) // 16))
        parts = [
            fn(shared, c)
            for c in tqdm(
                chunks, desc=desc, disable=not self.show_progress, leave=False
            )
        ]
        return _flatten(parts, [len(c) for c in chunks])


@functools.lru_cache(maxsize=2)
def _load_shared(path: str) -> Any:
    with open(path, "rb") as f:
        return pickle.load(f)


def _run_with_file(
    fn: Callable[[Any, Sequence[T]], list[R]], path: str, chunk: Sequence[T]
) -> list[R]:
    return fn(_load_shared(path), chunk)


def _collect(
    futures: list[Any], done: Iterator[Any], desc: str, show_progress: bool
) -> None:
    for _ in tqdm(
        done, total=len(futures), desc=desc, disable=not show_progress, leave=False
    ):
        pass


@dataclass
class ProcessExecutor:
    """Local worker processes (spawned: no state inherited from this process)."""

    workers: int
    chunks_per_worker: int = 4
    show_progress: bool = False
    _pool: ProcessPoolExecutor | None = None
    _tmp: tempfile.TemporaryDirectory[str] | None = None
    _count: int = 0

    def map(
        self,
        fn: Callable[[S, Sequence[T]], list[R]],
        shared: S,
        items: Sequence[T],
        desc: str = "",
    ) -> list[R]:
        if not items:
            return []
        if self._pool is None:
            self._pool = ProcessPoolExecutor(
                self.workers, mp_context=multiprocessing.get_context("spawn")
            )
            self._tmp = tempfile.TemporaryDirectory(prefix="colmap_vc_")
        assert self._tmp is not None
        self._count += 1
        path = str(Path(self._tmp.name) / f"shared_{self._count}.pkl")
        with open(path, "wb") as f:
            pickle.dump(shared, f, protocol=pickle.HIGHEST_PROTOCOL)
        chunks = _chunks(items, self.workers * self.chunks_per_worker)
        futures: list[Future[list[R]]] = [
            self._pool.submit(_run_with_file, fn, path, c) for c in chunks
        ]
        _collect(futures, as_completed(futures), desc, self.show_progress)
        return _flatten([f.result() for f in futures], [len(c) for c in chunks])

    def close(self) -> None:
        if self._pool is not None:
            # On an error or Ctrl-C the chunks not yet started are dropped.
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None
        if self._tmp is not None:
            self._tmp.cleanup()
            self._tmp = None


@dataclass
class DaskExecutor:
    """Tasks on a dask.distributed cluster; ``shared`` is scattered once."""

    client: Any
    chunks_per_worker: int = 4
    show_progress: bool = False

    def map(
        self,
        fn: Callable[[S, Sequence[T]], list[R]],
        shared: S,
        items: Sequence[T],
        desc: str = "",
    ) -> list[R]:
        from distributed import as_completed as dask_completed

        if not items:
            return []
        workers = max(1, len(self.client.scheduler_info().get("workers", {})))
        shared_future = self.client.scatter(shared, broadcast=True, hash=False)
        chunks = _chunks(items, workers * self.chunks_per_worker)
        futures = [
            self.client.submit(fn, shared_future, list(c), pure=False) for c in chunks
        ]
        _collect(futures, dask_completed(futures), desc, self.show_progress)
        parts = self.client.gather(futures)
        self.client.cancel([shared_future])
        return _flatten(parts, [len(c) for c in chunks])


def check_options(options: ExecutorOptions) -> None:
    """Raise before any work when ``options`` cannot run (ValueError, RuntimeError)."""
    kind = ExecutorKind(options.executor)
    if options.workers is not None and options.workers < 1:
        raise ValueError(f"--workers {options.workers}: at least 1")
    if kind is not ExecutorKind.DASK:
        return
    if not options.scheduler:
        raise ValueError(
            "--executor dask needs --scheduler ADDRESS (a dask.distributed "
            "scheduler, e.g. tcp://10.0.0.1:8786; docs/scaling.md)"
        )
    try:
        import distributed  # noqa: F401
    except ImportError as e:
        raise RuntimeError(
            "--executor dask needs dask.distributed: pip install 'colmap-vc[dask]'"
        ) from e


def _dask_client(scheduler: str) -> Any:
    from distributed import Client

    try:
        return Client(scheduler, timeout="10s")
    except OSError as e:
        raise RuntimeError(
            f"no dask.distributed scheduler answers at {scheduler}: {e} "
            "(docs/scaling.md says how to start one)"
        ) from e


def main_module_is_guarded() -> bool:
    """Whether spawned workers can import ``__main__`` without running it again.

    A spawned worker imports the main script; one that calls colmap-vc at top level,
    without ``if __name__ == "__main__":``, would run again in every worker. The
    CLI, notebooks and guarded scripts are safe; ``auto`` stays in this process for
    any other script (``executor="processes"`` asks for workers regardless).
    """
    main = sys.modules.get("__main__")
    path = getattr(main, "__file__", None)
    if not path:
        return True  # interactive or notebook: nothing to re-run
    try:
        source = Path(path).read_text(errors="replace")
    except OSError:
        return False
    return re.search(r"__name__\s*==\s*[\"']__main__[\"']", source) is not None


@contextmanager
def open_executor(
    options: ExecutorOptions, num_items: int, show_progress: bool = False
) -> Iterator[Executor]:
    """The executor ``options`` ask for, sized for ``num_items`` items."""
    check_options(options)
    kind = ExecutorKind(options.executor)
    workers = options.workers or os.cpu_count() or 1
    if kind is ExecutorKind.AUTO:
        kind = (
            ExecutorKind.PROCESSES
            if workers > 1
            and num_items >= options.min_parallel_items
            and main_module_is_guarded()
            else ExecutorKind.SERIAL
        )
    if kind is ExecutorKind.SERIAL:
        yield SerialExecutor(show_progress)
    elif kind is ExecutorKind.PROCESSES:
        logger.info("per-pair stages on %d local worker processes", workers)
        ex = ProcessExecutor(workers, options.chunks_per_worker, show_progress)
        try:
            yield ex
        finally:
            ex.close()
    else:
        client = _dask_client(str(options.scheduler))
        logger.info("per-pair stages on the dask cluster at %s", options.scheduler)
        try:
            yield DaskExecutor(client, options.chunks_per_worker, show_progress)
        finally:
            client.close()
