"""Packaging lives in pyproject.toml; this file only adds the compiled tick.

``pip install .`` or ``pip install -e .`` compiles the modules below with mypyc (a build
requirement, pyproject.toml), next to their sources in an editable install: the lockstep tick's
scalar-arithmetic modules, which the profile of ``archer sim`` puts on top (docs/twin_speed.md),
so campaigns run at the speed the README reports. mypyc compiles the same source to C with the
same IEEE double operations, so runs are bit for bit the pure-Python ones (tests/test_compiled.py
holds that). Where no C compiler is found, mypyc is missing or the build fails, the install goes
on in pure Python (about 2.5 times slower a tick), and ``archer sim``, ``campaign`` and ``bench``
say so in one line. ``ARCHER_COMPILE=0`` installs pure Python on purpose; after editing a
compiled module, rebuild with ``python setup.py build_ext --inplace`` (``sim_twin.compiled``
refuses a stale build).
"""

import os
import shlex
import shutil
import sys
import sysconfig

from setuptools import setup
from setuptools.command.build_ext import build_ext

COMPILED_MODULES = [
    "onboard/geometry/quaternion.py",
    "onboard/estimation/attitude_filter.py",
    "onboard/estimation/estimator.py",
    "onboard/estimation/com_filter.py",
    "onboard/estimation/phase.py",
    "onboard/estimation/input_gate.py",
    "onboard/estimation/leg_model.py",
    "onboard/estimation/contact.py",
    "onboard/estimation/imu_gaps.py",
    "onboard/estimation/position_sources.py",
    "onboard/low_level/tracking/foot_control.py",
    "onboard/low_level/tracking/attitude_control.py",
    "onboard/low_level/tracking/supervisor.py",
    "onboard/low_level/controller.py",
    "onboard/low_level/planning/zdp_policy.py",
    "onboard/low_level/tracking/flip.py",
    "onboard/contracts/reference.py",
    "sim_twin/sensors.py",
    "sim_twin/metrics.py",
    "sim_twin/actuation.py",
]
COMPILED_GROUP = "onboard.compiled_tick"
# mypy checks the compiled modules only; what they import is taken as it is typed
MYPYC_FLAGS = ["--ignore-missing-imports", "--follow-imports=silent"]



def _pure_python(why: str) -> list:
    print(f"archer-onboard: the lockstep tick stays pure Python ({why})", file=sys.stderr)
    return []


def _c_compiler() -> str | None:
    cc = shlex.split(os.environ.get("CC") or sysconfig.get_config_var("CC") or "cc")
    return shutil.which(cc[0]) if cc else None


def compiled_extensions() -> list:
    """The compiled tick's extensions, or none (and one line saying why) where they cannot be built."""
    if os.environ.get("ARCHER_COMPILE") == "0":
        return _pure_python("ARCHER_COMPILE=0")
    try:
        from mypyc.build import mypycify
    except ImportError:
        return _pure_python("mypyc is not installed: pip install mypy")
    if _c_compiler() is None:
        return _pure_python("no C compiler found")
    try:
        # the shared runtime of the group inside a package: a top-level module is not importable from every directory
        extensions = mypycify(MYPYC_FLAGS + COMPILED_MODULES, opt_level="3", group_name=COMPILED_GROUP)
    except (Exception, SystemExit) as exc:  # mypy refused a module: mypyc exits
        return _pure_python(f"mypyc refused the modules: {exc}")
    for extension in extensions:
        extension.optional = True  # a compiler error leaves the pure-Python module in use, with setuptools' warning
    return extensions


ext_modules = compiled_extensions()


class BuildExtStamped(build_ext):
    """Stamps every extension it leaves with the time of the build: mypyc regenerates the C from
    the sources as they are now, but an output whose text did not change is left with its old
    time, and ``sim_twin.compiled`` judges a build by its time (e.g. after a checkout that touched
    the sources without changing them)."""

    def run(self) -> None:
        super().run()
        for ext in self.extensions:
            path = self.get_ext_fullpath(ext.name)  # in the source tree with --inplace
            if os.path.exists(path):
                os.utime(path)


setup(ext_modules=ext_modules, cmdclass={"build_ext": BuildExtStamped})
