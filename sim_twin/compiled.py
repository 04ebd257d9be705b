"""Which modules run compiled (mypyc, ``setup.py``), and a refusal to run a stale build.

A compiled module lies next to its source (``estimator.cpython-311-x86_64-linux-gnu.so``
beside ``estimator.py``) and Python imports it in place of the source. One older than its
source was built from another text: importing it would run code that is not in the file
(an edit, a checkout of another branch). The lockstep runner refuses such a build rather than
run it; rebuild (``python setup.py build_ext --inplace``, or ``pip install -e .`` again) or delete it.
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
            for ext in sorted((root / package).rglob(f"*{suffix}")):  # the layers are subpackages
                source = ext.with_name(ext.name[: -len(suffix)] + ".py")
                if source.exists():
                    found.append((".".join(source.relative_to(root).with_suffix("").parts), ext, source))
    return found


def compiled_modules(root: Path = ROOT) -> list[str]:
    """The modules this checkout imports compiled."""
    return [name for name, _, _ in _builds(root)]


def check_fresh(root: Path = ROOT) -> None:
    """Raise ImportError naming every compiled module older than its source."""
    stale = [f"{name} ({ext.name})" for name, ext, source in _builds(root) if ext.stat().st_mtime < source.stat().st_mtime]
    if stale:
        raise ImportError(f"compiled modules older than their sources: {', '.join(stale)}; rebuild them with "
                          "python setup.py build_ext --inplace (or pip install -e . again), or delete them")
