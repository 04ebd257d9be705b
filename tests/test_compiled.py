"""The optional compiled build (setup.py, mypyc): a stale build is refused, a fresh one is what runs."""

from __future__ import annotations

import ast
import importlib
import importlib.machinery
import os
import subprocess
import sys

import pytest

from sim_twin.compiled import ROOT, check_fresh, compiled_modules

SUFFIX = importlib.machinery.EXTENSION_SUFFIXES[0]


def test_a_build_older_than_its_source_is_refused(tmp_path) -> None:
    package = tmp_path / "onboard" / "estimation"  # a layer's subpackage, as the compiled modules live
    package.mkdir(parents=True)
    source, build = package / "estimator.py", package / f"estimator{SUFFIX}"
    source.write_text("")
    build.write_bytes(b"")
    (package / f"orphan{SUFFIX}").write_bytes(b"")  # no source beside it: not ours
    os.utime(source, (1000.0, 1000.0))
    os.utime(build, (2000.0, 2000.0))
    assert compiled_modules(tmp_path) == ["onboard.estimation.estimator"]
    check_fresh(tmp_path)
    os.utime(source, (3000.0, 3000.0))  # edited after the build
    with pytest.raises(ImportError, match="onboard.estimation.estimator"):
        check_fresh(tmp_path)


def test_compiled_modules_are_the_ones_imported() -> None:
    names = compiled_modules()
    if not names:
        pytest.skip("no compiled build in this checkout (pip install -e . builds it where a C compiler is found)")
    for name in names:
        assert importlib.import_module(name).__file__.endswith(SUFFIX), name


def test_the_compiled_build_imports_from_any_directory(tmp_path) -> None:
    """Its shared runtime lives in a package, not at the checkout's top, which only a process
    started there has on its path (the archer command, a campaign worker, do not)."""
    names = compiled_modules()
    if not names:
        pytest.skip("no compiled build in this checkout")
    code = f"import importlib; [importlib.import_module(n) for n in {names!r}]"
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=env, check=True, timeout=120)


def _setup_list(name: str) -> list[str]:
    """A list literal of setup.py, read without running setup.py (it would run setuptools)."""
    tree = ast.parse((ROOT / "setup.py").read_text())
    for node in tree.body:
        if isinstance(node, ast.Assign) and any(isinstance(t, ast.Name) and t.id == name for t in node.targets):
            return ast.literal_eval(node.value)
    raise AssertionError(f"setup.py has no {name}")


def test_the_compiled_modules_type_check_as_mypyc_needs() -> None:
    """mypyc builds only what mypy accepts: a type error in a listed module breaks the build
    (it did once: the geometric MPC's setpoint lists returned where tuples were declared)."""
    pytest.importorskip("mypy", reason="mypy comes with the test extra")
    modules = _setup_list("COMPILED_MODULES")
    assert modules and all((ROOT / path).exists() for path in modules)
    done = subprocess.run([sys.executable, "-m", "mypy", "--no-incremental", *_setup_list("MYPYC_FLAGS"), *modules],
                          cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stdout + done.stderr
