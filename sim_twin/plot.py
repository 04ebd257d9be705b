"""PNG summary of a run: top-down path with obstacles and reference, tracking error, wheel speeds, torques."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only, no display
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from sim_twin.lockstep import RunResult  # noqa: E402


def plot_run(result: RunResult, path: str | Path) -> None:
    tr, scn, mt = result.trace, result.scenario, result.metrics
    fig, axes = plt.subplots(2, 2, figsize=(13, 9))
    ax = axes[0, 0]
    for ob in scn.obstacles:
        xy = np.array(ob.vertices + (ob.vertices[0],))
        ax.fill(xy[:, 0], xy[:, 1], color="0.6", alpha=0.8, lw=0)
    if tr.ref:
        ref = np.array(tr.ref)
        ax.plot(ref[:, 0], ref[:, 1], "--", color="tab:orange", lw=1.2, label="reference")
    if tr.com:
        com = np.array(tr.com)
        ax.plot(com[:, 0], com[:, 1], color="tab:blue", lw=1.0, label="CoM (true)")
    if tr.est:
        est = np.array(tr.est)
        ax.plot(est[:, 0], est[:, 1], color="tab:green", lw=0.6, alpha=0.6, label="CoM (estimate)")
    if tr.impacts:
        imp = np.array(tr.impacts)
        ax.plot(imp[:, 1], imp[:, 2], ".", color="tab:red", ms=3, label="touchdowns")
    ax.plot(*scn.start, "ko", ms=6, label="start")
    tx, ty = scn.target()
    ax.plot(tx, ty, "k*", ms=12, label="goal")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.legend(loc="best", fontsize=8)
    ax.set_title(f"{mt['scenario']} seed {mt['seed']}: {mt['hops']} hops, {mt['falls']} falls, {mt['collisions']} collisions")

    t = np.array(tr.t)
    ax = axes[0, 1]
    if len(t):
        ax.plot(t, tr.tracking_error, lw=0.8, label="|CoM - reference|")
    if tr.impacts:
        imp = np.array(tr.impacts)
        ax.plot(imp[:, 0], np.hypot(imp[:, 1] - imp[:, 3], imp[:, 2] - imp[:, 4]), ".", color="tab:red", ms=3, label="at touchdown")
    ax.set_xlabel("t [s]")
    ax.set_ylabel("tracking error [m]")
    ax.legend(loc="best", fontsize=8)

    ax = axes[1, 0]
    if len(t):
        wv = np.array(tr.wheel_vel)
        for i, name in enumerate("xyz"):
            ax.plot(t, wv[:, i], lw=0.7, label=f"wheel {name}")
    ax.set_xlabel("t [s]")
    ax.set_ylabel("wheel speed [rad/s]")
    ax.legend(loc="best", fontsize=8)

    ax = axes[1, 1]
    if len(t):
        tq = np.array(tr.torque)
        for i, name in enumerate(("wheel x", "wheel y", "wheel z", "foot spool")):
            ax.plot(t, tq[:, i], lw=0.7, label=name)
    ax.set_xlabel("t [s]")
    ax.set_ylabel("applied torque [N m]")
    ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
