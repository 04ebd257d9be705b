"""Which modules run compiled (mypyc, ``setup.py``), and a refusal to run a stale build.

A compiled module lies next to its source (``estimator.cpython-311-x86_64-linux-gnu.so``
beside ``estimator.py``) and Python imports it in place of the source. One older than its
source was built from another text: importing it would run code that is not in the file
(an edit, a checkout of another branch). The lockstep runner refuses such a build rather than
run it; rebuild (``ARCHER_COMPILE=1 python setup.py build_ext --inplace``) or delete it.
"""

from __future__ import annotations

import importlib.machinery
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("onboard", "sim_twin", "robot_description")  # where setup.py may compile modules


def _builds(root: Path) -> list[tuple[str, Path, Path]]:
    """(module, extension, source) for each extension module with a source beside it."""
    found = []
    for package in PACKAGES:
        for suffix in importlib.machinery.EXTENSION_SUFFIXES:
            for ext in sorted((root / package).glob(f"*{suffix}")):
                source = ext.with_name(ext.name[: -len(suffix)] + ".py")
                if source.exists():
                    found.append((f"{package}.{source.stem}", ext, source))
    return found


def compiled_modules(root: Path = ROOT) -> list[str]:
    """The modules this checkout imports compiled."""
    return [name for name, _, _ in _builds(root)]


def _built_at(root: Path, ext: Path) -> float:
    """When ``ext``'s code was built: a module's own extension is a shim into the group's shared
    library (``*__mypyc*``), which holds the code; a rebuild rewrites the library but leaves a shim
    whose text did not change as old as it was."""
    group = [lib.stat().st_mtime for package in PACKAGES for suffix in importlib.machinery.EXTENSION_SUFFIXES
             for lib in (root / package).glob(f"*__mypyc{suffix}")]
    return max([ext.stat().st_mtime, *group])


def check_fresh(root: Path = ROOT) -> None:
    """Raise ImportError naming every compiled module older than its source."""
    stale = [f"{name} ({ext.name})" for name, ext, source in _builds(root) if _built_at(root, ext) < source.stat().st_mtime]
    if stale:
        raise ImportError(f"compiled modules older than their sources: {', '.join(stale)}; rebuild them with "
                          "ARCHER_COMPILE=1 python setup.py build_ext --inplace, or delete them")
