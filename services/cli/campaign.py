"""``archer campaign``: a sweep of lockstep runs (scenarios x seeds x variants x options).

Each run is one ``archer sim --mode lockstep`` run, done in-process in a worker through the
same function (:func:`services.cli.sim.run_lockstep`) with the same arguments, so a campaign's
record of a run is what ``archer sim --json`` prints for it. Options are ``archer sim``'s own
(``--option perception=depth``); comma-separated values make an axis of the sweep
(``--option perception=truth,depth``).

Writes into ``--out``:

- ``runs.jsonl``: one JSON line per finished run: its ``key`` and ``spec`` (scenario, seed,
  variant, options) and either ``report`` (the sim's JSON report) or ``error`` and ``traceback``.
  A failing run is recorded and the sweep goes on. The file is the campaign's memory: a run
  whose key is already there is not run again (``--retry-errors`` reruns those that failed);
- ``summary.json`` and ``summary.txt``: per group of runs that differ only by seed, the success
  rate with its Wilson interval, falls, collisions, error percentiles, RTF
  (:mod:`services.cli.campaign_report`);
- ``campaign.png``: success rates with their intervals and the final goal errors per group.

Runs go to a local pool of worker processes (default one per core) or, with ``--ray ADDRESS``,
to a Ray cluster (``local``: a private instance on this machine); see
:mod:`services.cli.campaign_pool`.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import sys
import time
import traceback
from pathlib import Path
from typing import Any

from robot_description import params as rd
from services.runtime.process_env import prepare_environment

RUNS_FILE = "runs.jsonl"
# archer sim's options a campaign may set (the rest are about output, real time or the view)
SIM_OPTIONS = ("duration", "estimator", "planner", "controller", "perception", "obstacles", "config", "no-noise", "keep-going",
               "model-error", "sensing")
FLAG_OPTIONS = ("no-noise", "keep-going")  # store_true flags: true/false
TRUE_WORDS, FALSE_WORDS = ("1", "true", "yes", "on"), ("0", "false", "no", "off")
PROGRESS_WIDTH = 30


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scenario", required=True, help="comma list of scenarios (archer sim --scenario)")
    parser.add_argument("--seeds", default="0-9", help="comma list of seeds and inclusive ranges, e.g. 0-99 or 1,5,10-12")
    parser.add_argument("--variant", default=rd.DEFAULT_VARIANT, help=f"comma list of robot variants ({', '.join(rd.VARIANTS)})")
    parser.add_argument("--option", action="append", default=[], metavar="NAME=V1[,V2...]",
                        help=f"an archer sim option for every run ({', '.join(SIM_OPTIONS)}); several values make an axis")
    parser.add_argument("--out", required=True, help="campaign folder: runs.jsonl, summary.json/.txt, campaign.png")
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1, help="local worker processes (default: one per core)")
    parser.add_argument("--ray", default=None, metavar="ADDRESS",
                        help="run on this Ray cluster (HOST:PORT, or 'local' for a private instance on 127.0.0.1); needs .[cluster]")
    parser.add_argument("--retry-errors", action="store_true", help="run again the runs recorded with an error")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.add_argument("--json", action="store_true", help="print the summary as one JSON object (last stdout line)")


def parse_seeds(text: str) -> list[int]:
    """``"0-3,7"`` -> ``[0, 1, 2, 3, 7]`` (ranges inclusive, order kept, duplicates dropped)."""
    seeds: list[int] = []
    for part in filter(None, (p.strip() for p in text.split(","))):
        first, sep, last = part.partition("-")
        try:
            span = range(int(first), int(last) + 1) if sep else range(int(part), int(part) + 1)
        except ValueError:
            raise ValueError(f"--seeds: {part!r} is not a seed or a range A-B") from None
        if not span:
            raise ValueError(f"--seeds: empty range {part!r}")
        seeds += [s for s in span if s not in seeds]
    if not seeds:
        raise ValueError("--seeds: no seed")
    return seeds


def _option_value(name: str, text: str) -> Any:
    """The JSON value of one option: flags are booleans, numbers are numbers, the rest strings."""
    if name in FLAG_OPTIONS:
        if text.lower() not in TRUE_WORDS + FALSE_WORDS:
            raise ValueError(f"--option {name}: expected true or false, got {text!r}")
        return text.lower() in TRUE_WORDS
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return text


def parse_options(items: list[str]) -> dict[str, list[Any]]:
    """``["perception=truth,depth", "duration=5"]`` -> ``{"perception": ["truth", "depth"], "duration": [5]}``."""
    axes: dict[str, list[Any]] = {}
    for item in items:
        name, sep, values = item.partition("=")
        name = name.strip().removeprefix("--").replace("_", "-")
        if not sep or not values.strip():
            raise ValueError(f"--option {item!r}: expected NAME=VALUE[,VALUE...]")
        if name not in SIM_OPTIONS:
            raise ValueError(f"--option {name}: a campaign sets only {', '.join(SIM_OPTIONS)}")
        if name in axes:
            raise ValueError(f"--option {name} given twice: list its values with commas")
        axes[name] = [_option_value(name, v.strip()) for v in values.split(",")]
    return axes


def expand(scenarios: list[str], seeds: list[int], variants: list[str], option_axes: dict[str, list[Any]]) -> list[dict]:
    """Every run of the sweep as a spec; seeds vary fastest, so a group's runs finish together."""
    names = sorted(option_axes)
    specs = []
    for scenario, variant, values in itertools.product(scenarios, variants, itertools.product(*(option_axes[n] for n in names))):
        options = dict(zip(names, values))
        specs += [{"scenario": scenario, "seed": seed, "variant": variant, "options": options} for seed in seeds]
    return specs


