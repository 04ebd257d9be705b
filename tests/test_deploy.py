"""systemd units, example configs and `archer deploy install`."""

from __future__ import annotations

import json
import shutil
import stat
import subprocess
import sys
from pathlib import Path

import pytest
import zenoh

from services.runtime import zenoh_configs as zc
from services.cli.deploy import EXAMPLE_CONFIG_DIR, plan_install, apply, render_units, systemd_verify, unit_templates
from services.table import SERVICES
from services.runtime.config import load_params
from onboard.contracts.params import ControlParams, EstimatorParams, HardwareParams
from onboard.contracts.topics import STANDBY_SERVICES, STANDBY_SUFFIX
from services.runtime.supervisor import parse_unit, spec_from_unit

ROBOT = ("router", "hardware", "estimator", "control", "planner", "perception", "recorder")
HARDENING = {
    "NoNewPrivileges": "yes",
    "ProtectSystem": "strict",
    "PrivateTmp": "yes",
    "ProtectKernelTunables": "yes",
    "RestrictNamespaces": "yes",
    "LockPersonality": "yes",
}
FAKE_ARCHER = "/opt/archer/bin/archer"


def units() -> dict[str, dict]:
    return {name: parse_unit(text) for name, text in unit_templates().items()}


def one(unit: dict, section: str, key: str) -> str:
    return unit[section][key][-1]


def test_one_notify_unit_per_service_with_restart_watchdog_and_hardening():
    parsed = units()
    for service in ROBOT + ("twin", "mocap", "view"):
        unit = parsed[f"archer-{service}.service"]
        assert one(unit, "Service", "Type") == "notify"
        assert one(unit, "Service", "Restart") == "on-failure"
        assert float(one(unit, "Service", "WatchdogSec").removesuffix("s")) > 0
        for key, value in HARDENING.items():
            assert one(unit, "Service", key) == value, (service, key)
        families = one(unit, "Service", "RestrictAddressFamilies").split()
        assert {"AF_UNIX", "AF_INET"} <= set(families)
        assert ("AF_CAN" in families) == (service == "hardware")  # only the drives' bus
        exec_start = one(unit, "Service", "ExecStart").split()
        assert exec_start[:3] == ["@ARCHER@", "run", service] and service in SERVICES
        assert "@CONFIG_DIR@/archer.toml" in exec_start and f"@CONFIG_DIR@/zenoh/{service}.json5" in exec_start
        raises_itself = service in ("control", "estimator", "hardware")  # the 1 kHz loops and the bus master
        fifo_by_systemd = service in ("twin", "estimator")  # the hardware's stand-in; control's input, I/O threads too
        assert (one(unit, "Service", "RestrictRealtime") == "no") == (raises_itself or fifo_by_systemd)
        assert ("LimitRTPRIO" in unit["Service"]) == raises_itself
        assert (unit["Service"].get("CPUSchedulingPolicy") == ["fifo"]) == fifo_by_systemd
    control = parsed["archer-control.service"]["Service"]
    assert control["NotifyAccess"] == ["all"] and control["AmbientCapabilities"] == ["CAP_SYS_NICE"]
    for service in ("hardware", "estimator"):
        assert parsed[f"archer-{service}.service"]["Service"]["AmbientCapabilities"] == ["CAP_SYS_NICE"]
    assert spec_from_unit("estimator", ["true"]).fifo_priority == EstimatorParams().rt_priority
    twin = spec_from_unit("twin", ["true"])
    # the sensors' source below the estimator, the estimator below the control loop it feeds
    assert 0 < twin.fifo_priority < EstimatorParams().rt_priority < ControlParams().rt_priority
    assert HardwareParams().rt_priority < EstimatorParams().rt_priority
    robot = one(parsed["archer.target"], "Unit", "Wants").split()
    sil = one(parsed["archer-sil.target"], "Unit", "Wants").split()
    standbys = [f"archer-{s}{STANDBY_SUFFIX}.service" for s in STANDBY_SERVICES]  # hot standbys go with the stack
    assert sorted(robot) == sorted([f"archer-{s}.service" for s in ROBOT] + standbys)
    assert sorted(sil) == sorted([f"archer-{s}.service" for s in ROBOT if s != "hardware"] + ["archer-twin.service"] + standbys)
    firmware = one(parsed["archer-firmware.target"], "Unit", "Wants").split()
    assert sorted(firmware) == sorted([f"archer-{s}.service" for s in (*ROBOT, "mocap")] + standbys)
    assert "archer-view.service" not in robot + sil + firmware  # the viewer runs only when asked
    for name in firmware:  # stopping the target stops its units
        assert "archer-firmware.target" in one(parsed[name], "Unit", "PartOf").split(), name
    assert set(one(parsed["archer-firmware.target"], "Unit", "Conflicts").split()) == {"archer.target", "archer-sil.target"}


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze is not installed")
def test_rendered_units_pass_systemd_analyze_verify(tmp_path):
    archer = str(Path(sys.executable).parent / "archer")  # ExecStart must exist for verify
    result = systemd_verify(render_units(archer), tmp_path)
    assert result.returncode == 0 and result.stderr.strip() == "", result.stderr


