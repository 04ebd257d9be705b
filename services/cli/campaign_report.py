"""A campaign's summary: per group of runs (same scenario, variant and options; seeds vary).

Definitions, per group:

- ``success``: the run produced a report, reached its goal (``goal_reached``: within tolerance
  and never fell), touched no obstacle (``collisions == 0``) and never touched down on ground the
  scenario keeps it off (``keep_out_touchdowns``, a sidewalk's grass). A run that failed with an error
  counts as a run without success, so the rate never looks better for a crashing stack;
- ``success_ci95``: the Wilson score interval of the success rate at 95 % (sound at 0 or all
  successes and for small groups, where the normal approximation is not);
- ``runs_with_falls`` / ``runs_with_collisions`` and the totals ``falls`` / ``collisions``; where the
  scenario keeps the robot off some ground, ``runs_on_keep_out`` and ``keep_out_touchdowns``;
- where obstacles move: ``collisions_by_robot`` / ``collisions_by_obstacle`` (who moved into whom, at
  first contact), and ``collisions_by_robot_after_hit``: the robot's that came within
  ``sim_twin.metrics.HIT_REPORTED_S`` of an obstacle coming at it (knocked, then falling into one);
- without motion capture (``--sensing onboard``): the estimate's ``drift_per_m`` and ``final_drift_m``,
  and the terrain segmenter's ``segmentation_iou`` over every apex view of the group, pooled
  (the intersections' sum over the unions' sum, so a run with more views weighs more), with the
  per-run IoU's spread;
- percentiles (p50, p90, max) of ``final_goal_error_m`` and ``rms_tracking_error_m`` over the
  runs that report them; ``realtime_factor`` median and minimum.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

WILSON_Z = 1.959964  # two-sided 95 %
PERCENTILES = (50, 90)
SUMMARY_JSON, SUMMARY_TXT, PLOT_PNG = "summary.json", "summary.txt", "campaign.png"


def wilson_interval(successes: int, n: int, z: float = WILSON_Z) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion; (0, 1) when there is no trial."""
    if n == 0:
        return 0.0, 1.0
    p = successes / n
    denom = 1.0 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z * math.sqrt(p * (1.0 - p) / n + z * z / (4 * n * n)) / denom
    return max(0.0, centre - half), min(1.0, centre + half)


def group_name(spec: dict) -> str:
    options = " ".join(f"{k}={v}" for k, v in sorted(spec["options"].items()))
    return " ".join(filter(None, (spec["scenario"], spec["variant"], options)))


def succeeded(record: dict) -> bool:
    report = record.get("report")
    return (report is not None and bool(report["goal_reached"]) and report["collisions"] == 0
            and not report.get("keep_out_touchdowns"))


def _spread(values: list[float]) -> dict[str, float | None]:
    if not values:
        return {**{f"p{q}": None for q in PERCENTILES}, "max": None}
    out: dict[str, float | None] = {f"p{q}": round(float(np.percentile(values, q)), 4) for q in PERCENTILES}
    out["max"] = round(max(values), 4)
    return out


def _reported(reports: list[dict], field: str) -> list[float]:
    return [float(r[field]) for r in reports if r.get(field) is not None]


def _segmentation(reports: list[dict]) -> dict:
    """The terrain segmenter's IoU over the group's apex views (module docstring), or nothing."""
    seg = [r["segmentation"] for r in reports if r.get("segmentation")]
    if not seg:
        return {}
    union = sum(s["union"] for s in seg)
    return {"segmentation_iou": round(sum(s["intersection"] for s in seg) / union, 4) if union else None,
            "segmentation_views": sum(s["views"] for s in seg),
            "segmentation_iou_per_run": _spread([s["iou"] for s in seg if s["views"]])}