def spec_key(spec: dict) -> str:
    """A run's identity in ``runs.jsonl``: its spec as canonical JSON."""
    return json.dumps(spec, sort_keys=True, separators=(",", ":"))


def sim_argv(spec: dict) -> list[str]:
    """The ``archer sim`` arguments of a spec (lockstep, quiet, JSON report)."""
    argv = ["--scenario", spec["scenario"], "--seed", str(spec["seed"]), "--variant", spec["variant"], "--quiet", "--json"]
    for name, value in sorted(spec["options"].items()):
        if name in FLAG_OPTIONS:
            argv += [f"--{name}"] if value else []
        else:
            argv += [f"--{name}", str(value)]
    return argv


def sim_arguments(spec: dict) -> argparse.Namespace:
    """``archer sim``'s own parser on the spec, so a campaign accepts exactly what the command does."""
    from services.cli import sim

    parser = argparse.ArgumentParser(prog="archer sim", exit_on_error=False)
    sim.add_arguments(parser)
    try:
        return parser.parse_args(sim_argv(spec))
    except (argparse.ArgumentError, SystemExit) as exc:  # SystemExit: what exit_on_error does not cover
        raise ValueError(f"archer sim refuses {' '.join(sim_argv(spec))}: {exc}") from None


def run_spec(spec: dict) -> dict:
    """One run, as a worker does it: the record for ``runs.jsonl``; never raises for the run's own failure."""
    prepare_environment()  # a Ray worker did not start through archer's entry point
    from services.cli.sim import run_lockstep

    record: dict[str, Any] = {"key": spec_key(spec), "spec": spec}
    t0 = time.perf_counter()
    try:
        record["report"] = run_lockstep(sim_arguments(spec))
    except Exception as exc:  # a failing run is data: recorded, and the sweep goes on
        record["error"] = f"{type(exc).__name__}: {exc}"
        record["traceback"] = traceback.format_exc()
    record["worker_wall_s"] = round(time.perf_counter() - t0, 3)
    record["worker"] = f"{os.uname().nodename}:{os.getpid()}"
    return record


def crash_record(spec: dict, reason: str) -> dict:
    """The record of a run whose worker died under it (no traceback: the process is gone)."""
    return {"key": spec_key(spec), "spec": spec, "error": f"WorkerCrash: {reason}", "traceback": ""}


def read_records(path: Path) -> dict[str, dict]:
    """The runs already in ``runs.jsonl``, the last record of a key winning; a torn last line is ignored."""
    records: dict[str, dict] = {}
    if not path.exists():
        return records
    with path.open() as f:
        for line in f:
            try:
                record = json.loads(line)
            except json.JSONDecodeError:  # a line cut by a kill: that run is simply run again
                continue
            records[record["key"]] = record
    return records


