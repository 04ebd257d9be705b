"""Lockstep runs are the runs they were: the same events on any CPU, the same physics within
what CPUs make of the last bits, and bit for bit the same on a host whose pin we hold.

numpy, OpenBLAS (and the libraries on top of them) pick SIMD kernels by CPU, so the last bits
of a dot product or a transcendental differ between hosts, and a hopping robot's contacts and
the planner's solver iterations amplify them. So "the same run" is checked in three ways:

1. Exact on every CPU (``tests/data/lockstep_reference.json``): the scenario's own random
   draws; the sequence of phase and safety events (kinds, in order); the report's counts
   (hops, falls, collisions, touchdowns, events, plans, ...).
2. Within tolerances on every CPU (same file): the event ticks within ``EVENT_TICK_SLACK``
   tick (a touchdown is the first tick the foot touches: a drift far under a tick can still
   move one across a tick boundary); the estimator's per-tick counters within one tick per
   end of each stance; the report's floats and a decimated trace (true CoM, estimate, wheel
   speeds, applied torques) within a per-run, per-channel tolerance. Each tolerance is
   ``SPREAD_MARGIN`` times the spread measured, when the reference was made, between this
   host's full kernels and lower ones (``ALTERNATE_KERNELS``: numpy without its AVX2/AVX-512
   dispatch, OpenBLAS forced to older cores), and not below a per-channel floor
   (``FLOORS``) far under what a behaviour change makes. Measured on c9ea2b0 on an AMD EPYC
   (X86_V3, OpenBLAS Haswell): the largest spread is ``forest graph``'s (the planner's MPC
   turns last bits into solver-tolerance differences), CoM 7.5e-5 m, wheel speeds 4.3e-2
   rad/s; the other runs' CoM spreads are under 1e-8 m. A 2 % change of the attitude PD's
   ``kp_tilt`` moves the CoM by 1.2e-3 m (hop-in-place), 3e-5 m (push), 3.6e-3 m (forest
   graph), 2.7e-3 m (forest graph depth): over each run's tolerance; a 3 % change fails every run here under both kernel choices.
3. Bit for bit (``tests/data/lockstep_pinned.json``): a SHA-256 of the whole trace and the
   report, per host fingerprint (:func:`host_fingerprint`: library versions, numpy's SIMD
   dispatch in use, OpenBLAS's core type); skipped, saying so, on a host without a pin.

Regenerate only for a deliberate change of numerics, and say why in the commit:
``python -m tests.test_lockstep_pinned`` rewrites the reference (measuring the spread
again) and keeps only this host's pin; ``python -m tests.test_lockstep_pinned --add-host``
adds this host's pin after checking its runs against the reference.

The runs use one BLAS thread (:meth:`sim_twin.lockstep.LockstepRunner.run`): a multithreaded
LAPACK solve rounds differently per thread count; the last test holds a run's bits
independent of ``OPENBLAS_NUM_THREADS`` on the host it runs on.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path
from unittest import mock

import numpy as np
import pytest

from sim_twin import scenarios as sc
from sim_twin.lockstep import RunConfig, RunResult, config_with, run

ROOT = Path(__file__).resolve().parent.parent
REFERENCE = ROOT / "tests" / "data" / "lockstep_reference.json"
PINNED = ROOT / "tests" / "data" / "lockstep_pinned.json"
WALL_CLOCK_FIELDS = ("wall_time_s", "realtime_factor", "tick_us_mean")
RUNS: dict[str, RunConfig] = {
    "hop-in-place kalman": RunConfig(scenario="hop-in-place", seed=1, duration_s=2.0, estimator="kalman", planner="scenario"),
    "push truth": RunConfig(scenario="push", seed=4, duration_s=2.5, estimator="truth", planner="scenario"),
    "forest graph": RunConfig(scenario="forest", seed=2, duration_s=3.0, estimator="kalman", planner="graph"),
    "forest graph depth": RunConfig(scenario="forest", seed=0, duration_s=2.0, estimator="kalman", planner="graph", perception="depth"),
}
TRACE_CHANNELS = ("com", "est", "wheel_vel", "torque")
DECIMATE = 5  # trace samples (100 Hz) per stored sample: 20 Hz, a hop's flight is ~15 samples
EVENT_TICK_SLACK = 1  # [ticks] an event may move by one tick (see the module docstring)
TICK_COUNTERS = ("leg_fused", "pose_fused")  # estimator counters that count ticks of a phase
SPREAD_MARGIN = 10.0
# Below these nothing is a behaviour change: a 2 % gain change moves the least sensitive run
# (push) by 3e-5 m, 2e-4 rad/s; a tolerance is never below the floor, so a host whose kernels
# drift a little more than the measured ones still passes.
FLOORS = {"com": 1e-6, "est": 1e-6, "wheel_vel": 1e-5, "torque": 1e-3, "report": 1e-4}  # [m, m, rad/s, N m, relative]
REPORT_QUANTUM = 1e-3  # the report rounds its floats to 4 decimals, wheel speeds to 3: one step either way
# lower kernel choices on any x86-64 host: numpy at its baseline (no AVX2/FMA3/AVX-512 dispatch),
# OpenBLAS forced to older cores' kernels
ALTERNATE_KERNELS = (
    {"NPY_DISABLE_CPU_FEATURES": "X86_V3 X86_V4 AVX512_ICL AVX512_SPR", "OPENBLAS_CORETYPE": "Sandybridge"},
    {"NPY_DISABLE_CPU_FEATURES": "X86_V3 X86_V4 AVX512_ICL AVX512_SPR", "OPENBLAS_CORETYPE": "Nehalem"},
)


# --- what a run is --------------------------------------------------------------


class _RecordingRng:
    """A Generator that keeps every value it hands out."""

    def __init__(self, rng: np.random.Generator) -> None:
        self._rng = rng
        self.draws: list[list] = []

    def __getattr__(self, name: str):
        method = getattr(self._rng, name)

        def draw(*args, **kwargs):
            out = method(*args, **kwargs)
            self.draws.append([name, np.asarray(out).tolist()])
            return out
        return draw


def scenario_draws(cfg: RunConfig) -> list[list]:
    """Every random value the scenario's setup draws (exact on any CPU: integer PCG64 and IEEE
    basic arithmetic, no SIMD-dispatched kernel)."""
    recorders: list[_RecordingRng] = []
    default_rng = np.random.default_rng

    def recording(seed=None):
        recorders.append(_RecordingRng(default_rng(seed)))
        return recorders[-1]
    with mock.patch.object(np.random, "default_rng", recording):
        sc.make(cfg.scenario, cfg.seed, cfg.obstacles)
    return [d for r in recorders for d in r.draws]


def observed(cfg: RunConfig) -> dict:
    """A run as it is compared across CPUs: report, events, decimated trace; and its bits' hash."""
    events: list[tuple[str, int, str]] = []

    def sink(topic: str, now_ns: int, msg: object) -> None:
        if topic in ("phase", "safety"):
            events.append((topic, now_ns // 1_000_000, msg.event if topic == "phase" else msg.trip))
    result = run(config_with(cfg, sink=sink))
    trace = result.trace
    return {
        "report": {k: v for k, v in result.metrics.items() if k not in WALL_CLOCK_FIELDS},
        "events": [[topic, kind] for topic, _, kind in events],
        "event_ticks": [tick for _, tick, _ in events],
        "touchdown_ticks": [round(imp[0] * 1000) for imp in trace.impacts],
        "draws": scenario_draws(cfg),
        "trace": {ch: getattr(trace, ch)[DECIMATE - 1::DECIMATE] for ch in TRACE_CHANNELS},
        "trace_sha256": trace_sha256(result),
    }


def trace_sha256(result: RunResult) -> str:
    trace = json.dumps(dataclasses.asdict(result.trace), sort_keys=True)  # json writes floats by repr: exact
    return hashlib.sha256(trace.encode()).hexdigest()


def host_fingerprint() -> dict:
    """What decides a run's last bits on this host: library versions and the kernels in use."""
    import mujoco
    import osqp
    import piqp
    import scipy
    from numpy._core._multiarray_umath import __cpu_dispatch__, __cpu_features__
    from threadpoolctl import threadpool_info
    return {
        "python": sys.version.split()[0],
        "numpy": np.__version__, "scipy": scipy.__version__, "mujoco": mujoco.__version__,
        "osqp": osqp.__version__, "piqp": getattr(piqp, "__version__", "?"),
        "numpy_simd": [f for f in __cpu_dispatch__ if __cpu_features__.get(f)],
        "blas": sorted({f"{i['internal_api']} {i['version']} {i.get('architecture')}" for i in threadpool_info()
                        if i["user_api"] == "blas"}),
    }


def host_key(fp: dict) -> str:
    return json.dumps(fp, sort_keys=True)


# --- comparison -----------------------------------------------------------------


def _split_report(report: dict) -> tuple[dict, dict, dict]:
    """(exact fields, floats, tick counters)."""
    exact, floats = {}, {}
    for k, v in report.items():
        (floats if isinstance(v, float) else exact)[k] = v
    counters = dict(exact.get("estimator_counters") or {})
    ticks = {k: counters.pop(k) for k in TICK_COUNTERS if k in counters}
    exact = {**exact, "estimator_counters": counters}
    return exact, floats, ticks


def _max_abs(a: list, b: list) -> float:
    return float(np.max(np.abs(np.asarray(a, float) - np.asarray(b, float)), initial=0.0))


def spread(a: dict, b: dict) -> dict[str, float]:
    """How far two observations of one run are apart, channel by channel."""
    out = {ch: _max_abs(a["trace"][ch], b["trace"][ch]) for ch in TRACE_CHANNELS}
    fa, fb = _split_report(a["report"])[1], _split_report(b["report"])[1]
    out["report"] = max((abs(fa[k] - fb[k]) / max(abs(fa[k]), 1.0) for k in fa), default=0.0)
    return out


def differences(ref: dict, got: dict, tolerance: dict[str, float]) -> list[str]:
    """What of ``got`` is not the reference's run, in words; empty when it is."""
    bad = []
    if got["draws"] != ref["draws"]:
        bad.append("the scenario's random draws differ")
    if got["events"] != ref["events"]:
        bad.append(f"event sequence differs: {got['events']} vs {ref['events']}")
    for name in ("event_ticks", "touchdown_ticks"):
        if len(got[name]) != len(ref[name]):
            bad.append(f"{name}: {len(got[name])} vs {len(ref[name])}")
        elif (worst := max((abs(x - y) for x, y in zip(got[name], ref[name])), default=0)) > EVENT_TICK_SLACK:
            bad.append(f"{name}: moved by {worst} ticks (> {EVENT_TICK_SLACK})")
    (exact_g, floats_g, ticks_g), (exact_r, floats_r, ticks_r) = _split_report(got["report"]), _split_report(ref["report"])
    if exact_g != exact_r:
        bad.append(f"report: {[(k, exact_g.get(k), exact_r.get(k)) for k in exact_r if exact_g.get(k) != exact_r[k]]}")
    stance_ends = 2 * len(ref["touchdown_ticks"])  # each stance may gain or lose a tick at either end
    for k in ticks_r:
        if abs(ticks_g.get(k, -1) - ticks_r[k]) > EVENT_TICK_SLACK * stance_ends:
            bad.append(f"estimator counter {k}: {ticks_g.get(k)} vs {ticks_r[k]}")
    if set(floats_g) != set(floats_r):
        bad.append(f"report floats: {sorted(floats_g)} vs {sorted(floats_r)}")
    for k in floats_r.keys() & floats_g.keys():
        allowed = tolerance["report"] * max(abs(floats_r[k]), 1.0) + REPORT_QUANTUM
        if abs(floats_g[k] - floats_r[k]) > allowed:
            bad.append(f"report {k}: {floats_g[k]} vs {floats_r[k]} (allowed {allowed:.2g})")
    for ch in TRACE_CHANNELS:
        if len(got["trace"][ch]) != len(ref["trace"][ch]):
            bad.append(f"trace {ch}: {len(got['trace'][ch])} samples vs {len(ref['trace'][ch])}")
        elif (d := _max_abs(got["trace"][ch], ref["trace"][ch])) > tolerance[ch]:
            bad.append(f"trace {ch}: off by {d:.3g} (tolerance {tolerance[ch]:.3g})")
    return bad


# --- tests ----------------------------------------------------------------------


@pytest.mark.parametrize("name", list(RUNS))
def test_run_is_the_reference_run_on_any_cpu(name: str) -> None:
    ref = json.loads(REFERENCE.read_text())["runs"][name]
    got = observed(RUNS[name])
    assert differences(ref, got, ref["tolerance"]) == []


@pytest.mark.parametrize("name", list(RUNS))
def test_run_is_bit_for_bit_this_hosts_pin(name: str) -> None:
    fp = host_fingerprint()
    pins = json.loads(PINNED.read_text())
    if host_key(fp) not in pins:
        pytest.skip(f"no bit-for-bit pin for this host ({fp}); the cross-CPU reference test holds; "
                    "add one with `python -m tests.test_lockstep_pinned --add-host`")
    pinned = pins[host_key(fp)]["runs"][name]
    result = run(RUNS[name])
    assert {k: v for k, v in result.metrics.items() if k not in WALL_CLOCK_FIELDS} == pinned["report"]
    assert trace_sha256(result) == pinned["trace_sha256"]


OBSERVE_IN_A_PROCESS = (
    "import json, sys; from services.runtime.process_env import prepare_environment; prepare_environment(); "
    "from tests.test_lockstep_pinned import RUNS, observed; "
    "print(json.dumps({n: observed(RUNS[n]) for n in sys.argv[1:]}))"
)


def observed_in_a_process(names: list[str], env: dict[str, str]) -> dict:
    out = subprocess.run([sys.executable, "-c", OBSERVE_IN_A_PROCESS, *names], cwd=ROOT, env={**os.environ, **env},
                         capture_output=True, text=True, timeout=300, check=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def test_bits_do_not_depend_on_blas_threads() -> None:
    """One and three OpenBLAS threads, on this host: the same bits (the planner's MPC polish
    solves are where thread counts used to show)."""
    one, three = (observed_in_a_process(["forest graph"], {"OPENBLAS_NUM_THREADS": n})["forest graph"] for n in ("1", "3"))
    assert one["trace_sha256"] == three["trace_sha256"]
    assert one["report"] == three["report"]


# --- regeneration ---------------------------------------------------------------


def _tolerance(spreads: list[dict[str, float]]) -> dict[str, float]:
    worst = {ch: max(s[ch] for s in spreads) for ch in FLOORS}
    return {ch: float(f"{max(SPREAD_MARGIN * worst[ch], FLOORS[ch]):.1g}") for ch in FLOORS}


def regenerate() -> None:
    base = observed_in_a_process(list(RUNS), {})
    others = [observed_in_a_process(list(RUNS), env) for env in ALTERNATE_KERNELS]
    if all(o[n]["trace_sha256"] == base[n]["trace_sha256"] for o in others for n in RUNS):
        sys.exit("the alternate kernels changed no bit here: no spread to measure the tolerances from")
    runs = {}
    for name in RUNS:
        spreads = [spread(base[name], o[name]) for o in others]
        ref = {k: v for k, v in base[name].items() if k != "trace_sha256"}
        runs[name] = {**ref, "spread": {ch: max(s[ch] for s in spreads) for ch in FLOORS}, "tolerance": _tolerance(spreads)}
    REFERENCE.write_text(json.dumps({"kernels": [{}, *ALTERNATE_KERNELS], "runs": runs}, indent=None) + "\n")
    fp = host_fingerprint()
    pins = {host_key(fp): {"host": fp, "runs": {n: {"report": base[n]["report"], "trace_sha256": base[n]["trace_sha256"]}
                                                 for n in RUNS}}}
    PINNED.write_text(json.dumps(pins, indent=1) + "\n")
    for name, r in runs.items():
        print(f"{name}: spread {r['spread']}\n  tolerance {r['tolerance']}", file=sys.stderr)


def add_host() -> None:
    refs = json.loads(REFERENCE.read_text())["runs"]
    got = observed_in_a_process(list(RUNS), {})
    bad = {n: d for n in RUNS if (d := differences(refs[n], got[n], refs[n]["tolerance"]))}
    if bad:
        sys.exit(f"this host's runs are not the reference's, no pin added: {bad}")
    fp = host_fingerprint()
    pins = json.loads(PINNED.read_text())
    pins[host_key(fp)] = {"host": fp, "runs": {n: {"report": got[n]["report"], "trace_sha256": got[n]["trace_sha256"]}
                                               for n in RUNS}}
    PINNED.write_text(json.dumps(pins, indent=1) + "\n")


if __name__ == "__main__":
    add_host() if sys.argv[1:] == ["--add-host"] else regenerate()
    print(f"wrote {PINNED}", file=sys.stderr)
