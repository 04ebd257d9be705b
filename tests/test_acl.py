"""Access control: generated from the topic table, and enforced by a real router on loopback."""

from __future__ import annotations

import asyncio
import json
import shutil
import subprocess
import time
from pathlib import Path

import msgspec
import pytest
import zenoh

from services.runtime import zenoh_configs as zc
from onboard.contracts import messages as m
from onboard.contracts.topics import TOPICS, liveliness_key, params_key
from services.runtime.peers import live_services, query_status
from services.runtime.service import Service
from services.runtime.zenoh_session import free_endpoint, link_queue_config, loopback_config

NS = "archer/acltest"
DELIVERY_S = 0.5  # generous time for a put to cross the router on loopback
ZENOH_DIR = Path(__file__).resolve().parent.parent / "deploy" / "zenoh"


def test_checked_in_configs_are_the_generated_ones_and_parse():
    for name, text in zc.checked_in_files().items():
        path = ZENOH_DIR / name
        assert path.read_text() == text, f"{name} drifted from onboard/contracts/topics.py; run `archer deploy acl --write`"
        zenoh.Config.from_file(str(path))  # Zenoh itself accepts it


def test_every_config_queues_the_fast_priorities_alike():
    expected = link_queue_config()["size"]
    configs = {"loopback_config": loopback_config("peer", free_endpoint())}
    configs |= {path.name: zenoh.Config.from_file(str(path)) for path in sorted(ZENOH_DIR.glob("*.json5"))}
    assert len(configs) == 5
    for name, config in configs.items():
        sizes = json.loads(config.get_json("transport/link/tx/queue/size"))
        assert {k: sizes[k] for k in expected} == expected and expected["real_time"] > 2, name


def test_rules_follow_the_publishers_column():
    acl = zc.access_control()
    policies = {p["id"]: p for p in acl["policies"]}
    for topic in TOPICS.values():
        assert policies[f"{topic.name}-publishers"]["subjects"] == sorted(topic.publishers)
    # the two promises the deployment makes, spelled out
    for command in ("torque_cmd", "attitude_cmd"):
        assert policies[f"{command}-publishers"]["subjects"] == ["control"]
    for sensor in ("imu", "joints"):
        assert policies[f"{sensor}-publishers"]["subjects"] == ["hardware", "twin"]
    assert policies["pose-publishers"]["subjects"] == ["hardware", "mocap", "twin"]  # motion capture too
    assert policies["depth-publishers"]["subjects"] == ["camera", "hardware", "twin"]  # the D435 too
    rules = {r["id"]: r for r in acl["rules"]}
    put_rules = [r for r in rules.values() if "put" in r["messages"] and "ingress" in r["flows"]]
    assert all(r["id"].startswith("publish-") for r in put_rules)  # nothing else lets anyone publish
    assert acl["default_permission"] == "deny"


class Robot:
    """A router with the generated ACL on a free loopback port, and authenticated clients."""

    def __init__(self, tmp: Path) -> None:
        self.endpoint = free_endpoint()
        self.passwords = zc.new_passwords()
        users = tmp / "users.txt"
        users.write_text(zc.users_file_text(self.passwords))
        self.tmp = tmp
        config = zc.router_config(listen=[self.endpoint], users_file=str(users))
        self.router = zenoh.open(self._load("router", config))
        self.sessions: list[zenoh.Session] = []

    def _load(self, name: str, config: dict) -> zenoh.Config:
        path = self.tmp / f"{name}.json5"
        path.write_text(json.dumps(config))
        return zenoh.Config.from_file(str(path))

    def client_file(self, user: str, password: str | None = None) -> str:
        path = self.tmp / f"{user}.json5"
        path.write_text(json.dumps(zc.client_config(user, password or self.passwords[user], [self.endpoint])))
        return str(path)

    def client(self, user: str, password: str | None = None) -> zenoh.Session:
        session = zenoh.open(zenoh.Config.from_file(self.client_file(user, password)))
        self.sessions.append(session)
        return session

    def close(self) -> None:
        for s in self.sessions:
            s.close()
        self.router.close()


