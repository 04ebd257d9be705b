"""systemd units, example configs and `archer deploy install`."""

from __future__ import annotations

import ctypes.util
import json
import os
import shutil
import signal
import socket
import time
import stat
import subprocess
import sys
from pathlib import Path

import pytest
import zenoh

from services.runtime import zenoh_configs as zc
from services.cli.deploy import (EXAMPLE_CONFIG_DIR, EXPOSURE_MAX, apply, ip_allow_dropins, plan_install, render_units,
                                 systemd_exposure, systemd_verify, unit_templates)
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


def needs_systemd_security() -> None:
    if shutil.which("systemd-analyze") is None:
        pytest.skip("systemd-analyze is not installed")
    probe = subprocess.run(["systemd-analyze", "security", "--offline=true", "--help"], capture_output=True, text=True, check=False)
    if probe.returncode != 0:
        pytest.skip(f"this systemd-analyze cannot rate unit files offline (systemd 250 or later): {probe.stderr.strip()}")


def test_every_unit_is_locked_down_and_still_verifies(tmp_path):
    """Issue 30.4: each service unit rates an exposure of at most 2.0, with the drop-ins
    `archer deploy install` adds for the robot too, and systemd still accepts every unit."""
    needs_systemd_security()
    archer = str(Path(sys.executable).parent / "archer")  # ExecStart must exist for verify
    rendered = render_units(archer)
    result = systemd_verify(rendered, tmp_path)
    assert result.returncode == 0 and result.stderr.strip() == "", result.stderr
    exposure = systemd_exposure(rendered, tmp_path)
    assert sorted(exposure) == sorted(name for name in rendered if name.endswith(".service"))  # every service unit rated
    assert {f"archer-{s}.service" for s in (*ROBOT, "twin", "mocap", "view", "camera", "camera-overhead")} <= set(exposure)
    assert all(level <= EXPOSURE_MAX for level in exposure.values()), exposure
    # the robot's drop-ins open the allow lists (a unit's settings then its drop-in's, as systemd reads them)
    dropins = ip_allow_dropins(EXAMPLE_CONFIG_DIR / "archer-firmware.toml")
    dropins["archer-router.service"] = (Path(__file__).resolve().parents[1] / "deploy/systemd/archer-lan.conf").read_text()
    opened = {name: rendered[name] + "\n" + text.split("[Service]\n", 1)[1] for name, text in dropins.items()}
    (tmp_path / "robot").mkdir()
    assert all(level <= EXPOSURE_MAX for level in systemd_exposure(opened, tmp_path / "robot").values())
    # and the rating would catch a unit that lost its hardening
    loose = {"archer-view.service": rendered["archer-view.service"].replace("SystemCallFilter=", "#SystemCallFilter=")}
    (tmp_path / "loose").mkdir()
    assert systemd_exposure(loose, tmp_path / "loose")["archer-view.service"] > EXPOSURE_MAX