class Progress:
    """Runs done out of the sweep on stderr: redrawn in place on a terminal, a line per 10 % otherwise."""

    def __init__(self, total: int, enabled: bool) -> None:
        self.total, self.enabled = total, enabled and total > 0
        self.tty = sys.stderr.isatty()
        self.done = self.errors = 0
        self.t0 = time.perf_counter()
        self.last_decile = -1

    def advance(self, record: dict) -> None:
        self.done += 1
        self.errors += "error" in record
        if not self.enabled:
            return
        frac = self.done / self.total
        wall = time.perf_counter() - self.t0
        eta = wall / frac - wall
        text = (f"[{'#' * int(frac * PROGRESS_WIDTH):<{PROGRESS_WIDTH}}] {self.done}/{self.total} runs, "
                f"{self.errors} errors, {wall:6.0f} s, ETA {eta:5.0f} s")
        if self.tty:
            sys.stderr.write("\r" + text + ("\n" if self.done == self.total else ""))
            sys.stderr.flush()
        elif int(frac * 10) > self.last_decile:
            self.last_decile = int(frac * 10)
            print(text, file=sys.stderr, flush=True)


def sweep(specs: list[dict], out: Path, workers: int, ray_address: str | None = None,
          retry_errors: bool = False, progress: bool = False) -> dict[str, dict]:
    """Run the specs not finished yet in ``out/runs.jsonl``, appending each record as it comes;
    the records of every spec of the sweep, by key."""
    from services.cli import campaign_pool

    out.mkdir(parents=True, exist_ok=True)
    runs_path = out / RUNS_FILE
    done = read_records(runs_path)
    todo = [s for s in specs if spec_key(s) not in done or (retry_errors and "error" in done[spec_key(s)])]
    bar = Progress(len(todo), progress)
    executor = campaign_pool.RayPool(ray_address, workers) if ray_address else campaign_pool.LocalPool(workers)
    with runs_path.open("a") as f, executor:
        for record in executor.map_unordered(run_spec, todo, crash_record):
            f.write(json.dumps(record) + "\n")
            f.flush()  # what is written survives a kill: the next start resumes after it
            done[record["key"]] = record
            bar.advance(record)
    return {spec_key(s): done[spec_key(s)] for s in specs}


def _split(text: str) -> list[str]:
    return [v.strip() for v in text.split(",") if v.strip()]


def build_specs(args: argparse.Namespace) -> list[dict]:
    """The sweep the arguments ask for, every spec checked by archer sim's parser before any runs."""
    from sim_twin import scenarios as sc

    scenarios, variants = _split(args.scenario), _split(args.variant)
    unknown = [s for s in scenarios if s not in sc.SCENARIOS] + [v for v in variants if v not in rd.VARIANTS]
    if unknown or not scenarios or not variants:
        raise ValueError(f"unknown or missing scenario/variant {unknown}; scenarios: {', '.join(sc.SCENARIOS)}; "
                         f"variants: {', '.join(rd.VARIANTS)}")
    specs = expand(scenarios, parse_seeds(args.seeds), variants, parse_options(args.option))
    for spec in {spec_key({**s, "seed": 0}): s for s in specs}.values():  # one check per combination
        sim_arguments(spec)
    return specs


def run(args: argparse.Namespace) -> int:
    """Exit code 0 when the sweep ran (failed runs included: they are data); 2 for a bad request."""
    from services.cli import campaign_report

    try:
        specs = build_specs(args)
        if args.workers < 1:
            raise ValueError("--workers must be at least 1")
        out = Path(args.out)
        t0 = time.perf_counter()
        records = sweep(specs, out, args.workers, args.ray, args.retry_errors, not args.quiet)
    except (ValueError, ImportError) as exc:
        print(f"archer campaign: {exc}", file=sys.stderr)
        return 2
    wall = time.perf_counter() - t0
    summary = campaign_report.summarize(list(records.values()))
    summary["campaign_wall_s"] = round(wall, 1)
    summary["executor"] = f"ray {args.ray}" if args.ray else f"local pool of {args.workers}"
    campaign_report.write(summary, list(records.values()), out)
    if args.json:
        print(json.dumps(summary))
    else:
        print(campaign_report.table(summary))
    return 0
