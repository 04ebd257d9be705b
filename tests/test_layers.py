"""The folders are the layers, and imports point one way (README "Where things live").

``LAYERS`` is the one statement of the rule: each layer (a package, or a subpackage /
module that the longest prefix picks) with the layers it may import. Every import in
every module counts, including those inside functions and under ``TYPE_CHECKING``: a
lazy import is still a dependency the robot has to ship. Imports between modules must
also form no cycle, inside a layer as well.

The robot's services (everything in ``services`` but the twin, the command line and
the benches) run without the simulator: the second test imports them and builds their
controller and parameters with ``mujoco`` and ``sim_twin`` unimportable.
"""

from __future__ import annotations

import ast
import subprocess
import sys
import textwrap
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("onboard", "offline", "robot_description", "drivers", "sim_twin", "services", "deploy")

# Inside ``onboard``, the thesis's layers bottom to top (README "Where things live"): the
# contracts, shared geometry, estimation and perception, then the low level (its tracking
# layer, its planning layer, the controller composing them) and the high level (tracking,
# then planning). A layer may import those listed for it; the high level learns of the low
# level only through the contracts.
_CONTRACTS = {"onboard.contracts"}
_BASE = _CONTRACTS | {"onboard.geometry"}
_HIGH_TRACKING = _BASE | {"onboard.high_level.tracking"}
ONBOARD_LAYERS: dict[str, set[str]] = {
    "onboard.contracts": set(),
    "onboard.geometry": _CONTRACTS,
    "onboard.estimation": _BASE,
    "onboard.perception": _BASE,
    "onboard.low_level.tracking": _BASE | {"onboard.estimation"},
    "onboard.low_level.planning": _BASE | {"onboard.estimation", "onboard.low_level.tracking"},
    "onboard.low_level": _BASE | {"onboard.estimation", "onboard.low_level.tracking", "onboard.low_level.planning"},
    "onboard.high_level.tracking": _BASE,
    "onboard.high_level.planning": _HIGH_TRACKING | {"onboard.perception"},
}
_ONBOARD = set(ONBOARD_LAYERS)
_ROBOT = _ONBOARD | {"robot_description", "drivers", "services.runtime"}
LAYERS: dict[str, set[str]] = {
    # layer: the layers it may import (besides itself)
    **ONBOARD_LAYERS,
    "onboard": set(),  # the package's own docstring; every module lives in a layer above
    "offline": _ONBOARD | {"robot_description"},  # training: pure, never imported by the robot
    "robot_description": _ONBOARD,  # the MJCF and what is read from it, without MuJoCo
    "drivers": _ONBOARD | {"robot_description"},
    "sim_twin": _ONBOARD | {"robot_description"},  # physics, sensors, scenarios, lockstep
    "services.runtime": _ONBOARD | {"robot_description", "drivers"},
    "services": _ROBOT,  # one module per robot service process
    "services.twin": _ROBOT | {"services", "sim_twin"},  # the twin's service stands in for the hardware
    "deploy": _ROBOT | {"services"},  # units, Zenoh configs, the SIL soak
    "services.bench": _ROBOT | {"services", "services.twin", "sim_twin"},
    "services.cli": _ROBOT | {"services", "services.twin", "sim_twin", "deploy", "offline", "services.reproduce"},
    # archer reproduce: campaigns, benches and the examples, drawn as the thesis draws them
    "services.reproduce": _ROBOT | {"services", "services.twin", "sim_twin", "offline", "services.cli", "services.bench"},
}
ROBOT_SERVICES = ("control", "estimator", "planner", "perception", "hardware", "recorder", "mocap", "camera", "view")


def layer_of(module: str) -> str:
    parts = module.split(".")
    for n in range(len(parts), 0, -1):
        if ".".join(parts[:n]) in LAYERS:
            return ".".join(parts[:n])
    raise AssertionError(f"{module} is in no layer: add its package to LAYERS")


def _modules() -> dict[str, Path]:
    found = {}
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            parts = list(path.relative_to(ROOT).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            found[".".join(parts)] = path
    return found


def _imports(module: str, path: Path, known: dict[str, Path]) -> set[str]:
    """The package modules ``module`` imports (``from pkg import sub`` counts as ``pkg.sub``)."""
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                base = ".".join(anchor + ([node.module] if node.module else []))
            names = [f"{base}.{alias.name}" if f"{base}.{alias.name}" in known else base for alias in node.names]
        else:
            continue
        for name in names:
            while name and name not in known:  # a name inside a module: the module
                name = name.rpartition(".")[0]
            if name:
                out.add(name)
    return out


def _graph() -> dict[str, set[str]]:
    known = _modules()
    return {m: _imports(m, p, known) - {m} for m, p in known.items()}


def test_every_import_points_down() -> None:
    upward = []
    for module, imported in sorted(_graph().items()):
        mine = layer_of(module)
        for target in sorted(imported):
            theirs = layer_of(target)
            if theirs != mine and theirs not in LAYERS[mine]:
                upward.append(f"{module} ({mine}) imports {target} ({theirs})")
    assert not upward, "imports against the layers:\n" + "\n".join(upward)


def test_no_import_cycle() -> None:
    graph = _graph()
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    cycles: list[list[str]] = []

    def visit(v: str) -> None:  # Tarjan's strongly connected components
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                cycles.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    assert not cycles, "import cycles:\n" + "\n".join(" <-> ".join(c) for c in cycles)


def test_robot_services_run_without_the_simulator() -> None:
    code = textwrap.dedent(f"""
        import importlib, sys

        class NoSimulator:
            def find_spec(self, name, path=None, target=None):
                if name.split(".")[0] in ("mujoco", "sim_twin"):
                    raise ImportError(f"{{name}} is not installed on the robot")
                return None

        sys.meta_path.insert(0, NoSimulator())
        for name in {ROBOT_SERVICES!r}:
            importlib.import_module("services." + name)
        # What the services read at start-up: the robot's parameters and the low level built from them.
        from robot_description.params import VARIANTS, hopper_model, robot_params
        from robot_description.controller import build_controller
        for variant in VARIANTS:
            robot_params(variant), hopper_model(variant)
        build_controller()
        from services import hardware
        hardware.gear_ratios()
        assert not any(m.split(".")[0] in ("mujoco", "sim_twin") for m in sys.modules)
    """)
    done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=240)
    assert done.returncode == 0, done.stderr[-3000:]
