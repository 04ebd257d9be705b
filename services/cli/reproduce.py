"""``archer reproduce``: the thesis's ARCHER figures and tables, regenerated and compared (issue 29).

Runs each item (:mod:`services.reproduce.items`), writes its figures and ``DIR/items/ITEM.json``,
then ``DIR/report.md`` over every item done so far. Resumable twice over: an item whose JSON is
there is not run again (``--redo`` runs it anew, its lockstep runs too: a redone item's figures are
its commit's), and inside an item the lockstep runs already in ``DIR/runs/ITEM.jsonl`` are kept. ``--quick`` is a small subset with few seeds (CI checks the
report is produced); a quick and a full run do not share a folder.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

ITEMS_DIR = "items"
MODE_FILE = "mode.json"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", required=True, help="folder: report.md, the figures, items/ and runs/ (resumable)")
    parser.add_argument("--only", default=None, help="comma list of items (default: all; --list names them)")
    parser.add_argument("--quick", action="store_true", help="the CI subset: a few items, few seeds, short runs")
    parser.add_argument("--redo", action="store_true",
                        help="run the chosen items again, their lockstep runs too, even where their result is there")
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1, help="local campaign workers (default: one per core)")
    parser.add_argument("--ray", default=None, metavar="ADDRESS", help="run campaigns on this Ray cluster ('local': a private one)")
    parser.add_argument("--report", default=None, metavar="FILE.md",
                        help="write the report here too, its figures copied into a folder named after it (docs/reproduction.md)")
    parser.add_argument("--list", action="store_true", help="list the items and exit")
    parser.add_argument("--quiet", action="store_true", help="no progress")


def _chosen(args: argparse.Namespace, items: dict) -> list:
    if args.only:
        names = [n.strip() for n in args.only.split(",") if n.strip()]
        unknown = [n for n in names if n not in items]
        if unknown:
            raise ValueError(f"unknown items {unknown}; known: {', '.join(items)}")
        return [items[n] for n in names]
    return [i for i in items.values() if i.quick or not args.quick]


def _check_mode(out: Path, quick: bool) -> None:
    """A folder holds quick or full results, never both (their seeds and durations differ)."""
    path = out / MODE_FILE
    if path.exists():
        was = json.loads(path.read_text())["quick"]
        if was != quick:
            raise ValueError(f"{out} holds a {'quick' if was else 'full'} reproduction: use another --out")
    else:
        out.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps({"quick": quick}))


def run(args: argparse.Namespace) -> int:
    from services.reproduce import report
    from services.reproduce.engine import RUNS_DIR, Context
    from services.reproduce.catalogue import load_all
    from services.reproduce.items import ItemResult

    items = load_all()
    if args.list:
        for it in items.values():
            print(f"{it.name:10s} {it.where:40s} {it.title}{'  [quick]' if it.quick else ''}")
        return 0
    try:
        chosen = _chosen(args, items)
        if args.workers < 1:
            raise ValueError("--workers must be at least 1")
        out = Path(args.out)
        _check_mode(out, args.quick)
    except ValueError as exc:
        print(f"archer reproduce: {exc}", file=sys.stderr)
        return 2
    ctx = Context(out=out, quick=args.quick, workers=args.workers, ray=args.ray, progress=not args.quiet)
    done_dir = out / ITEMS_DIR
    done_dir.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    failed = []
    for k, it in enumerate(chosen, 1):
        path = done_dir / f"{it.name}.json"
        if path.exists() and not args.redo:
            continue
        if args.redo:  # the runs kept from an older commit would be reported under this one
            (out / RUNS_DIR / f"{it.name}.jsonl").unlink(missing_ok=True)
        if not args.quiet:
            print(f"[{k}/{len(chosen)}] {it.name}: {it.title}", file=sys.stderr, flush=True)
        start = time.perf_counter()
        try:
            result = it.build(ctx)
        except Exception as exc:  # an item that cannot run is reported, and the others go on
            import traceback

            traceback.print_exc()
            failed.append(f"{it.name}: {type(exc).__name__}: {exc}")
            continue
        result.wall_s = time.perf_counter() - start
        result.commit = report.commit()
        path.write_text(json.dumps(result.to_json(), indent=1))
        if not args.quiet:
            print(f"[{k}/{len(chosen)}] {it.name}: {result.verdict} ({result.wall_s:.0f} s)", file=sys.stderr, flush=True)
    results = {p.stem: ItemResult.from_json(json.loads(p.read_text())) for p in sorted(done_dir.glob("*.json"))}
    wall = sum(r.wall_s for r in results.values())
    header = {"commit": report.commit(), "machine": report.machine(),
              "command": f"archer reproduce --out {out}{' --quick' if args.quick else ''}",
              "wall time of the items": f"{wall:.0f} s (this invocation: {time.perf_counter() - t0:.0f} s)",
              "workers": f"ray {args.ray}" if args.ray else f"local pool of {args.workers}"}
    path = report.write(out, list(items.values()), results, header)
    if args.report:
        report.write(out, list(items.values()), results, header, Path(args.report))
    print(json.dumps({"report": str(path), "items": {n: r.verdict for n, r in results.items()}, "failed": failed,
                      "wall_s": round(wall, 1)}))
    return 1 if failed else 0
