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

import pycolmap


@contextlib.contextmanager
def colmap_quiet(logger: logging.Logger) -> Iterator[None]:
    """COLMAP's log lines below FATAL off inside the block, unless ``logger``
    logs at DEBUG; glog's level is restored after it."""
    if logger.isEnabledFor(logging.DEBUG):
        yield
        return
    level = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = max(level, 3)  # FATAL only
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = level
