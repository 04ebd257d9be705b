"""``archer plot FILE.mcap|DIR ...``: PNG plots of a recording.

Reads the flight recorder's files (or a lockstep ``archer sim --record`` file), decodes
every message with its schema and writes, into ``--out`` (default: next to the input,
``<name>_plots/``):

- ``path.png``: the CoM path seen by the estimator, the reference the low level was
  given, waypoints, goals, touchdowns, obstacles (or free cells) from ``polytopes``;
- ``tracking.png``: |CoM - reference| in the horizontal plane over time, and the
  tube the low level reports (``tube``: p95 of the impact error);
- ``attitude.png``: roll, pitch, yaw of the estimate [deg];
- ``wheels.png``: wheel speeds (estimate, and the joint sensors when recorded);
- ``torques.png``: commanded wheel and foot torques, shaded where disarmed;
- ``timing.png``: torque command and state periods (publisher stamps and recorder
  arrival), and the control loop's own statistics from its recorded status.

Prints one JSON object of summary figures (also written as ``summary.json``).
Times are seconds on the stack's clock from the first state estimate.
"""

from __future__ import annotations

import argparse
import bisect
import json
import math
import sys
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from onboard.contracts import messages as m
from onboard.geometry import quaternion as qt
from onboard.contracts.reference import sample_reference
from onboard.contracts.topics import TOPICS
from services.recorder import read_recording, recording_files

NS = 1e9
MAX_POINTS = 20_000  # per plotted series: more points only slow matplotlib down
PERIOD_WINDOW_S = 1.0  # message periods are summarised per window
_BY_SUFFIX = {t.suffix: t for t in TOPICS.values()}
_STATUS_SUFFIX = "/status"


@dataclass
class Series:
    """Decoded messages of one topic, in arrival order."""

    stamps: list[int] = field(default_factory=list)  # message stamp_ns
    arrivals: list[int] = field(default_factory=list)  # recorder log time [ns]
    msgs: list[Any] = field(default_factory=list)


def topic_name(key: str) -> str | None:
    """The topic-table name of a channel key, whatever the namespace; ``status:<svc>`` for statuses."""
    parts = key.split("/")
    if len(parts) >= 4 and parts[-3] == "svc" and parts[-1] == "status":
        return f"status:{parts[-2]}"
    for i in range(1, len(parts)):
        topic = _BY_SUFFIX.get("/".join(parts[i:]))
        if topic is not None:
            return topic.name
    return None


def load(paths: list[str]) -> tuple[dict[str, Series], dict[str, int]]:
    """Every JSON message by topic; counts of what was skipped."""
    series: dict[str, Series] = defaultdict(Series)
    skipped: dict[str, int] = defaultdict(int)
    for rec in read_recording(paths):
        name = topic_name(rec.key)
        msg_type = getattr(m, rec.schema, None)
        if name is None or not (isinstance(msg_type, type) and issubclass(msg_type, m.Message)):
            skipped[rec.schema or rec.key] += 1  # binary images and grids, unknown channels
            continue
        try:
            msg = m.decode(rec.data, msg_type)
        except m.MessageError:
            skipped[f"invalid {name}"] += 1
            continue
        if msg.stamp_ns <= 0:  # no time of its own (e.g. an estimate before any sensor data)
            skipped[f"unstamped {name}"] += 1
            continue
        s = series[name]
        s.stamps.append(msg.stamp_ns)
        s.arrivals.append(rec.log_ns)
        s.msgs.append(msg)
    return series, dict(skipped)


def _thin(n: int) -> slice:
    return slice(None, None, max(1, math.ceil(n / MAX_POINTS)))


def tracking_errors(states: Series, refs: Series) -> tuple[np.ndarray, np.ndarray]:
    """|CoM - reference| [m] at each state stamp, with the reference in force then."""
    order = sorted(range(len(refs.msgs)), key=lambda i: refs.stamps[i])
    ref_stamps = [refs.stamps[i] for i in order]
    t, err = [], []
    for stamp, st in zip(states.stamps, states.msgs):
        k = bisect.bisect_right(ref_stamps, stamp) - 1
        if k < 0:
            continue
        ref = refs.msgs[order[k]]
        if not ref.segments:
            continue
        x, y, _, _ = sample_reference(ref, (stamp - ref.t_ref_ns) / NS)
        t.append(stamp)
        err.append(math.hypot(st.position[0] - x, st.position[1] - y))
    return np.array(t, dtype=np.int64), np.array(err)