@pytest.fixture
def robot(tmp_path):
    r = Robot(tmp_path)
    try:
        yield r
    finally:
        r.close()


def _torque(tag: float) -> bytes:
    return m.encode(m.TorqueCommand(wheel_torque=[tag, 0.0, 0.0], foot_torque=0.0, armed=False))


def _imu(tag: float) -> bytes:
    return m.encode(m.ImuSample(quat=[1.0, 0, 0, 0], gyro=[tag, 0, 0], accel=[0, 0, 9.81]))


def test_only_allowed_publishers_get_through(robot):
    observer = robot.client("recorder")
    received: list[tuple[str, float]] = []

    def on_sample(sample: zenoh.Sample) -> None:
        key = str(sample.key_expr).removeprefix(NS + "/")
        data = json.loads(sample.payload.to_bytes())
        received.append((key, (data.get("wheel_torque") or data.get("gyro") or data.get("position"))[0]))

    sub = observer.declare_subscriber(f"{NS}/**", on_sample)
    sessions = {name: robot.client(name) for name in ("control", "planner", "hardware", "twin", "estimator", "operator")}
    time.sleep(DELIVERY_S)
    torque, imu, goal = (TOPICS[n].key(NS) for n in ("torque_cmd", "imu", "goal"))
    sessions["control"].put(torque, _torque(1.0))
    sessions["planner"].put(torque, _torque(2.0))  # denied
    sessions["operator"].put(torque, _torque(3.0))  # denied
    sessions["hardware"].put(imu, _imu(4.0))
    sessions["twin"].put(imu, _imu(5.0))
    sessions["estimator"].put(imu, _imu(6.0))  # denied
    sessions["control"].put(imu, _imu(7.0))  # denied
    sessions["operator"].put(goal, m.encode(m.Goal(position=[8.0, 0.0])))
    sessions["planner"].put(goal, m.encode(m.Goal(position=[9.0, 0.0])))  # denied
    time.sleep(DELIVERY_S)
    sub.undeclare()
    assert sorted(received) == [("control/torque", 1.0), ("plan/goal", 8.0), ("sensors/imu", 4.0), ("sensors/imu", 5.0)]


def test_a_wrong_password_cannot_connect(robot):
    with pytest.raises(zenoh.ZError):
        robot.client("control", password="not-the-password")


class Probe(Service):
    name = "estimator"
    params_sections = ("safety",)


def test_the_stack_works_under_access_control(robot):
    """Liveliness, status and parameters pass for the right subjects, and only for them."""

    async def scenario() -> None:
        service = Probe(ns=NS, config_file=robot.client_file("estimator"))
        task = asyncio.create_task(service.run())
        operator = robot.client("operator")
        planner = robot.client("planner")
        try:
            deadline = time.monotonic() + 10
            while "estimator" not in await asyncio.to_thread(live_services, operator, NS):
                assert time.monotonic() < deadline, "liveliness token not seen through the router"
                await asyncio.sleep(0.1)
            status = await asyncio.to_thread(query_status, operator, NS, "estimator")
            assert status is not None and status.state == "running"

            # a token posing as another service is dropped by the router
            fake = planner.liveliness().declare_token(liveliness_key(NS, "control"))
            await asyncio.sleep(DELIVERY_S)
            assert "control" not in await asyncio.to_thread(live_services, operator, NS)
            fake.undeclare()

            def set_limit(session: zenoh.Session, value: float) -> list:
                body = msgspec.json.encode(m.ParamRequest(set={"safety.wheel_torque_max": value}))
                return [r.ok for r in session.get(params_key(NS, "estimator"), payload=body, timeout=2.0) if r.ok]

            assert await asyncio.to_thread(set_limit, planner, 0.5) == []  # denied: no reply
            assert service.params["safety"].wheel_torque_max == 1.5
            assert len(await asyncio.to_thread(set_limit, operator, 1.0)) == 1
            assert service.params["safety"].wheel_torque_max == 1.0
        finally:
            service.stopping.set()
            await asyncio.wait_for(task, 10.0)

    asyncio.run(asyncio.wait_for(scenario(), 60))


