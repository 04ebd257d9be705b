"""``onboard/`` is pure: importing and running it leaves the process's environment, OpenCV's
global random state and the source tree as they were; numba caches where the process says.

Each check runs in a fresh interpreter, as a service process starts: what a module does
at import shows only the first time it is imported.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PROBE = r"""
import json, os, pkgutil, importlib, sys
import cv2
import numpy as np
import onboard
before = dict(os.environ)
for info in pkgutil.walk_packages(onboard.__path__, "onboard."):
    importlib.import_module(info.name)
changed = sorted(k for k in set(before) | set(os.environ) if before.get(k) != os.environ.get(k))

from onboard.contracts.params import PerceptionParams
from onboard.perception import maps
from onboard.perception.decomposition import decompose_free_space
from onboard.perception.obstacles import obstacles_from_mask

def draws():
    out = np.zeros(8, np.float64)
    cv2.randu(out, 0.0, 1.0)
    return out.tolist()

world = maps.BUILDERS["clutter"](seed=3)
params = PerceptionParams(seed=5)
cv2.setRNGSeed(1234)
expected = draws()
cv2.setRNGSeed(1234)
obstacles_from_mask(world.occupied, 0.05, (0.0, 0.0), params)
decompose_free_space(~world.occupied, 0.05, (0.0, 0.0), params, start=(1.0, 1.0))
print(json.dumps({"env_changed": changed, "cv2_rng_untouched": draws() == expected}))
"""


def _numba_files(under: Path) -> set[Path]:
    return {p for p in under.rglob("*") if p.suffix in (".nbi", ".nbc")}


def test_importing_and_running_onboard_touches_no_global_state_and_no_source_file(tmp_path):
    cache = tmp_path / "numba"
    env = {k: v for k, v in os.environ.items() if k not in ("NUMBA_CACHE_DIR", "OMP_WAIT_POLICY")}
    env["NUMBA_CACHE_DIR"] = str(cache)
    in_tree_before = {p: p.stat().st_mtime for p in _numba_files(ROOT / "onboard")}
    started = time.time()
    out = subprocess.run([sys.executable, "-c", PROBE], cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    report = json.loads(out.stdout.strip().splitlines()[-1])
    assert report["env_changed"] == []  # e.g. OMP_WAIT_POLICY is the entry point's to set
    assert report["cv2_rng_untouched"]  # seeds are passed, not planted in OpenCV's global generator
    assert _numba_files(cache)  # the kernels were compiled and cached where the process said
    written = [p for p in _numba_files(ROOT / "onboard") if p.stat().st_mtime >= started or p not in in_tree_before]
    assert written == []
