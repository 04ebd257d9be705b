"""What the items' figures share: a headless matplotlib, arrays from a run's record, the saving."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

TRACE_DT_S = 0.01  # the metrics' trace period (sim_twin.metrics.TRACE_EVERY ticks at 1 kHz)


def pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save(fig: Any, out: Path, name: str) -> str:
    """Writes ``name`` into ``out`` and returns the name (the report links it relative to itself)."""
    fig.tight_layout()
    fig.savefig(out / name, dpi=110)
    pyplot().close(fig)
    return name


def trace_arrays(record: dict) -> dict[str, np.ndarray]:
    """A run's trace as arrays, with the CoM velocity differentiated from the position."""
    tr = record["trace"]
    out = {k: np.asarray(tr[k], dtype=float) for k in ("t", "com", "est", "ref", "wheel_vel", "torque", "tracking_error")}
    out["vel"] = np.gradient(out["com"][:, :2], out["t"], axis=0) if len(out["t"]) > 1 else np.zeros((len(out["t"]), 2))
    return out


def stance_mask(t: np.ndarray, phases: list[tuple[float, str]]) -> np.ndarray:
    """True at the samples between a touchdown and the next liftoff."""
    mask = np.zeros(len(t), dtype=bool)
    down = None
    for when, event in phases:
        if event == "touchdown":
            down = when
        elif event == "liftoff" and down is not None:
            mask |= (t >= down) & (t < when)
            down = None
    return mask


def draw_obstacles(ax: Any, obstacles: list[list[list[float]]], **style: Any) -> None:
    for poly in obstacles:
        pts = np.asarray(poly + poly[:1])
        ax.fill(pts[:, 0], pts[:, 1], **{"color": "0.6", "alpha": 0.6, **style})
