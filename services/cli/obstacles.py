"""``archer obstacles``: the overhead camera's floor and obstacles, for the operator (issue 28).

    archer obstacles calibrate [--config F.toml] [--source S] [--json]
    archer obstacles init [--config F.toml] [--source S] [--name K=NAME ...] [--out NAMES.json] [--json]

``calibrate`` fits the floor homography to the ArUco markers of ``[camera_overhead]`` on one frame of
the source (default: the section's) and prints the reprojection error (pixels in the undistorted
image, and metres on the floor). ``init`` is the thesis's one click per obstacle: it lists the
obstacles it sees (index, centre, area) and lets the operator name them: ``--name K=NAME`` for each
(non-interactive), else it asks for each on a terminal (empty: leave it out); the named ones are
written to ``--out`` (the service's ``camera_overhead.names_file``), whose tracks then carry the names.
Exit code 2 when the source cannot be read or the frame does not calibrate.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys

from drivers.camera_overhead import tracking as tk
from drivers.camera_overhead.calibration import CalibrationError
from drivers.camera_overhead.device import CameraError, VideoSource
from services.camera_overhead import ObstacleCamera, source_of
from services.runtime.config import ConfigError, load_params

EXIT_BAD_INPUT = 2


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("action", choices=("calibrate", "init"))
    parser.add_argument("--config", default=None, help="TOML with a [camera_overhead] section")
    parser.add_argument("--source", default=None, help="camera index or video file (default: camera_overhead.source)")
    parser.add_argument("--name", action="append", default=[], metavar="K=NAME", help="name obstacle K (init)")
    parser.add_argument("--out", default=None, help="write the named obstacles here (init)")
    parser.add_argument("--json", action="store_true", help="print one JSON object")


def _frame(camera_params, source: str | None):
    p = camera_params if source is None else dataclasses.replace(camera_params, source=source)
    with VideoSource(source_of(p), p.crop_left) as src:
        frame = src.read()
    if frame is None:
        raise CameraError(f"no frame from {p.source!r}")
    return p, frame


def run(args: argparse.Namespace) -> int:
    try:
        p = load_params(args.config, ("camera_overhead",))["camera_overhead"]
        p, frame = _frame(p, args.source)
        camera = ObstacleCamera(p)
        cal = camera.calibrate(frame)
        blobs = camera.blobs(frame) if args.action == "init" else []
        names = dict(_split(n) for n in args.name)
    except (CameraError, CalibrationError, ConfigError, ValueError, OSError) as exc:
        print(f"archer obstacles: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    if args.action == "calibrate":
        out = {"rms_px": round(cal.rms_px, 4), "rms_m": round(cal.rms_m, 5), "markers": list(cal.markers_used),
               "homography": cal.H.tolist()}
        print(json.dumps(out) if args.json else
              f"floor from markers {list(cal.markers_used)}: reprojection error {cal.rms_px:.3f} px rms, {1e3 * cal.rms_m:.1f} mm on the floor")
        return 0
    blobs.sort(key=lambda b: tuple(tk.centroid(b)))
    listed = [{"index": k, "centre": [round(float(v), 3) for v in tk.centroid(b)], "area_m2": round(_area(b), 4),
               "polygon": b.tolist()} for k, b in enumerate(blobs)]
    if not args.json:
        for o in listed:
            print(f"[{o['index']}] centre ({o['centre'][0]:.2f}, {o['centre'][1]:.2f}) m, {o['area_m2']:.3f} m^2")
    if not names and sys.stdin.isatty() and not args.json:
        for o in listed:
            name = input(f"name of [{o['index']}] (empty: leave it out): ").strip()
            if name:
                names[o["index"]] = name
    bad = [k for k in names if not 0 <= k < len(listed)]
    if bad:
        print(f"archer obstacles: no obstacle {bad} (seen: {len(listed)})", file=sys.stderr)
        return EXIT_BAD_INPUT
    named = [{"name": names[o["index"]], "centre": o["centre"], "polygon": o["polygon"]} for o in listed if o["index"] in names]
    if args.out:
        with open(args.out, "w", encoding="utf-8") as f:
            json.dump({"obstacles": named}, f, indent=1)
    if args.json:
        print(json.dumps({"obstacles": listed, "named": named, "rms_px": round(cal.rms_px, 4)}))
    return 0


def _split(text: str) -> tuple[int, str]:
    k, sep, name = text.partition("=")
    if not sep or not k.strip().isdigit() or not name.strip():
        raise ValueError(f"--name wants K=NAME, got {text!r}")
    return int(k), name.strip()


def _area(poly) -> float:
    x, y = poly[:, 0], poly[:, 1]
    return float(abs((x * (y.take(range(1, len(y) + 1), mode="wrap")) - y * (x.take(range(1, len(x) + 1), mode="wrap"))).sum()) / 2)
