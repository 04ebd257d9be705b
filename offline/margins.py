"""One-factor margins of the stack against the twin's model error (issue 26): each factor of
:mod:`sim_twin.model_error` alone, on a ladder of growing values, with the stack nominal, until
the robot first misses its goal and first falls; the same ladder for each controller config
(e.g. before and after a change). ``archer margins`` runs the ladders as a campaign
(:func:`services.cli.campaign.sweep`: resumable, a local pool or Ray) and writes the table and
the plot this module makes from the records.

A rung is one fixed value of one factor (``--model-error name=value``: for a per-wheel or
per-axis factor the value is every wheel's or axis's); the runs of a rung are the scenarios x
seeds asked. A rung fails on the first fall of any of its runs; it misses when a run does not
reach its goal (or collides) without falling.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class Ladder:
    factor: str  # a sim_twin.model_error factor
    values: tuple[float, ...]  # growing away from the MJCF
    why: str  # what the ladder spans


# The ladders: from about the datasheet profile's spread to well past where a robot would be built.
LADDERS: tuple[Ladder, ...] = (
    Ladder("com_x", (0.01, 0.02, 0.03, 0.04, 0.05, 0.06), "CoM off the spine, body x [m]"),
    Ladder("wheel_viscous", (0.002, 0.005, 0.01, 0.02, 0.05), "each wheel's bearing drag [N m s/rad] (catalogue: <= 1e-3)"),
    Ladder("wheel_coulomb", (0.01, 0.02, 0.05, 0.1, 0.2), "each wheel's Coulomb friction [N m] (catalogue: <= 1e-2)"),
    Ladder("spring_stiffness", (-0.2, -0.4, -0.6, -0.8), "foot spring stiffness, relative (datasheet: +-10 %)"),
    Ladder("spring_damping", (10.0, 20.0, 40.0, 80.0, 160.0), "foot spring losses [N s/m] (not published)"),
    Ladder("wheel_torque_constant", (-0.2, -0.4, -0.6, -0.8), "every wheel's torque constant, relative (datasheet: +-10 %)"),
    Ladder("imu_misalign", (0.01, 0.02, 0.04, 0.08, 0.16), "IMU mount rotation on each body axis [rad]"),
    Ladder("imu_latency", (0.002, 0.005, 0.01, 0.02, 0.04), "extra IMU latency [s]"),
    Ladder("actuator_delay", (0.002, 0.005, 0.01, 0.02, 0.04), "extra command delay to the motors [s]"),
    Ladder("pose_latency", (0.01, 0.02, 0.05, 0.1, 0.2), "extra motion-capture latency [s]"),
)


def ladder(factor: str) -> Ladder:
    for lad in LADDERS:
        if lad.factor == factor:
            return lad
    raise ValueError(f"no ladder for {factor!r}; ladders: {', '.join(lad.factor for lad in LADDERS)}")


def rung_error(factor: str, value: float) -> str:
    """The ``--model-error`` of one rung."""
    return f"{factor}={value:g}"


def specs(ladders: list[Ladder], scenarios: list[str], seeds: list[int], configs: list[str], variant: str) -> list[dict]:
    """Every run: configs x ladders x rungs x scenarios x seeds, as campaign specs."""
    out = []
    for config in configs:
        for lad in ladders:
            for value in lad.values:
                for scenario in scenarios:
                    for seed in seeds:
                        options = {"estimator": "kalman", "model-error": rung_error(lad.factor, value)}
                        if config:
                            options["config"] = config
                        out.append({"scenario": scenario, "seed": seed, "variant": variant, "options": options})
    return out


@dataclass
class Rung:
    value: float
    runs: int = 0
    errors: int = 0  # runs that did not finish (a crash is not a margin: reported apart)
    falls: int = 0  # runs with a fall
    misses: int = 0  # runs that did not reach the goal or collided, without falling
    goal_error_max: float = 0.0  # [m] over the runs that did not fall

    @property
    def verdict(self) -> str:
        return "fall" if self.falls else "miss" if self.misses else "error" if self.errors else "ok"


@dataclass
class Margin:
    factor: str
    config: str
    rungs: list[Rung]

    def first(self, verdicts: tuple[str, ...]) -> float | None:
        return next((r.value for r in self.rungs if r.verdict in verdicts), None)

    @property
    def first_fall(self) -> float | None:
        return self.first(("fall",))

    @property
    def first_miss(self) -> float | None:
        return self.first(("fall", "miss"))

    @property
    def holds_to(self) -> float | None:
        """The largest rung before the first miss or fall (None: not even the first)."""
        held = None
        for r in self.rungs:
            if r.verdict != "ok":
                break
            held = r.value
        return held


def margins(records: list[dict], ladders: list[Ladder], configs: list[str]) -> list[Margin]:
    """The rungs of every (config, factor) from the campaign's records."""
    by_rung: dict[tuple[str, str], list[dict]] = {}
    for rec in records:
        options = rec["spec"]["options"]
        by_rung.setdefault((options.get("config", ""), options["model-error"]), []).append(rec)
    out = []
    for config in configs:
        for lad in ladders:
            rungs = []
            for value in lad.values:
                rung = Rung(value)
                for rec in by_rung.get((config, rung_error(lad.factor, value)), []):
                    rung.runs += 1
                    report = rec.get("report")
                    if report is None:
                        rung.errors += 1
                    elif report["falls"]:
                        rung.falls += 1
                    else:
                        if not report["goal_reached"] or report["collisions"]:
                            rung.misses += 1
                        err = report.get("final_goal_error_m")
                        if err is not None and math.isfinite(err):
                            rung.goal_error_max = max(rung.goal_error_max, err)
                rungs.append(rung)
            out.append(Margin(lad.factor, config, rungs))
    return out


