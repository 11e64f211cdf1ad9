"""COLMAP's own log lines (glog, written to stderr by COLMAP and Ceres).

`colmap-vc` shows COLMAP's warnings and errors (``cli`` sets glog's level), but
not those of the steps it runs itself and reports in its own words: on
people-only problems Ceres writes dozens of "Linear solver failure ... dense
Cholesky" warnings per model (the damped step that follows succeeds; the
robustness sweep counted 163 in one `map`), and COLMAP's mapper "Failed to create
any sparse model" where `map` says it found no model. With ``--verbose`` (the
caller's logger at DEBUG) they are all shown.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator

import pyceres
import pycolmap

GLOGS = (pycolmap.logging, pyceres.logging)
"""The two glog instances: pycolmap's (COLMAP, its mappers and its Ceres) and
pyceres's own (linked into its module: the solves colmap-vc runs through
``pyceres.solve``). Setting one leaves the other as it was."""


def set_min_log_level(level: int) -> None:
    """glog's lowest level written (0 info, 1 warning, 2 error, 3 fatal), in
    both instances."""
    for glog in GLOGS:
        glog.minloglevel = level


@contextlib.contextmanager
def colmap_quiet(logger: logging.Logger) -> Iterator[None]:
    """COLMAP's and Ceres's log lines below FATAL off inside the block, unless
    ``logger`` logs at DEBUG; glog's levels are restored after it. Inside the
    block pyceres's glog writes to stderr only: left as it is, its first lines
    after COLMAP's also open log files in the working folder
    (``.<host>.<user>.log.WARNING.<time>``), which two earlier runs left in
    this repository."""
    levels = [glog.minloglevel for glog in GLOGS]
    to_stderr = pyceres.logging.logtostderr
    pyceres.logging.logtostderr = True
    if not logger.isEnabledFor(logging.DEBUG):
        for glog, level in zip(GLOGS, levels, strict=True):
            glog.minloglevel = max(level, 3)  # FATAL only
    try:
        yield
    finally:
        for glog, level in zip(GLOGS, levels, strict=True):
            glog.minloglevel = level
        pyceres.logging.logtostderr = to_stderr
