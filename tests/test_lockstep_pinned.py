"""Lockstep runs are bit for bit what they were before the twin was made faster.

``tests/data/lockstep_pinned.json`` holds, for a few short runs, the report (wall-clock
figures aside) and a SHA-256 of the whole trace (true CoM, estimate, reference, wheel
speeds, applied torques, touchdowns, every float by its exact ``repr``), captured at commit
ab650b1 (main before issue 19's speed work) with two OpenBLAS threads, this machine's default.
A speed-up that changes any float of any tick fails here.

One change was deliberate: lockstep runs now use one BLAS thread
(:meth:`sim_twin.lockstep.LockstepRunner.run`). Before, ``forest graph``'s trace differed
between one and two OpenBLAS threads (the planner's MPC polish solves), i.e. a run's bits
depended on the machine; its trace hash was re-pinned then (the report did not change), and
the last test holds the bits independent of ``OPENBLAS_NUM_THREADS``. Regenerate only for a deliberate change of numerics, with
``python -m tests.test_lockstep_pinned``, and say why in the commit.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from sim_twin.lockstep import RunConfig, RunResult, run

ROOT = Path(__file__).resolve().parent.parent
PINNED = ROOT / "tests" / "data" / "lockstep_pinned.json"
WALL_CLOCK_FIELDS = ("wall_time_s", "realtime_factor", "tick_us_mean")
RUNS: dict[str, RunConfig] = {
    "hop-in-place kalman": RunConfig(scenario="hop-in-place", seed=1, duration_s=2.0, estimator="kalman", planner="scenario"),
    "push truth": RunConfig(scenario="push", seed=4, duration_s=2.5, estimator="truth", planner="scenario"),
    "forest graph": RunConfig(scenario="forest", seed=2, duration_s=3.0, estimator="kalman", planner="graph"),
    "forest graph depth": RunConfig(scenario="forest", seed=0, duration_s=2.0, estimator="kalman", planner="graph", perception="depth"),
}


def fingerprint(result: RunResult) -> dict:
    report = {k: v for k, v in result.metrics.items() if k not in WALL_CLOCK_FIELDS}
    trace = json.dumps(dataclasses.asdict(result.trace), sort_keys=True)  # json writes floats by repr: exact
    return {"report": report, "trace_sha256": hashlib.sha256(trace.encode()).hexdigest()}


@pytest.mark.parametrize("name", list(RUNS))
def test_run_is_bit_for_bit_the_pinned_one(name: str) -> None:
    pinned = json.loads(PINNED.read_text())[name]
    got = fingerprint(run(RUNS[name]))
    assert got["report"] == pinned["report"]
    assert got["trace_sha256"] == pinned["trace_sha256"]


FINGERPRINT_IN_A_PROCESS = (
    "import json; from services.runtime.process_env import prepare_environment; prepare_environment(); "
    "from tests.test_lockstep_pinned import RUNS, fingerprint; from sim_twin.lockstep import run; "
    "print(json.dumps(fingerprint(run(RUNS['forest graph']))))"
)


@pytest.mark.parametrize("threads", ["1", "3"])
def test_bits_do_not_depend_on_blas_threads(threads: str) -> None:
    env = {**os.environ, "OPENBLAS_NUM_THREADS": threads}
    out = subprocess.run([sys.executable, "-c", FINGERPRINT_IN_A_PROCESS], cwd=ROOT, env=env, capture_output=True, text=True,
                         timeout=120, check=True).stdout
    assert json.loads(out.strip().splitlines()[-1]) == json.loads(PINNED.read_text())["forest graph"]


if __name__ == "__main__":
    PINNED.write_text(json.dumps({name: fingerprint(run(cfg)) for name, cfg in RUNS.items()}, indent=1) + "\n")
    print(f"wrote {PINNED}", file=sys.stderr)