def summarize(records: list[dict]) -> dict:
    """The campaign's figures per group (see the module docstring), groups in first-seen order."""
    groups: dict[str, list[dict]] = {}
    for record in records:
        groups.setdefault(group_name(record["spec"]), []).append(record)
    out = []
    for name, members in groups.items():
        reports = [r["report"] for r in members if "report" in r]
        successes = sum(succeeded(r) for r in members)
        low, high = wilson_interval(successes, len(members))
        rtf = _reported(reports, "realtime_factor")
        out.append({
            "group": name,
            "runs": len(members),
            "errors": len(members) - len(reports),
            "successes": successes,
            "success_rate": round(successes / len(members), 4),
            "success_ci95": [round(low, 4), round(high, 4)],
            "runs_with_falls": sum(r["falls"] > 0 for r in reports),
            "falls": sum(r["falls"] for r in reports),
            "runs_with_collisions": sum(r["collisions"] > 0 for r in reports),
            "collisions": sum(r["collisions"] for r in reports),
            # ground the robot must not hop on (where the scenario has any): runs that touched down on it
            **({"runs_on_keep_out": sum(r["keep_out_touchdowns"] > 0 for r in reports),
                "keep_out_touchdowns": sum(r["keep_out_touchdowns"] for r in reports)}
               if any("keep_out_touchdowns" in r for r in reports) else {}),
            # obstacles that move: who moved into whom, replanning rate (where runs report them)
            **({"collisions_by_robot": sum(r["collisions_by_robot"] for r in reports if "collisions_by_robot" in r),
                "collisions_by_obstacle": sum(r["collisions_by_obstacle"] for r in reports if "collisions_by_obstacle" in r),
                # of the robot's: those within HIT_REPORTED_S of an obstacle coming at it (knocked, then falling into one)
                "collisions_by_robot_after_hit": sum(e["by"] == "robot" and e["since_hit_s"] is not None
                                                     for r in reports for e in r.get("collision_events", ())),
                "replans_per_s": _spread(_reported(reports, "planner_replans_per_s"))}
               if any("collisions_by_robot" in r for r in reports) else {}),
            # no motion capture (--sensing onboard): how far the estimate drifted, per metre travelled and in all
            **({"drift_per_m": _spread(_reported(reports, "drift_per_m")),
                "final_drift_m": _spread(_reported(reports, "final_drift_m"))}
               if any("drift_per_m" in r for r in reports) else {}),
            **({"time_to_goal_s": _spread(_reported(reports, "time_to_goal_s"))}
               if any("time_to_goal_s" in r for r in reports) else {}),
            **_segmentation(reports),
            "final_goal_error_m": _spread(_reported(reports, "final_goal_error_m")),
            "rms_tracking_error_m": _spread(_reported(reports, "rms_tracking_error_m")),
            "realtime_factor_median": round(float(np.median(rtf)), 2) if rtf else None,
            "realtime_factor_min": round(min(rtf), 2) if rtf else None,
            "sim_time_s": round(sum(_reported(reports, "sim_time_s")), 3),
            "error_examples": sorted({r["error"] for r in members if "error" in r})[:3],
        })
    return {"groups": out, "runs": len(records), "errors": sum(g["errors"] for g in out)}