def test_locked_down_units_keep_what_each_service_needs():
    """The hardening takes nothing a service uses: real time where a loop asks for it, the
    drives' bus and serial adapters for the hardware, writable memory for numba's JIT, the
    recorder's directory, loopback for every Zenoh session."""
    parsed = units()
    for service in ROBOT + ("twin", "mocap", "view"):
        unit = parsed[f"archer-{service}.service"]["Service"]
        filters = unit["SystemCallFilter"]
        assert filters[0] == "@system-service" and all(f.startswith("~") for f in filters[1:]), service
        denied = {g for f in filters[1:] for g in f.removeprefix("~").split()}
        assert "@privileged" in denied
        raises_itself = service in ("control", "estimator", "hardware")
        # sched_setscheduler / sched_setaffinity (the loops raise themselves); the others' nice is their unit's
        assert ("@resources" in denied) == (not raises_itself), service
        assert unit["CapabilityBoundingSet"][-1] == ("CAP_SYS_NICE" if raises_itself else "")
        assert ("PrivateUsers" in unit) == (not raises_itself)  # a user namespace voids the capability
        assert ("MemoryDenyWriteExecute" in unit) == (service not in ("planner", "perception")), service
        assert unit["IPAddressDeny"] == ["any"] and unit["IPAddressAllow"] == ["localhost"]
        assert unit["ProtectProc"] == ["invisible"] and unit["RemoveIPC"] == ["yes"]
        # /proc without its system files, but where numba (/proc/cpuinfo) or a library (/proc/mounts) reads them
        assert ("ProcSubset" in unit) == (service not in ("planner", "perception", "twin")), service
        assert unit["UMask"] == (["0027"] if service == "recorder" else ["0077"])
        # AF_CAN for the drives; AF_NETLINK for the router only (it lists the interfaces it listens on)
        extra = {"hardware": {"AF_CAN"}, "router": {"AF_NETLINK"}}.get(service, set())
        assert set(unit["RestrictAddressFamilies"][-1].split()) == {"AF_UNIX", "AF_INET"} | extra, service
    hardware = parsed["archer-hardware.service"]["Service"]
    assert hardware["DeviceAllow"] == ["char-ttyACM rw", "char-ttyUSB rw"] and hardware["DevicePolicy"] == ["closed"]
    for service in ("planner", "perception"):
        assert parsed[f"archer-{service}.service"]["Service"]["CacheDirectory"] == ["archer"]  # numba's cache
    assert parsed["archer-recorder.service"]["Service"]["StateDirectory"] == ["archer"]  # the recordings


JAILED = ("router", "estimator", "control", "recorder", "view")  # the router first: the others are its clients
JAIL_READY_TIMEOUT_S = 180.0  # imports and Zenoh on a loaded 2-core machine


def test_services_start_under_their_units_system_call_filter(tmp_path):
    """The filters take nothing a service needs to start: the router and its clients, each run
    under its unit's SystemCallFilter, RestrictAddressFamilies and MemoryDenyWriteExecute
    (tests/unit_jail.py, libseccomp as systemd loads it), report READY=1 and keep running;
    control's loop process and its real-time request included."""
    if shutil.which("systemd-analyze") is None or ctypes.util.find_library("seccomp") is None:
        pytest.skip("needs systemd-analyze (its system call groups) and libseccomp")
    rendered = render_units(str(Path(sys.executable).parent / "archer"))
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        endpoint = f"tcp/127.0.0.1:{s.getsockname()[1]}"
    config = tmp_path / "archer.toml"
    config.write_text(f'[recorder]\ndirectory = "{tmp_path / "rec"}"\n')
    procs: dict[str, subprocess.Popen] = {}
    managers: dict[str, socket.socket] = {}
    ready: set[str] = set()

    def collect(until: float, wanted: set[str]) -> None:
        while time.monotonic() < until and not wanted <= ready:
            for name, sock in managers.items():
                try:
                    if "READY=1" in sock.recv(4096).decode().splitlines():
                        ready.add(name)
                except BlockingIOError:
                    pass
            dead = {n: p.returncode for n, p in procs.items() if p.poll() is not None}
            assert not dead, (dead, {n: (tmp_path / f"{n}.log").read_text()[-2000:] for n in dead})
            time.sleep(0.05)

    try:
        for name in JAILED:
            unit = tmp_path / f"archer-{name}.service"
            unit.write_text(rendered[unit.name])
            notify = tmp_path / f"{name}.notify"
            managers[name] = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
            managers[name].bind(str(notify))
            managers[name].setblocking(False)
            env = dict(os.environ, NOTIFY_SOCKET=str(notify), NUMBA_CACHE_DIR=str(tmp_path / "numba"))
            command = [sys.executable, "-m", "services.cli.main", "run", name, "--endpoint", endpoint,
                       "--namespace", "archer/jail", "--config", str(config)]
            procs[name] = subprocess.Popen([sys.executable, str(Path(__file__).with_name("unit_jail.py")), str(unit), "--", *command],
                                           env=env, stdout=open(tmp_path / f"{name}.log", "w"), stderr=subprocess.STDOUT,
                                           start_new_session=True)
            if name == "router":
                collect(time.monotonic() + JAIL_READY_TIMEOUT_S, {"router"})
        collect(time.monotonic() + JAIL_READY_TIMEOUT_S, set(JAILED))
        assert ready == set(JAILED), {n: (tmp_path / f"{n}.log").read_text()[-2000:] for n in set(JAILED) - ready}
        collect(time.monotonic() + 2.0, set(JAILED) | {"never"})  # and they keep running
        logs = {n: (tmp_path / f"{n}.log").read_text() for n in JAILED}
        assert all("Traceback" not in text for text in logs.values()), logs
    finally:
        for proc in reversed(procs.values()):
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGTERM)
        for proc in procs.values():
            try:
                proc.wait(15)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
        for sock in managers.values():
            sock.close()


