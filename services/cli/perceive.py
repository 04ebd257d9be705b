"""``archer perceive``: convex free cells or convex obstacles of an occupancy grid, offline.

    archer perceive --grid GRID.npy --resolution R --origin X Y [--mode free|obstacles] --json

GRID is a 2D ``.npy`` array, nonzero meaning occupied, row index along y, column index
along x; ``--origin`` is the world position [m] of the lower-left corner of cell
[0, 0]; ``--resolution`` the cell side [m]. Output: one JSON object with ``mode``,
``polytopes`` (list of ``{"A", "b", "vertices"}``, world [m]; ``A x <= b``), ``ms``.
A bad grid or argument gets a clear error on stderr and exit code 2.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time

import numpy as np

from onboard.contracts.params import PerceptionParams
from onboard.perception.decomposition import decompose_free_space
from onboard.perception.obstacles import obstacles_from_mask

EXIT_BAD_INPUT = 2
MAX_CELLS = 4096 * 4096  # a sanity bound on what one call decomposes


class BadInput(ValueError):
    pass


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--grid", required=True, help="2D .npy array, nonzero = occupied, rows along y")
    parser.add_argument("--resolution", required=True, type=float, help="cell side [m]")
    parser.add_argument("--origin", required=True, type=float, nargs=2, metavar=("X", "Y"),
                        help="world position [m] of the lower-left corner of cell [0, 0]")
    parser.add_argument("--mode", choices=("free", "obstacles"), default="free")
    parser.add_argument("--json", action="store_true", help="print one JSON object")


def load_grid(path: str) -> np.ndarray:
    """The occupied mask of a ``.npy`` grid; raises :class:`BadInput` with the reason."""
    try:
        arr = np.load(path, allow_pickle=False)
    except FileNotFoundError:
        raise BadInput(f"grid file not found: {path}") from None
    except (ValueError, OSError) as exc:
        raise BadInput(f"not a readable .npy array: {path} ({exc})") from None
    if not isinstance(arr, np.ndarray):
        raise BadInput(f"{path} holds several arrays (.npz); expected one 2D array")
    if arr.ndim != 2:
        raise BadInput(f"grid must be 2D (rows along y, columns along x), got shape {arr.shape}")
    if arr.size == 0:
        raise BadInput(f"grid is empty (shape {arr.shape})")
    if arr.size > MAX_CELLS:
        raise BadInput(f"grid has {arr.size} cells, more than {MAX_CELLS}")
    if arr.dtype.kind not in "biuf":
        raise BadInput(f"grid must be bool, integer or float, got dtype {arr.dtype}")
    if arr.dtype.kind == "f" and not np.all(np.isfinite(arr)):
        raise BadInput("grid has NaN or infinite cells")
    return arr != 0


def perceive(occupied: np.ndarray, resolution: float, origin: tuple[float, float], mode: str,
             params: PerceptionParams = PerceptionParams()) -> dict:
    if not (math.isfinite(resolution) and resolution > 0):
        raise BadInput(f"resolution must be a positive number of metres, got {resolution}")
    if not all(math.isfinite(v) for v in origin):
        raise BadInput(f"origin must be finite, got {list(origin)}")
    t0 = time.perf_counter()
    if mode == "free":
        polys, _ = decompose_free_space(~occupied, resolution, origin, params)
    else:
        polys = obstacles_from_mask(occupied, resolution, origin, params)
    ms = (time.perf_counter() - t0) * 1e3
    return {
        "mode": mode,
        "polytopes": [{"A": p.A.tolist(), "b": p.b.tolist(), "vertices": p.vertices.tolist()} for p in polys],
        "ms": round(ms, 3),
    }


def run(args: argparse.Namespace) -> int:
    try:
        occupied = load_grid(args.grid)
        out = perceive(occupied, args.resolution, (args.origin[0], args.origin[1]), args.mode)
    except BadInput as exc:
        print(f"archer perceive: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    if args.json:
        print(json.dumps(out))
    else:
        print(f"{len(out['polytopes'])} {args.mode} polytopes in {out['ms']:.1f} ms")
    return 0
