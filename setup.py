"""Packaging lives in pyproject.toml; this file only adds the optional compiled build.

``ARCHER_COMPILE=1 python setup.py build_ext --inplace`` (with ``pip install -e '.[compile]'``
first) compiles the modules below with mypyc, next to their sources: the lockstep tick's
scalar-arithmetic modules, which the profile of ``archer sim`` puts on top (docs/twin_speed.md).
mypyc compiles the same source to C with the same IEEE double operations, so runs are bit for
bit the pure-Python ones (tests/test_lockstep_pinned.py holds that in either mode). Without the
variable, or on the robot, nothing is compiled. ``sim_twin.compiled`` refuses a stale build.
"""

import os

from setuptools import setup
from setuptools.command.build_ext import build_ext

COMPILED_MODULES = [
    "onboard/geometry/quaternion.py",
    "onboard/estimation/attitude_filter.py",
    "onboard/estimation/estimator.py",
    "onboard/estimation/com_filter.py",
    "onboard/estimation/phase.py",
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

ext_modules = []
if os.environ.get("ARCHER_COMPILE") == "1":
    from mypyc.build import mypycify

    # the shared runtime of the group inside a package: a top-level module is not importable from every directory
    ext_modules = mypycify(MYPYC_FLAGS + COMPILED_MODULES, opt_level="3", group_name=COMPILED_GROUP)


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
