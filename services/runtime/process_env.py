"""What every ``archer`` process puts in its environment before numerical libraries load.

``onboard/`` does no I/O of its own; what its libraries read from the environment when
they load is set here, by the process entry point (:func:`services.cli.main.main`), and
an explicit setting in the environment wins:

- ``NUMBA_CACHE_DIR``: compiled numba kernels are cached in the service's cache directory
  (systemd ``CacheDirectory=`` gives ``$CACHE_DIRECTORY``; else ``$XDG_CACHE_HOME/archer``
  or ``~/.cache/archer``), never beside the source (read-only on the robot).
- ``OMP_WAIT_POLICY=PASSIVE``: idle OpenMP threads of numba's parallel kernels that spin
  steal the core the other thread needs on a small, shared machine (a 2-thread cut took
  longer than a 1-thread one); passive waiting fixes that.
- ``OPENBLAS_NUM_THREADS=1``: the stack's matrices are small (the geometric MPC exponentiates
  24 x 24 matrices by the thousand); waking BLAS threads for them on a shared 2-core machine
  made a lockstep run with the MPC 13 times slower (1.5 s of ``archer sim``: 17.2 s of wall
  time against 1.3 s single-threaded).
"""

from __future__ import annotations

import os
from pathlib import Path

APP_CACHE = "archer"


def cache_directory() -> Path:
    """The process's cache directory (see the module docstring)."""
    systemd = os.environ.get("CACHE_DIRECTORY")  # colon-separated when a unit names several
    if systemd:
        return Path(systemd.split(":")[0])
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / APP_CACHE


def prepare_environment() -> None:
    """Before anything imports numba (its configuration is read once, at import)."""
    os.environ.setdefault("NUMBA_CACHE_DIR", str(cache_directory() / "numba"))
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
