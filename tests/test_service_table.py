"""The service table (services/table.py): every process has a row, every robot unit a
process, and the runtime holds each service to what its row says it reads and writes."""

from __future__ import annotations

from pathlib import Path

import pytest

from onboard.contracts.topics import STANDBY_SERVICES, STANDBY_SUFFIX, TOPICS
from services.runtime.clock import WallClock
from services.runtime.service import EVERY_TOPIC, Service
from services.runtime.supervisor import parse_unit
from services.table import SERVICES

UNITS = Path(__file__).resolve().parent.parent / "deploy" / "systemd"


def test_every_unit_runs_a_row_and_every_row_with_a_unit_has_one():
    unit_files = {p.name for p in UNITS.glob("*.service")}
    rows_with_units = {row.unit for row in SERVICES.values() if row.unit}
    # a hot standby's unit runs a second instance of its service's row (services/runtime/service.py)
    standby_units = {f"archer-{s}{STANDBY_SUFFIX}.service": s for s in STANDBY_SERVICES}
    assert unit_files == rows_with_units | set(standby_units)
    for row in SERVICES.values():
        if row.unit:
            exec_start = parse_unit((UNITS / row.unit).read_text())["Service"]["ExecStart"][-1].split()
            assert exec_start[1:3] == ["run", row.process], row.unit
    for unit, process in standby_units.items():
        parsed = parse_unit((UNITS / unit).read_text())
        assert parsed["Service"]["ExecStart"][-1].split()[1:3] == ["run", process], unit
        assert f"archer-{process}.service" in parsed["Unit"]["After"][-1].split(), unit  # the primary first


@pytest.mark.parametrize("process", sorted(SERVICES))
def test_each_row_reads_and_writes_known_topics(process):
    row = SERVICES[process].describe()
    cls = SERVICES[process].service_class()
    assert cls.subscribes == EVERY_TOPIC or set(cls.subscribes) <= set(TOPICS)
    assert set(row["publishes"]) <= set(TOPICS)
    assert row["params"] == list(cls.params_sections)


class _Planner(Service):
    name = "planner"
    subscribes = ("goal",)


def test_the_runtime_refuses_a_publisher_or_a_subscription_the_row_does_not_list():
    service = _Planner(ns="archer/test_table", endpoint="tcp/127.0.0.1:1", params={}, clock=WallClock())
    with pytest.raises(ValueError, match="planner may not publish 'torque_cmd'"):
        service.publisher("torque_cmd")  # the access control would deny it on the robot
    with pytest.raises(ValueError, match="planner subscribes to 'imu'"):
        service.on_message("imu", lambda msg: None)
    with pytest.raises(ValueError, match="planner subscribes to 'state'"):
        service.latest_sampled("state")


def test_a_missing_optional_dependency_is_one_clear_line_before_anything_starts(monkeypatch):
    """Without the `mocap` extra, the run that needs it says which extra to install, at once,
    instead of a unit that never comes up."""
    import importlib.util
    import subprocess
    import sys

    from services.table import SERVICES, missing_dependencies

    real_find_spec = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "motioncapture" else real_find_spec(name, *a))
    lines = missing_dependencies(["estimator", "mocap"])
    assert lines == ["mocap needs the Python module 'motioncapture': install the 'mocap' extra (pip install -e '.[mocap]' in the checkout)"]
    assert SERVICES["estimator"].missing() == []
    # the same through the command line, in a process where the module cannot be found
    hide = ("import importlib.util, sys; f = importlib.util.find_spec; "
            "importlib.util.find_spec = lambda n, *a: None if n == 'motioncapture' else f(n, *a); "
            "from services.cli.main import main; sys.exit(main(sys.argv[1:]))")
    done = subprocess.run([sys.executable, "-c", hide, "run", "mocap", "--endpoint", "tcp/127.0.0.1:9"], capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 2 and "install the 'mocap' extra" in done.stderr and done.stderr.count("\n") == 1, done.stderr