def _fmt(value: float | None, digits: int = 3) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def table(summary: dict) -> str:
    """The summary as an aligned text table, one line per group."""
    head = ("group", "runs", "err", "success", "95% CI", "falls", "coll.", "goal err p50/p90/max [m]",
            "rms track p50/p90 [m]", "RTF med/min")
    rows = [head]
    for g in summary["groups"]:
        ge, te = g["final_goal_error_m"], g["rms_tracking_error_m"]
        rows.append((
            g["group"], str(g["runs"]), str(g["errors"]), f"{g['successes']}/{g['runs']} {100 * g['success_rate']:.0f}%",
            f"[{100 * g['success_ci95'][0]:.0f}, {100 * g['success_ci95'][1]:.0f}]%",
            f"{g['runs_with_falls']} ({g['falls']})", f"{g['runs_with_collisions']} ({g['collisions']})",
            f"{_fmt(ge['p50'])}/{_fmt(ge['p90'])}/{_fmt(ge['max'])}", f"{_fmt(te['p50'])}/{_fmt(te['p90'])}",
            f"{_fmt(g['realtime_factor_median'], 1)}/{_fmt(g['realtime_factor_min'], 1)}",
        ))
    widths = [max(len(r[i]) for r in rows) for i in range(len(head))]
    lines = ["  ".join(cell.ljust(w) for cell, w in zip(row, widths)).rstrip() for row in rows]
    for g in summary["groups"]:
        if "collisions_by_robot" in g:
            lines.append(f"{g['group']}: collisions by the robot {g['collisions_by_robot']} "
                         f"({g['collisions_by_robot_after_hit']} soon after it was hit), by an obstacle {g['collisions_by_obstacle']}")
        if "keep_out_touchdowns" in g:
            lines.append(f"{g['group']}: {g['runs_on_keep_out']} runs touched down on ground kept off "
                         f"({g['keep_out_touchdowns']} touchdowns)")
        if "time_to_goal_s" in g:
            tg = g["time_to_goal_s"]
            lines.append(f"{g['group']}: time to goal p50/p90/max {_fmt(tg['p50'], 1)}/{_fmt(tg['p90'], 1)}/{_fmt(tg['max'], 1)} s "
                         f"over the runs that came within its tolerance")
        if "drift_per_m" in g:
            d, f = g["drift_per_m"], g["final_drift_m"]
            lines.append(f"{g['group']}: drift per metre p50/p90/max {_fmt(d['p50'], 4)}/{_fmt(d['p90'], 4)}/{_fmt(d['max'], 4)}, "
                         f"final drift p50/p90 {_fmt(f['p50'])}/{_fmt(f['p90'])} m")
        if "segmentation_iou" in g:
            lines.append(f"{g['group']}: segmentation IoU {_fmt(g['segmentation_iou'])} over {g['segmentation_views']} "
                         f"apex views (per run p50 {_fmt(g['segmentation_iou_per_run']['p50'])})")
    lines.append(f"{summary['runs']} runs, {summary['errors']} errors"
                 + (f", {summary['campaign_wall_s']} s wall ({summary['executor']})" if "campaign_wall_s" in summary else ""))
    return "\n".join(lines)


def plot(summary: dict, records: list[dict], path: Path) -> None:
    """Success rate with its Wilson interval, and the final goal errors, per group."""
    import matplotlib

    matplotlib.use("Agg")  # files only, no display
    import matplotlib.pyplot as plt

    groups = summary["groups"]
    names = [g["group"] for g in groups]
    fig, (ax_rate, ax_err) = plt.subplots(1, 2, figsize=(12, 1.5 + 0.6 * len(groups)), squeeze=True)
    rates = [g["success_rate"] for g in groups]
    lows = [g["success_rate"] - g["success_ci95"][0] for g in groups]
    highs = [g["success_ci95"][1] - g["success_rate"] for g in groups]
    y = np.arange(len(groups))
    ax_rate.barh(y, rates, xerr=[lows, highs], color="tab:blue", alpha=0.7, capsize=4)
    ax_rate.set_yticks(y, names)
    ax_rate.set_xlim(0, 1)
    ax_rate.set_xlabel("success rate (95 % Wilson interval)")
    ax_rate.invert_yaxis()
    errors = [[r["report"]["final_goal_error_m"] for r in records
               if "report" in r and group_name(r["spec"]) == name] for name in names]
    for i, values in enumerate(errors):
        ax_err.plot(values, np.full(len(values), i), "|", color="tab:red", ms=12, alpha=0.6)
    ax_err.set_yticks(y, [""] * len(y))
    ax_err.set_ylim(ax_rate.get_ylim())
    ax_err.set_xscale("symlog", linthresh=0.1)
    ax_err.set_xlabel("final goal error per run [m]")
    fig.suptitle(f"campaign: {summary['runs']} runs, {summary['errors']} errors")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write(summary: dict, records: list[dict], out: Path) -> None:
    """``summary.json``, ``summary.txt`` and ``campaign.png`` into ``out``."""
    (out / SUMMARY_JSON).write_text(json.dumps(summary, indent=1) + "\n")
    (out / SUMMARY_TXT).write_text(table(summary) + "\n")
    plot(summary, records, out / PLOT_PNG)