def test_install_opens_the_ip_allow_lists_to_what_the_config_names(tmp_path):
    assert ip_allow_dropins(EXAMPLE_CONFIG_DIR / "archer.toml") == {}  # drives on CAN, mocap on loopback
    firmware = ip_allow_dropins(EXAMPLE_CONFIG_DIR / "archer-firmware.toml")
    params = load_params(EXAMPLE_CONFIG_DIR / "archer-firmware.toml")
    assert f"IPAddressAllow={params['archer_firmware'].board_host}\n" in firmware["archer-hardware.service"]
    assert f"IPAddressAllow={params['mocap'].host}\n" in firmware["archer-mocap.service"]
    apply(plan_install(tmp_path, FAKE_ARCHER, profile="archer-firmware"), dry_run=False)
    unit_dir = tmp_path / "etc/systemd/system"
    assert (unit_dir / "archer-hardware.service.d/50-ip-allow.conf").read_text() == firmware["archer-hardware.service"]
    lan = unit_dir / "archer-router.service.d/archer-lan.conf"
    assert "IPAddressAllow=" in lan.read_text()
    lan.write_text("[Service]\nIPAddressAllow=192.168.7.0/24\n")  # the operator's robot LAN is kept
    apply(plan_install(tmp_path, FAKE_ARCHER, profile="archer-firmware"), dry_run=False)
    assert lan.read_text() == "[Service]\nIPAddressAllow=192.168.7.0/24\n"
    named = tmp_path / "named.toml"
    named.write_text('[mocap]\nhost = "motive.lab"\n')
    with pytest.raises(ValueError, match="needs an address"):
        ip_allow_dropins(named)


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
    assert sorted(p.name for p in unit_dir.glob("archer*[!d]")) == sorted(unit_templates())  # *.d: drop-ins
    control = (unit_dir / "archer-control.service").read_text()
    assert f"ExecStart={FAKE_ARCHER} run control --config /etc/archer/archer.toml --zenoh-config /etc/archer/zenoh/control.json5" in control
    assert "@ARCHER@" not in control and "@CONFIG_DIR@" not in control  # (@system-service is a filter set)
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


def test_archer_outdoor_profile_runs_the_d435_in_place_of_motion_capture(tmp_path):
    apply(plan_install(tmp_path, FAKE_ARCHER, profile="archer-outdoor"), dry_run=False)
    params = load_params(tmp_path / "etc/archer/archer.toml")
    assert params["hardware"].backend == "archer-firmware" and params["estimator"].position_source == "odometry"
    assert params["perception"].segmenter == "color" and params["camera"].source == "device"
    parsed = units()
    wants = one(parsed["archer-outdoor.target"], "Unit", "Wants").split()
    assert "archer-camera.service" in wants and "archer-mocap.service" not in wants
    for name in wants:  # stopping the target stops its units
        assert "archer-outdoor.target" in one(parsed[name], "Unit", "PartOf").split(), name
    conflicts = set(one(parsed["archer-outdoor.target"], "Unit", "Conflicts").split())
    assert conflicts == {"archer.target", "archer-sil.target", "archer-firmware.target"}
