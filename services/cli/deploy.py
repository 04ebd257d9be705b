"""``archer deploy``: install the stack as systemd services; check and regenerate configs.

``archer deploy install [--prefix DIR] [--dry-run]`` writes, under ``DIR`` (default
``/``, used like ``DESTDIR``: paths inside the files are the target's):

- ``etc/systemd/system/``: the units of ``deploy/systemd/`` with ``@ARCHER@`` (the
  ``archer`` executable) and ``@CONFIG_DIR@`` (``/etc/archer``) filled in;
- ``usr/lib/sysusers.d/archer.conf`` (the ``archer`` user) and
  ``etc/systemd/network/80-archer-can.network`` (the CAN bus);
- the drop-ins that open a unit's IP allow list (loopback only in the units) to what it
  talks to: the robot's LAN for the router (``archer-lan.conf``, kept once installed), and,
  from the installed ``archer.toml``, ARCHER's board for the hardware service and the mocap
  server for the mocap service;
- ``etc/archer/archer.toml`` and ``etc/archer/environment`` from ``deploy/config/``,
  only when absent (an operator's edits are kept);
- ``etc/archer/zenoh/``: the router's config with access control, its password file
  (``users.txt``) and one client config per service and for the operator;
  secrets are mode 0640, group ``archer``. Passwords are generated once and kept on later installs.

``archer deploy verify`` runs ``systemd-analyze verify`` on the rendered units and
``systemd-analyze security`` on each service (exposure at most ``EXPOSURE_MAX``);
``archer deploy render DIR`` writes them to ``DIR``; ``archer deploy acl [--write]``
prints (or rewrites) the generated Zenoh configs checked in under ``deploy/zenoh/``.
"""

from __future__ import annotations

import argparse
import grp
import ipaddress
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

from services.runtime import zenoh_configs as zc
from services.runtime.config import load_params

DEPLOY_DIR = Path(__file__).resolve().parents[2] / "deploy"
UNIT_DIR = DEPLOY_DIR / "systemd"
EXAMPLE_CONFIG_DIR = DEPLOY_DIR / "config"
EXPOSURE_MAX = 2.0  # `systemd-analyze security` exposure every service unit stays within (tests/test_deploy.py)
ZENOH_DIR = DEPLOY_DIR / "zenoh"
TARGET_CONFIG_DIR = "/etc/archer"
SYSTEMD_UNIT_DIR = "etc/systemd/system"
SYSUSERS_PATH = "usr/lib/sysusers.d/archer.conf"
NETWORK_PATH = "etc/systemd/network/80-archer-can.network"
LAN_DROPIN = "archer-lan.conf"  # the robot's LAN: the router serves an offboard workstation there
IP_DROPIN_NAME = "50-ip-allow.conf"
SERVICE_GROUP = "archer"
UNIT_SUFFIXES = (".service", ".target")
KEPT_CONFIGS = ("archer.toml", "environment")  # never overwritten once installed
# robot profiles: deploy/config/<profile>.toml is installed as archer.toml, and the profile's target runs it
PROFILES = {"archer": "archer.target", "archer-firmware": "archer-firmware.target", "archer-outdoor": "archer-outdoor.target"}
_PLACEHOLDER = re.compile(r"@[A-Z_]+@")


@dataclass
class Action:
    path: Path  # where it goes, under the prefix
    text: str
    mode: int = 0o644
    keep_existing: bool = False  # leave an existing file alone (operator's edits)
    group_readable: bool = False  # chgrp to the service group when it exists


def archer_executable() -> str:
    """The ``archer`` entry point next to this interpreter, else the one on PATH."""
    beside = Path(sys.executable).parent / "archer"
    if beside.is_file() and os.access(beside, os.X_OK):
        return str(beside)
    found = shutil.which("archer")
    if found is None:
        raise FileNotFoundError("no `archer` executable: install the package (pip install -e .) first")
    return str(Path(found).resolve())


def unit_templates() -> dict[str, str]:
    return {p.name: p.read_text() for p in sorted(UNIT_DIR.iterdir()) if p.suffix in UNIT_SUFFIXES}


def render_units(archer: str, config_dir: str = TARGET_CONFIG_DIR) -> dict[str, str]:
    """Unit name -> text with the placeholders filled in."""
    out = {}
    for name, text in unit_templates().items():
        rendered = text.replace("@ARCHER@", archer).replace("@CONFIG_DIR@", config_dir)
        leftover = _PLACEHOLDER.findall(rendered)
        if leftover:
            raise ValueError(f"{name}: unknown placeholders {leftover}")
        out[name] = rendered
    return out