def _openssl(*args: str, cwd: Path) -> None:
    subprocess.run(["openssl", *args], cwd=cwd, check=True, capture_output=True)


def _make_certs(d: Path, client: str) -> None:
    """A CA, the router's certificate for 127.0.0.1 and a client certificate (X.509 v3)."""
    ec = ["-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes"]
    _openssl("req", "-x509", *ec, "-keyout", "ca-key.pem", "-out", "ca.pem", "-days", "1", "-subj", "/CN=archer-test-ca", cwd=d)
    for name, ext in (("router", "subjectAltName=IP:127.0.0.1\n"), (client, f"subjectAltName=DNS:{client}\nextendedKeyUsage=clientAuth\n")):
        (d / f"{name}.ext").write_text(ext)
        _openssl("req", *ec, "-keyout", f"{name}-key.pem", "-out", f"{name}.csr", "-subj", f"/CN={name}", cwd=d)
        _openssl("x509", "-req", "-in", f"{name}.csr", "-CA", "ca.pem", "-CAkey", "ca-key.pem", "-CAcreateserial",
                 "-out", f"{name}.pem", "-days", "1", "-extfile", f"{name}.ext", cwd=d)


@pytest.mark.skipif(shutil.which("openssl") is None, reason="openssl is not installed")
def test_tls_router_admits_only_clients_with_a_certificate_and_keeps_the_acl(tmp_path):
    _make_certs(tmp_path, "planner")
    endpoint = "tls/127.0.0.1:" + free_endpoint().rsplit(":", 1)[1]
    passwords = zc.new_passwords()
    (tmp_path / "users.txt").write_text(zc.users_file_text(passwords))
    sessions = []

    def open_json(name: str, config: dict) -> zenoh.Session:
        (tmp_path / f"{name}.json5").write_text(json.dumps(config))
        session = zenoh.open(zenoh.Config.from_file(str(tmp_path / f"{name}.json5")))
        sessions.append(session)
        return session

    try:
        open_json("router", zc.router_config([endpoint], str(tmp_path / "users.txt"), tls=True, tls_dir=str(tmp_path)))
        planner = open_json("planner", zc.tls_client_config("planner", passwords["planner"], [endpoint], str(tmp_path)))
        no_cert = zc.client_config("planner", passwords["planner"], [endpoint])
        no_cert["transport"]["link"] = {"tls": {"root_ca_certificate": str(tmp_path / "ca.pem")}}
        with pytest.raises(zenoh.ZError):  # a password alone does not pass mutual TLS
            open_json("nocert", no_cert)
        received: list[str] = []
        sub = planner.declare_subscriber(f"{NS}/**", lambda s: received.append(str(s.key_expr)))
        observer = open_json("observer", zc.tls_client_config("planner", passwords["planner"], [endpoint], str(tmp_path)))
        time.sleep(DELIVERY_S)
        observer.put(TOPICS["waypoints"].key(NS), b"{}")  # the planner's own topic: allowed
        observer.put(TOPICS["torque_cmd"].key(NS), b"{}")  # not the planner's: denied
        time.sleep(DELIVERY_S)
        sub.undeclare()
        assert received == [TOPICS["waypoints"].key(NS)]
    finally:
        for s in reversed(sessions):
            s.close()


# real time: loops at their rate, processes and Zenoh over loopback share two loaded cores
pytestmark = pytest.mark.timing_sensitive(reason="real-time loops, processes or Zenoh over loopback on a shared host")
