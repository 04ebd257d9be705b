"""The perception service's warm-up: before it reports ready, its compiled kernels are loaded.

In ``archer sim --mode realtime`` on two busy cores the service (Nice=10) took over 5 s to
fuse its first view, which loaded numba's kernels on the event loop: the watchdog killed it
every run and the planner never saw the way.
"""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from onboard.contracts.binary_messages import CELL_FREE, CELL_OCCUPIED
from onboard.contracts.params import PerceptionParams
from onboard.perception.pipeline import Perception, polytopes_of_grid
from services.perception import warm_view

# What each mode's views and decompositions call (bfs_labels only joins free cells that came
# out apart: compiled when that first happens); obstacles are found by OpenCV.
KERNELS_OF_MODE = {
    "free": {"carve", "fit_free", "mark_interior", "overlaps_blocked", "overlap_groups"},
    "obstacles": {"carve"},
}

KERNELS_COMPILED_AFTER_WARM_UP = """
import json, sys
from services.runtime.process_env import prepare_environment
prepare_environment()
from numba.core.registry import CPUDispatcher
from onboard.contracts.params import PerceptionParams
from services.perception import warm_up
import onboard.perception._kernels as kernels
warm_up(PerceptionParams(mode=sys.argv[1]))
print(json.dumps({name: len(f.signatures) for name, f in vars(kernels).items()
                  if isinstance(f, CPUDispatcher) and not name.startswith("_")}))
"""


def test_the_warm_view_holds_floor_and_wall_and_gives_convex_sets_in_both_modes() -> None:
    params = PerceptionParams()
    view = Perception(params)
    stats = view.integrate(warm_view(), (0.0, 0.0))
    assert stats.traversable > 0 and stats.occupied > 0 and stats.ground_inliers > 0
    grid = view.grid(0, 0)
    assert (grid.cells == CELL_FREE).any() and (grid.cells == CELL_OCCUPIED).any()
    free, _ = polytopes_of_grid(grid, params, "free", (0.0, 0.0), ((0.0, 0.0),))
    obstacles, _ = polytopes_of_grid(grid, params, "obstacles")
    assert free and obstacles


@pytest.mark.parametrize("mode", sorted(KERNELS_OF_MODE))
def test_warm_up_compiles_every_kernel_a_view_and_its_decomposition_call(mode: str) -> None:
    """In a fresh interpreter: what an earlier test compiled in this one would hide a gap."""
    run = subprocess.run([sys.executable, "-c", KERNELS_COMPILED_AFTER_WARM_UP, mode],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    signatures = json.loads(run.stdout.strip().splitlines()[-1])
    assert KERNELS_OF_MODE[mode] <= {name for name, n in signatures.items() if n > 0}, signatures