def _per_window(t: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """p99 and max of ``values`` per ``PERIOD_WINDOW_S`` of ``t``: readable where 600k raw points are not."""
    bins = np.floor(t / PERIOD_WINDOW_S).astype(np.int64)
    edges = np.flatnonzero(np.diff(bins)) + 1
    groups = np.split(values, edges)
    starts = bins[np.concatenate(([0], edges))] * PERIOD_WINDOW_S
    return starts, np.array([np.percentile(g, 99) for g in groups]), np.array([g.max() for g in groups])


def _pct(a: np.ndarray, q: float) -> float:
    return round(float(np.percentile(a, q)), 6) if len(a) else float("nan")


def plot(series: dict[str, Series], out: Path) -> dict[str, Any]:
    import matplotlib

    matplotlib.use("Agg")  # files only
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    states = series.get("state", Series())
    if not states.msgs:
        raise ValueError("no state estimates in the recording: nothing to plot against")
    t0 = min(states.stamps)

    def secs(stamps: list[int] | np.ndarray) -> np.ndarray:
        return (np.asarray(stamps, dtype=np.int64) - t0) / NS

    summary: dict[str, Any] = {"messages": {k: len(v.msgs) for k, v in sorted(series.items())}}
    thin = _thin(len(states.msgs))
    st_t = secs(states.stamps)[thin]
    st_msgs = states.msgs[thin]
    pos = np.array([s.position for s in st_msgs])
    summary["duration_s"] = round(float(secs(states.stamps).max()), 3)
    written = []

    def save(fig, name: str) -> None:
        fig.tight_layout()
        fig.savefig(out / name, dpi=110)
        plt.close(fig)
        written.append(str(out / name))

    # path and obstacles
    fig, ax = plt.subplots(figsize=(8, 8))
    polys = series.get("polytopes")
    if polys is not None and polys.msgs:
        last = polys.msgs[-1]
        for p in last.polytopes:
            v = np.array(p.vertices + p.vertices[:1])
            if last.mode == "obstacles":
                ax.fill(v[:, 0], v[:, 1], color="0.55", alpha=0.8, lw=0)
            else:
                ax.plot(v[:, 0], v[:, 1], color="tab:green", lw=0.5, alpha=0.5)
        summary["polytopes"] = {"mode": last.mode, "count": len(last.polytopes)}
    refs = series.get("reference", Series())
    if refs.msgs:
        ref = refs.msgs[-1]
        for seg in ref.segments:
            curve = [sample_reference(ref, seg.t0 + seg.duration * s)[:2] for s in np.linspace(0, 1, 30)]
            c = np.array(curve)
            ax.plot(c[:, 0], c[:, 1], "--", color="tab:orange", lw=1.0)
    wps = series.get("waypoints")
    if wps is not None and wps.msgs and wps.msgs[-1].points:
        w = np.array(wps.msgs[-1].points)
        ax.plot(w[:, 0], w[:, 1], "o:", color="tab:purple", ms=3, lw=0.8, label="waypoints")
    ax.plot(pos[:, 0], pos[:, 1], color="tab:blue", lw=0.8, label="CoM (estimate)")
    phase = series.get("phase")
    if phase is not None:
        td = np.array([e.position for e in phase.msgs if e.event == "touchdown"])
        if len(td):
            ax.plot(td[:, 0], td[:, 1], ".", color="tab:red", ms=3, label="touchdowns")
        summary["hops"] = int(sum(1 for e in phase.msgs if e.event == "touchdown"))
    goals = series.get("goal")
    if goals is not None and goals.msgs:
        g = np.array([x.position for x in goals.msgs])
        ax.plot(g[:, 0], g[:, 1], "k*", ms=12, label="goals")
    ax.plot([], [], "--", color="tab:orange", label="reference (last)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.legend(loc="best", fontsize=8)
    ax.set_title("path and obstacles")
    save(fig, "path.png")

    # tracking error
    fig, ax = plt.subplots(figsize=(10, 4))
    if refs.msgs:
        tt, err = tracking_errors(states, refs)
        th = _thin(len(tt))
        ax.plot(secs(tt)[th], err[th], lw=0.7, label="|CoM - reference|")
        summary["tracking_error_m"] = {"p50": _pct(err, 50), "p95": _pct(err, 95), "max": _pct(err, 100)}
    tube = series.get("tube")
    if tube is not None and tube.msgs:
        ax.step(secs(tube.stamps), [x.impact_err_p95 for x in tube.msgs], where="post", color="tab:red", label="tube: impact error p95")
    ax.set_xlabel("t [s]")
    ax.set_ylabel("[m]")
    ax.legend(loc="best", fontsize=8)
    ax.set_title("tracking error")
    save(fig, "tracking.png")

    # attitude
    fig, ax = plt.subplots(figsize=(10, 4))
    eul = np.degrees(np.array([qt.to_euler(s.quat) for s in st_msgs]))
    for i, label in enumerate(("roll", "pitch", "yaw")):
        ax.plot(st_t, eul[:, i], lw=0.7, label=label)
    ax.set_xlabel("t [s]")
    ax.set_ylabel("[deg]")
    ax.legend(loc="best", fontsize=8)
    ax.set_title("attitude (estimate)")
    summary["tilt_max_deg"] = round(float(np.max(np.hypot(eul[:, 0], eul[:, 1]))), 3)
    save(fig, "attitude.png")

    # wheel speeds
    fig, ax = plt.subplots(figsize=(10, 4))
    wv = np.array([s.wheel_vel for s in st_msgs])
    for i in range(3):
        ax.plot(st_t, wv[:, i], lw=0.7, label=f"wheel {i} (estimate)")
    joints = series.get("joints")
    if joints is not None and joints.msgs:
        th = _thin(len(joints.msgs))
        jv = np.array([j.wheel_vel for j in joints.msgs[th]])
        for i in range(3):
            ax.plot(secs(joints.stamps)[th], jv[:, i], lw=0.4, alpha=0.5, label=f"wheel {i} (sensor)")
    ax.set_xlabel("t [s]")
    ax.set_ylabel("[rad/s]")
    ax.legend(loc="best", fontsize=7, ncol=2)
    ax.set_title("wheel speeds")
    save(fig, "wheels.png")

    # torques
    fig, (ax, ax2) = plt.subplots(2, 1, figsize=(10, 6), sharex=True)
    cmds = series.get("torque_cmd")
    if cmds is not None and cmds.msgs:
        th = _thin(len(cmds.msgs))
        ct = secs(cmds.stamps)[th]
        wt = np.array([c.wheel_torque for c in cmds.msgs[th]])
        for i in range(3):
            ax.plot(ct, wt[:, i], lw=0.6, label=f"wheel {i}")
        ax2.plot(ct, [c.foot_torque for c in cmds.msgs[th]], lw=0.6, color="tab:brown", label="foot")
        disarmed = np.array([not c.armed for c in cmds.msgs[th]])
        for a in (ax, ax2):
            a.fill_between(ct, 0, 1, where=disarmed, transform=a.get_xaxis_transform(), color="tab:red", alpha=0.1, lw=0)
        summary["torque_cmd_disarmed_fraction"] = round(float(np.mean([not c.armed for c in cmds.msgs])), 4)
    ax.set_ylabel("wheel [N m]")
    ax2.set_ylabel("foot [N m]")
    ax2.set_xlabel("t [s] (red: disarmed)")
    ax.legend(loc="best", fontsize=8)
    ax.set_title("commanded torques")
    save(fig, "torques.png")

    # loop timing
    fig, (ax, ax2) = plt.subplots(2, 1, figsize=(10, 7))
    timing: dict[str, Any] = {}
    for name in ("torque_cmd", "state"):
        s = series.get(name)
        if s is None or len(s.msgs) < 2:
            continue
        period_ms = np.diff(np.asarray(s.stamps, dtype=np.int64)) / 1e6
        arrival_ms = np.diff(np.asarray(s.arrivals, dtype=np.int64)) / 1e6
        t_bin, p99, pmax = _per_window(secs(s.stamps[1:]), period_ms)
        line = ax.plot(t_bin, p99, lw=0.8, label=f"{name}: period p99 per {PERIOD_WINDOW_S:g} s")[0]
        ax.plot(t_bin, pmax, lw=0.5, ls=":", color=line.get_color(), label=f"{name}: period max")
        timing[name] = {
            "period_ms_p50": _pct(period_ms, 50), "period_ms_p99": _pct(period_ms, 99), "period_ms_max": _pct(period_ms, 100),
            "arrival_ms_p99": _pct(arrival_ms, 99), "arrival_ms_max": _pct(arrival_ms, 100),
        }
    ax.set_ylabel("[ms]")
    ax.set_yscale("log")
    ax.legend(loc="best", fontsize=8)
    ax.set_xlabel("t [s]")
    ax.set_title("message periods (publisher stamps)")
    control = series.get("status:control")
    if control is not None and control.msgs:
        ct = secs(control.stamps)
        for key in ("loop_period_jitter_us_p99", "loop_tick_us_p99", "loop_period_jitter_us_max"):
            vals = [st.extra.get(key, float("nan")) for st in control.msgs]
            ax2.plot(ct, vals, lw=0.8, label=key)
        last = control.msgs[-1].extra
        timing["control_loop"] = {k.removeprefix("loop_"): v for k, v in last.items() if k.startswith("loop_")}
        ax2.legend(loc="best", fontsize=8)
    ax2.set_xlabel("t [s]")
    ax2.set_ylabel("[us]")
    ax2.set_yscale("log")  # p99 of microseconds beside maxima of milliseconds
    ax2.set_title("control loop (from its recorded status)" if control else "control loop: no status recorded")
    summary["timing"] = timing
    save(fig, "timing.png")

    summary["plots"] = written
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    return summary


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("paths", nargs="+", metavar="FILE.mcap|DIR", help="recording files or the recorder's directory")
    parser.add_argument("--out", default=None, help="directory for the PNGs (default: <first input>_plots)")


def run(args: argparse.Namespace) -> int:
    files = recording_files(args.paths)
    if not files:
        print("archer plot: no .mcap files", file=sys.stderr)
        return 2
    first = Path(args.paths[0])
    out = Path(args.out) if args.out else first.with_name(first.name.removesuffix(".mcap") + "_plots")
    try:
        series, skipped = load([str(f) for f in files])
        summary = plot(series, out)
    except (OSError, ValueError) as exc:
        print(f"archer plot: {exc}", file=sys.stderr)
        return 2
    summary["files"] = len(files)
    summary["skipped"] = skipped
    print(json.dumps(summary))
    return 0
