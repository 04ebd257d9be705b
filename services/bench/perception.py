"""``archer bench perception``: Algorithm 4 on 200 x 200 grids of 5 cm.

Decomposes synthetic maps (rooms, corridors, random clutter; several seeds each) into
convex free cells, from the map's start cell, and prints: ``grid``, ``polytopes``
(median count), ``ms_p50``, ``ms_p99`` (per decomposition), ``coverage`` (worst map:
fraction of the free cells reachable from the start whose centre lies in a polygon),
``overlap_cells`` (occupied cells any returned polygon overlaps, exact square test: 0
by construction, since the decomposition drops such polygons before returning) beside
``polygons_dropped_for_overlap`` (how many it dropped, summed over the maps: what the
fits got wrong, which ``overlap_cells`` cannot show),
``cpu_ms_p50`` (CPU time of this process per decomposition, for a busy machine),
``connected`` (maps where overlapping polygons chain start to goal), and the obstacle
mode's time.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from onboard.contracts.params import PerceptionParams
from onboard.perception import maps
from onboard.perception.decomposition import decompose_free_space, target_region
from onboard.perception.geometry import cell_centres, chain_exists, covered_mask, overlapping_cells
from onboard.perception.obstacles import obstacles_from_mask

RESOLUTION_M = 0.05
ORIGIN_M = (-5.0, -5.0)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--maps", default="rooms,corridors,clutter", help="comma-separated map kinds")
    parser.add_argument("--seeds", type=int, default=3, help="maps per kind")
    parser.add_argument("--repeat", type=int, default=10, help="timed decompositions per map")
    parser.add_argument("--size", type=int, default=200, help="grid side [cells]")


def measure(args: argparse.Namespace) -> dict:
    params = PerceptionParams()
    times: list[float] = []
    cpu_times: list[float] = []
    obstacle_times: list[float] = []
    counts: list[int] = []
    coverage: list[float] = []
    overlap = 0
    dropped = 0
    connected = 0
    n_maps = 0
    kinds = [k.strip() for k in args.maps.split(",") if k.strip()]
    for kind in kinds:
        if kind not in maps.BUILDERS:
            raise SystemExit(f"unknown map kind {kind!r}; known: {sorted(maps.BUILDERS)}")
    decompose_free_space(~maps.rooms(args.size).occupied, RESOLUTION_M, ORIGIN_M, params)  # compile / warm
    for kind in kinds:
        for seed in range(args.seeds):
            tm = maps.BUILDERS[kind](size=args.size, seed=seed)
            free = ~tm.occupied
            start = tuple(cell_centres(np.array([tm.start[0]]), np.array([tm.start[1]]), RESOLUTION_M, ORIGIN_M)[0])
            goal = tuple(cell_centres(np.array([tm.goal[0]]), np.array([tm.goal[1]]), RESOLUTION_M, ORIGIN_M)[0])
            for _ in range(args.repeat):
                t0, c0 = time.perf_counter(), time.process_time()
                polys, stats = decompose_free_space(free, RESOLUTION_M, ORIGIN_M, params, start=start, must_cover=(start, goal))
                times.append((time.perf_counter() - t0) * 1e3)
                cpu_times.append((time.process_time() - c0) * 1e3)
                t0 = time.perf_counter()
                obstacles_from_mask(tm.occupied, RESOLUTION_M, ORIGIN_M, params)
                obstacle_times.append((time.perf_counter() - t0) * 1e3)
            n_maps += 1
            counts.append(len(polys))
            target = target_region(free, RESOLUTION_M, ORIGIN_M, start)
            coverage.append(float(covered_mask(polys, free.shape, RESOLUTION_M, ORIGIN_M)[target].mean()))
            overlap += sum(len(overlapping_cells(p, tm.occupied, RESOLUTION_M, ORIGIN_M)) for p in polys)
            dropped += stats.dropped_for_overlap  # the same seeded fits on every repeat: the last one's
            connected += int(chain_exists(polys, np.array(start), np.array(goal)))
    return {
        "grid": f"{args.size}x{args.size}",
        "resolution_m": RESOLUTION_M,
        "maps": n_maps,
        "polytopes": int(np.median(counts)),
        "ms_p50": round(float(np.percentile(times, 50)), 2),
        "ms_p99": round(float(np.percentile(times, 99)), 2),
        "cpu_ms_p50": round(float(np.percentile(cpu_times, 50)), 2),  # this process's CPU time: less hurt by a loaded machine
        "coverage": round(min(coverage), 4),
        "coverage_mean": round(float(np.mean(coverage)), 4),
        "overlap_cells": overlap,
        "polygons_dropped_for_overlap": dropped,
        "connected": f"{connected}/{n_maps}",
        "obstacles_ms_p50": round(float(np.percentile(obstacle_times, 50)), 2),
    }