def config_label(config: str) -> str:
    return Path(config).stem if config else "default"


def _fmt(value: float | None) -> str:
    return "-" if value is None else f"{value:g}"


def table(results: list[Margin], configs: list[str]) -> str:
    """Markdown: per factor, each config's margin (holds to / first miss / first fall)."""
    head = "| factor | ladder | " + " | ".join(f"{config_label(c)}: holds to / first miss / first fall" for c in configs) + " |"
    lines = [head, "|" + "---|" * (2 + len(configs))]
    by = {(m.factor, m.config): m for m in results}
    for lad in LADDERS:
        if (lad.factor, configs[0]) not in by:
            continue
        cells = []
        for c in configs:
            m = by[(lad.factor, c)]
            errors = sum(r.errors for r in m.rungs)
            note = f" ({errors} runs crashed)" if errors else ""
            cells.append(f"{_fmt(m.holds_to)} / {_fmt(m.first_miss)} / {_fmt(m.first_fall)}{note}")
        lines.append(f"| `{lad.factor}` | {lad.why}: {', '.join(f'{v:g}' for v in lad.values)} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def plot(results: list[Margin], configs: list[str], path: Path) -> None:
    """One panel per factor: the worst goal error per rung, per config; a cross where a run fell."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    factors = [lad.factor for lad in LADDERS if any(m.factor == lad.factor for m in results)]
    cols = 4
    rows = math.ceil(len(factors) / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.0 * cols, 3.0 * rows), squeeze=False)
    by = {(m.factor, m.config): m for m in results}
    fall_height = 3.0  # [m] where a fall is drawn, above any goal error
    for ax, factor in zip(axes.flat, factors):
        for k, c in enumerate(configs):
            m = by[(factor, c)]
            xs = [abs(r.value) for r in m.rungs]
            ys = [fall_height if r.falls else max(r.goal_error_max, 1e-4) for r in m.rungs]
            line, = ax.plot(xs, ys, "o-", label=config_label(c), alpha=0.8)
            falls = [(x, y) for x, y, r in zip(xs, ys, m.rungs) if r.falls]
            if falls:
                ax.plot(*zip(*falls), "x", color=line.get_color(), markersize=12, markeredgewidth=2.5)
        ax.set_yscale("log")
        ax.set_ylim(1e-3, 5.0)
        ax.axhline(fall_height, color="grey", lw=0.5, ls=":")
        sign = "-" if by[(factor, configs[0])].rungs[0].value < 0 else ""
        ax.set_xlabel(f"{sign}|{factor}|")
        ax.set_ylabel("worst goal error [m] (x: fell)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    for ax in list(axes.flat)[len(factors):]:
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def write(results: list[Margin], configs: list[str], out: Path) -> tuple[Path, Path]:
    """``margins.md`` (the table) and ``margins.png`` (the plot) in ``out``, and the rungs as JSON."""
    out.mkdir(parents=True, exist_ok=True)
    md, png = out / "margins.md", out / "margins.png"
    md.write_text(table(results, configs) + "\n")
    plot(results, configs, png)
    rungs = [{"factor": m.factor, "config": config_label(m.config), "holds_to": m.holds_to, "first_miss": m.first_miss,
              "first_fall": m.first_fall, "rungs": [vars(r) | {"verdict": r.verdict} for r in m.rungs]} for m in results]
    (out / "margins.json").write_text(json.dumps(rungs, indent=1) + "\n")
    return md, png