def ip_allow_dropins(config: Path) -> dict[str, str]:
    """Unit name -> drop-in adding the addresses beyond loopback that ``config`` (an
    ``archer.toml``) makes the unit talk to: ARCHER's board (``[archer_firmware] board_host``,
    hardware backend ``archer-firmware``) and the mocap server (``[mocap] host``)."""
    params = load_params(config)
    wanted = {"archer-mocap.service": ("[mocap] host", params["mocap"].host)}
    if params["hardware"].backend == "archer-firmware":
        wanted["archer-hardware.service"] = ("[archer_firmware] board_host", params["archer_firmware"].board_host)
    out = {}
    for unit, (key, host) in wanted.items():
        try:
            address = ipaddress.ip_address(host)
        except ValueError:
            raise ValueError(f"{config}: {key} = {host!r}: the unit's IP allow list needs an address, not a name") from None
        if address.is_loopback:
            continue  # the units allow loopback already
        out[unit] = (f"# {unit}: the one address beyond loopback it talks to, {key} of {config.name}.\n"
                     f"# Written by `archer deploy install`; rerun it after changing {key}.\n"
                     f"[Service]\nIPAddressAllow={address}\n")
    return out


def read_users_file(path: Path) -> dict[str, str]:
    if not path.is_file():
        return {}
    pairs = (line.split(":", 1) for line in path.read_text().splitlines() if ":" in line)
    return {user: password for user, password in pairs}


def plan_install(prefix: Path, archer: str, config_dir: str = TARGET_CONFIG_DIR, profile: str = "archer") -> list[Action]:
    """Every file ``install`` writes, with its text and mode; ``profile`` picks the robot's
    parameters (``deploy/config/<profile>.toml`` becomes ``archer.toml``)."""
    if profile not in PROFILES:
        raise ValueError(f"unknown profile {profile!r}; known: {', '.join(PROFILES)}")
    zenoh_dir = f"{config_dir}/zenoh"
    local = prefix / config_dir.lstrip("/")
    actions = [Action(prefix / SYSTEMD_UNIT_DIR / name, text) for name, text in render_units(archer, config_dir).items()]
    actions.append(Action(prefix / SYSUSERS_PATH, (UNIT_DIR / "archer.sysusers.conf").read_text()))
    actions.append(Action(prefix / NETWORK_PATH, (UNIT_DIR / "80-archer-can.network").read_text()))
    actions.append(Action(prefix / SYSTEMD_UNIT_DIR / "archer-router.service.d" / LAN_DROPIN, (UNIT_DIR / LAN_DROPIN).read_text(),
                          keep_existing=True))
    sources = {"archer.toml": f"{profile}.toml"}
    for name in KEPT_CONFIGS:
        actions.append(Action(local / name, (EXAMPLE_CONFIG_DIR / sources.get(name, name)).read_text(), keep_existing=True))
    # the allow lists follow the config the services will read: the installed one when kept
    installed = local / "archer.toml"
    for unit, text in ip_allow_dropins(installed if installed.is_file() else EXAMPLE_CONFIG_DIR / sources["archer.toml"]).items():
        actions.append(Action(prefix / SYSTEMD_UNIT_DIR / f"{unit}.d" / IP_DROPIN_NAME, text))
    # Zenoh: passwords generated once, kept afterwards (services already hold theirs).
    users_path = local / "zenoh" / "users.txt"
    passwords = read_users_file(users_path)
    passwords.update({u: p for u, p in zc.new_passwords().items() if u not in passwords})
    users_file = f"{zenoh_dir}/users.txt"
    actions.append(Action(users_path, zc.users_file_text(passwords), mode=0o640, group_readable=True))
    router = zc.router_config(users_file=users_file)
    actions.append(Action(local / "zenoh" / "router.json5", zc.render(router, "The robot's router (archer-router.service). Generated by `archer deploy install`."), mode=0o644))
    for user in zc.users():
        text = zc.render(zc.client_config(user, passwords[user]), f"Zenoh session of `{user}`: a client of the robot's router, authenticated.")
        actions.append(Action(local / "zenoh" / f"{user}.json5", text, mode=0o640, group_readable=True))
    return actions


def apply(actions: list[Action], dry_run: bool) -> list[str]:
    """Write the files (or say what would be written); returns one line per file."""
    try:
        gid = grp.getgrnam(SERVICE_GROUP).gr_gid
    except KeyError:
        gid = None  # no `archer` group yet (systemd-sysusers creates it)
    lines = []
    for act in actions:
        verb = "would write" if dry_run else "wrote"
        if act.keep_existing and act.path.exists():
            lines.append(f"kept        {act.path} (exists; edit it by hand)")
            continue
        if not dry_run:
            act.path.parent.mkdir(parents=True, exist_ok=True)
            tmp = act.path.with_name(act.path.name + ".tmp")
            tmp.write_text(act.text)
            os.chmod(tmp, act.mode)
            if act.group_readable and gid is not None and os.geteuid() == 0:
                os.chown(tmp, 0, gid)
            os.replace(tmp, act.path)
        lines.append(f"{verb:<11} {act.path} ({act.mode:04o}, {len(act.text)} bytes)")
    return lines