def test_systemd_analyze_verify_would_catch_a_broken_unit(tmp_path):
    if shutil.which("systemd-analyze") is None:
        pytest.skip("systemd-analyze is not installed")
    broken = render_units(str(Path(sys.executable).parent / "archer"))
    broken["archer-router.service"] = broken["archer-router.service"].replace("Restart=on-failure", "Restart=sometimes")
    assert "restart specifier" in systemd_verify(broken, tmp_path).stderr


def test_example_configs_load():
    for path in sorted(EXAMPLE_CONFIG_DIR.glob("*.toml")):
        params = load_params(path)
        assert params["recorder"].chunk_s > 0
    assert load_params(EXAMPLE_CONFIG_DIR / "archer.toml")["control"].rt_priority > 0
    env = dict(line.split("=", 1) for line in (EXAMPLE_CONFIG_DIR / "environment").read_text().splitlines() if line and not line.startswith("#"))
    assert env["ARCHER_NAMESPACE"].startswith("archer/")


def test_install_writes_everything_and_keeps_edits_and_passwords(tmp_path):
    assert apply(plan_install(tmp_path, FAKE_ARCHER), dry_run=True)
    assert list(tmp_path.iterdir()) == []  # a dry run writes nothing

    lines = apply(plan_install(tmp_path, FAKE_ARCHER), dry_run=False)
    unit_dir = tmp_path / "etc/systemd/system"
    assert sorted(p.name for p in unit_dir.iterdir()) == sorted(unit_templates())
    control = (unit_dir / "archer-control.service").read_text()
    assert f"ExecStart={FAKE_ARCHER} run control --config /etc/archer/archer.toml --zenoh-config /etc/archer/zenoh/control.json5" in control
    assert "@" not in control
    conf = tmp_path / "etc/archer"
    users = conf / "zenoh/users.txt"
    assert stat.S_IMODE(users.stat().st_mode) == 0o640
    passwords = dict(line.split(":", 1) for line in users.read_text().splitlines())
    assert sorted(passwords) == zc.users()
    client = json.loads((conf / "zenoh/planner.json5").read_text().split("\n", 1)[1])
    assert client["transport"]["auth"]["usrpwd"] == {"user": "planner", "password": passwords["planner"]}
    for name in ("router.json5", "planner.json5", "operator.json5"):
        zenoh.Config.from_file(str(conf / "zenoh" / name))
    router = json.loads((conf / "zenoh/router.json5").read_text().split("\n", 1)[1])
    assert router["transport"]["auth"]["usrpwd"]["dictionary_file"] == "/etc/archer/zenoh/users.txt"
    load_params(conf / "archer.toml")
    assert (tmp_path / "usr/lib/sysusers.d/archer.conf").read_text().startswith("#")
    assert any("archer-control.service" in line for line in lines)

    # a second install keeps an operator's config edits and the passwords services hold
    (conf / "archer.toml").write_text("[control]\ncpu = 1\n")
    lines = apply(plan_install(tmp_path, FAKE_ARCHER), dry_run=False)
    assert (conf / "archer.toml").read_text() == "[control]\ncpu = 1\n"
    assert any(line.startswith("kept") and "archer.toml" in line for line in lines)
    assert dict(line.split(":", 1) for line in users.read_text().splitlines()) == passwords


def test_cli_dry_run(tmp_path):
    out = subprocess.run(
        [sys.executable, "-m", "services.cli.main", "deploy", "install", "--prefix", str(tmp_path), "--dry-run", "--archer", FAKE_ARCHER],
        capture_output=True, text=True, check=True,
    ).stdout
    assert "would write" in out and "archer-control.service" in out and "systemctl enable --now archer.target" in out
    assert list(tmp_path.iterdir()) == []


def test_archer_firmware_profile_installs_the_robot_lan_config(tmp_path):
    apply(plan_install(tmp_path, FAKE_ARCHER, profile="archer-firmware"), dry_run=False)
    params = load_params(tmp_path / "etc/archer/archer.toml")
    fw, hw, mocap, control = params["archer_firmware"], params["hardware"], params["mocap"], params["control"]
    assert hw.backend == "archer-firmware" and control.output == "attitude"
    assert (fw.board_host, fw.board_port, fw.computer_host, fw.computer_port) == ("10.0.0.7", 4333, "10.0.0.6", 4333)
    assert mocap.system == "optitrack" and mocap.host != "127.0.0.1"
    # the board's PD on Im(q) is the loop's on 2 Im(q) with twice the stiffness
    assert (fw.kp_tilt, fw.kp_yaw) == (2 * control.kp_tilt, 2 * control.kp_yaw)
    assert (fw.kd_tilt, fw.kd_yaw) == (control.kd_tilt, control.kd_yaw)
    with pytest.raises(ValueError):
        plan_install(tmp_path, FAKE_ARCHER, profile="nonesuch")