NEXT_STEPS = """next, on the robot:
  systemd-sysusers && systemctl daemon-reload && systemctl restart systemd-networkd
  systemctl enable --now {target}        # or: systemctl start archer-sil.target
  journalctl -u 'archer-*' -f                 # JSON log lines per service
  ARCHER_ZENOH_CONFIG={config_dir}/zenoh/operator.json5 archer status   # as a member of group archer"""


def systemd_verify(units: dict[str, str], directory: Path) -> subprocess.CompletedProcess:
    """``systemd-analyze verify`` on the units written to ``directory`` (together, so
    that their references to each other resolve)."""
    paths = []
    for name, text in units.items():
        path = directory / name
        path.write_text(text)
        paths.append(str(path))
    return subprocess.run(["systemd-analyze", "verify", *paths], capture_output=True, text=True, check=False)


_EXPOSURE = re.compile(r"Overall exposure level for (\S+): ([0-9.]+)")


def systemd_exposure(units: dict[str, str], directory: Path) -> dict[str, float]:
    """``systemd-analyze security --offline=true`` on each service of ``units`` written to
    ``directory``: its overall exposure, 0 (locked down) to 10 (exposed)."""
    out = {}
    for name, text in units.items():
        if not name.endswith(".service"):
            continue
        path = directory / name
        path.write_text(text)
        result = subprocess.run(["systemd-analyze", "security", "--offline=true", "--no-pager", str(path)],
                                capture_output=True, text=True, check=False)
        found = _EXPOSURE.search(result.stdout)
        if found is None:
            raise RuntimeError(f"systemd-analyze security {name}: no exposure in its answer: {result.stderr.strip()}")
        out[name] = float(found.group(2))
    return out


# --- command line ------------------------------------------------------------------------------


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="action", required=True, metavar="ACTION")
    p = sub.add_parser("install", help="render and install units, configs and Zenoh credentials")
    p.add_argument("--prefix", default="/", help="install root, as DESTDIR (default /)")
    p.add_argument("--dry-run", action="store_true", help="print what would be written, write nothing")
    p.add_argument("--archer", default=None, help="path of the archer executable the units run (default: this one)")
    p.add_argument("--profile", choices=sorted(PROFILES), default="archer",
                   help="the robot: archer (our drives and Teensy protocol), archer-firmware (ARCHER's own boards over UDP, OptiTrack)")
    p = sub.add_parser("render", help="write the rendered units to a directory")
    p.add_argument("directory")
    p.add_argument("--archer", default=None)
    sub.add_parser("verify", help="systemd-analyze verify the rendered units and rate their exposure (security)")
    p = sub.add_parser("acl", help="print the generated Zenoh router configs (access control from the topic table)")
    p.add_argument("--write", action="store_true", help=f"rewrite them under {ZENOH_DIR}")


def run(args: argparse.Namespace) -> int:
    try:
        if args.action == "install":
            archer = args.archer or archer_executable()
            lines = apply(plan_install(Path(args.prefix), archer, profile=args.profile), args.dry_run)
            print("\n".join(lines))
            print(NEXT_STEPS.format(config_dir=TARGET_CONFIG_DIR, target=PROFILES[args.profile]))
            return 0
        if args.action == "render":
            out = Path(args.directory)
            out.mkdir(parents=True, exist_ok=True)
            for name, text in render_units(args.archer or archer_executable()).items():
                (out / name).write_text(text)
                print(out / name)
            return 0
        if args.action == "verify":
            if shutil.which("systemd-analyze") is None:
                print("archer deploy verify: systemd-analyze is not installed", file=sys.stderr)
                return 2
            with tempfile.TemporaryDirectory() as tmp:
                units = render_units(archer_executable())
                result = systemd_verify(units, Path(tmp))
                exposure = systemd_exposure(units, Path(tmp))
            sys.stdout.write(result.stdout)
            sys.stderr.write(result.stderr)
            for name, level in exposure.items():
                print(f"{name}: exposure {level:.1f}{'' if level <= EXPOSURE_MAX else f' > {EXPOSURE_MAX}'}")
            clean = result.returncode == 0 and not result.stderr.strip() and max(exposure.values()) <= EXPOSURE_MAX
            print(f"{len(unit_templates())} units: {'ok' if clean else 'problems above'}")
            return 0 if clean else 1
        if args.action == "acl":
            if args.write:
                for path in zc.write_checked_in(ZENOH_DIR):
                    print(path)
            else:
                print(json.dumps(zc.access_control(), indent=2))
            return 0
    except (OSError, ValueError, RuntimeError) as exc:  # RuntimeError: a systemd-analyze that cannot rate
        print(f"archer deploy {args.action}: {exc}", file=sys.stderr)
        return 2
    return 2
