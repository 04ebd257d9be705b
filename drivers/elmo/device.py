"""ELMO drives as CiA 402 devices, and the group that exchanges with all of them.

The device layer of the ELMO driver:

- :class:`ElmoDrive` knows one drive: it configures it over SDO (PDO mapping,
  cyclic synchronous torque mode, current clamp, heartbeats), converts joint units to
  the drive's (torque in per mille of the rated torque 0x6076, encoder counts) and
  builds its command frame (:meth:`ElmoDrive.make_command`) without sending it.
- :class:`DriveGroup` owns the bus: NMT, the SYNC producer, the host heartbeat
  producer, the consumer of the drives' heartbeats, EMCY handling, and one batched
  exchange per tick (:meth:`DriveGroup.exchange`): read every frame that arrived
  (the feedback to the previous SYNC), then send every drive's RPDO and one SYNC.

Faults latch (EMCY, a drive in FAULT, lost heartbeat or feedback, a rebooted drive,
error frames, bus-off, a broken interface): every drive is then commanded zero torque
with its power stage disabled until :meth:`DriveGroup.recover` is called.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

from drivers.faults import LatchedFaults
from drivers.elmo import codec as c
from drivers.elmo.sdo import SdoClient, SdoError
from drivers.elmo.transport import CanTransport
from onboard.contracts.params import HardwareParams

log = logging.getLogger("archer.drivers.elmo")

TWO_PI = 2.0 * math.pi
PROFILE_402 = 0x0192  # low 16 bits of the device type of a CiA 402 drive
MAX_PERMILLE = 0x7FFF
BOOTUP_TIMEOUT_S = 1.0  # after NMT reset communication
ABORT_CONNECTION_FAULT = 1  # 0x6007: fault reaction on lost heartbeat
INTERPOLATION_EXPONENT_MS = -3  # 0x60C2 sub 2: period value in milliseconds


class DriveError(Exception):
    """A drive could not be configured or enabled."""


@dataclass(frozen=True)
class JointDrive:
    """How one joint is wired to its drive."""

    node_id: int
    torque_constant: float  # [N m/A] at the motor shaft
    current_max: float  # [A] drive clamp
    gear_ratio: float  # motor turns per joint turn
    sign: int  # +1 or -1: motor direction vs joint direction


def joint_drives(params: HardwareParams, gear_ratios: Sequence[float]) -> list[JointDrive]:
    """One :class:`JointDrive` per node id; ``gear_ratios`` from the MJCF model (joint order)."""
    n = len(params.node_ids)
    for name in ("torque_constant", "current_max", "joint_sign"):
        if len(getattr(params, name)) != n:
            raise ValueError(f"hardware.{name} needs {n} values, one per node id")
    if len(gear_ratios) != n:
        raise ValueError(f"{n} gear ratios needed, got {len(gear_ratios)}")
    return [
        JointDrive(params.node_ids[i], params.torque_constant[i], params.current_max[i], float(gear_ratios[i]), params.joint_sign[i])
        for i in range(n)
    ]


@dataclass
class Feedback:
    """Last values from one drive, in joint units."""

    statusword: int = 0
    state: c.DriveState | None = None
    torque: float = 0.0  # [N m] at the joint
    velocity: float = 0.0  # [rad/s] at the joint
    position: float = 0.0  # [rad] at the joint
    sync: int = -1  # the SYNC the last TPDO1 answered
    nmt: c.NmtState | None = None  # from the last heartbeat
    last_heartbeat_s: float = -1.0
    last_emcy: c.Emergency | None = None


class ElmoDrive:
    """One drive: configuration, unit conversion, command frames, feedback parsing."""

    def __init__(self, joint: JointDrive) -> None:
        self.joint = joint
        self.node_id = c.check_node_id(joint.node_id)
        self.name = ""
        self.rated_torque_nm = 0.0  # 0x6076, read at configure
        self.rated_current_a = 0.0  # 0x6075
        self.counts_per_rev = 0.0  # 0x608F increments per motor revolution
        self.limit_permille = 0  # command clamp (from the current clamp)
        self.feedback = Feedback()
        self._tpdo1_id = c.TPDO_BASE[0] + self.node_id
        self._tpdo2_id = c.TPDO_BASE[1] + self.node_id

    # --- configuration (SDO, before the cyclic exchange) ----------------------------------

    def configure(
        self,
        sdo: SdoClient,
        host_node_id: int,
        heartbeat_timeout_ms: int,
        producer_ms: int,
        position_every: int,
        cycle_us: int,
    ) -> None:
        """Check the profile, read ratings, set the clamp, map the PDOs, select CST mode."""
        device_type = sdo.read_u32(c.DEVICE_TYPE)
        if device_type & 0xFFFF != PROFILE_402:
            raise DriveError(f"node {self.node_id}: device type 0x{device_type:08X} is not a CiA 402 drive")
        self.name = sdo.read_string(c.DEVICE_NAME)
        if not sdo.read_u32(c.SUPPORTED_MODES) & c.SUPPORTED_CST_BIT:
            raise DriveError(f"node {self.node_id}: cyclic synchronous torque mode not supported")
        self.rated_torque_nm = sdo.read_u32(c.RATED_TORQUE) / 1000.0
        self.rated_current_a = sdo.read_u32(c.RATED_CURRENT) / 1000.0
        increments = sdo.read_u32(c.ENCODER_RESOLUTION, 1)
        revolutions = sdo.read_u32(c.ENCODER_RESOLUTION, 2)
        if self.rated_torque_nm <= 0 or self.rated_current_a <= 0 or increments == 0 or revolutions == 0:
            raise DriveError(f"node {self.node_id}: drive reports zero rating or encoder resolution")
        self.counts_per_rev = increments / revolutions
        current_permille = min(MAX_PERMILLE, round(self.joint.current_max / self.rated_current_a * c.PERMILLE))
        torque_at_clamp = self.joint.current_max * self.joint.torque_constant
        self.limit_permille = min(current_permille, round(torque_at_clamp / self.rated_torque_nm * c.PERMILLE))
        sdo.write(c.MAX_CURRENT, 0, "<H", current_permille)
        sdo.write(c.MAX_TORQUE, 0, "<H", self.limit_permille)
        self._map_pdo(sdo, c.RPDO_COMM, c.RPDO_MAP, c.RPDO_BASE[0], c.RPDO1_MAPPING, c.TRANSMISSION_SYNC)
        self._map_pdo(sdo, c.TPDO_COMM, c.TPDO_MAP, c.TPDO_BASE[0], c.TPDO1_MAPPING, c.TRANSMISSION_SYNC)
        self._map_pdo(sdo, c.TPDO_COMM + 1, c.TPDO_MAP + 1, c.TPDO_BASE[1], c.TPDO2_MAPPING, position_every)
        for n in (1, 2, 3):
            self._disable_pdo(sdo, c.RPDO_COMM + n, c.RPDO_BASE[n])
        for n in (2, 3):
            self._disable_pdo(sdo, c.TPDO_COMM + n, c.TPDO_BASE[n])
        sdo.write(c.TARGET_TORQUE, 0, "<h", 0)
        sdo.write(c.MODES_OF_OPERATION, 0, "<b", c.MODE_CST)
        if sdo.read_i8(c.MODES_DISPLAY) != c.MODE_CST:
            raise DriveError(f"node {self.node_id}: mode display does not show cyclic synchronous torque")
        sdo.write(c.INTERPOLATION_PERIOD, 1, "<B", max(1, cycle_us // 1000))
        sdo.write(c.INTERPOLATION_PERIOD, 2, "<b", INTERPOLATION_EXPONENT_MS)
        sdo.write(c.ABORT_CONNECTION_OPTION, 0, "<h", ABORT_CONNECTION_FAULT)
        sdo.write(c.PRODUCER_HEARTBEAT, 0, "<H", producer_ms)
        sdo.write(c.CONSUMER_HEARTBEAT, 1, "<I", (host_node_id << 16) | heartbeat_timeout_ms)

    def _disable_pdo(self, sdo: SdoClient, comm: int, base: int) -> None:
        sdo.write(comm, 1, "<I", c.PDO_COB_INVALID | (base + self.node_id))

    def _map_pdo(self, sdo: SdoClient, comm: int, mapping: int, base: int, entries: tuple[int, ...], transmission: int) -> None:
        """CiA 301 procedure: disable, clear, write entries, set count, enable."""
        cob_id = base + self.node_id
        sdo.write(comm, 1, "<I", c.PDO_COB_INVALID | cob_id)
        sdo.write(mapping, 0, "<B", 0)
        for i, entry in enumerate(entries, start=1):
            sdo.write(mapping, i, "<I", entry)
        sdo.write(mapping, 0, "<B", len(entries))
        sdo.write(comm, 2, "<B", transmission)
        sdo.write(comm, 1, "<I", cob_id)

    # --- units ---------------------------------------------------------------------------

    def torque_to_permille(self, joint_torque: float) -> int:
        """Joint torque [N m] -> target torque [per mille of rated], clamped to the drive limit."""
        if not math.isfinite(joint_torque) or self.rated_torque_nm <= 0:
            return 0
        motor = joint_torque * self.joint.sign / self.joint.gear_ratio
        permille = round(motor / self.rated_torque_nm * c.PERMILLE)
        return max(-self.limit_permille, min(self.limit_permille, permille))

    @property
    def torque_limit(self) -> float:
        """Largest joint torque [N m] the drive applies (its current clamp)."""
        return self.limit_permille / c.PERMILLE * self.rated_torque_nm * self.joint.gear_ratio

    # --- cyclic ----------------------------------------------------------------------------

    def make_command(self, joint_torque: float, target: c.DriveState, fault_reset: bool = False) -> c.Frame:
        """RPDO1 moving the drive one step towards ``target``, torque only once enabled."""
        state = self.feedback.state
        if state == c.DriveState.FAULT:
            controlword = c.Controlword.FAULT_RESET if fault_reset else c.Controlword.DISABLE_VOLTAGE
        elif state is None:
            controlword = c.Controlword.DISABLE_VOLTAGE
        else:
            step = c.next_command(state, target)
            if step is not None:
                controlword = step
            elif target == c.DriveState.OPERATION_ENABLED:
                controlword = c.Controlword.ENABLE_OPERATION
            elif target == c.DriveState.READY_TO_SWITCH_ON:
                controlword = c.Controlword.SHUTDOWN
            elif target == c.DriveState.QUICK_STOP_ACTIVE:
                controlword = c.Controlword.QUICK_STOP
            else:
                controlword = c.Controlword.DISABLE_VOLTAGE
        enabled = state == c.DriveState.OPERATION_ENABLED and target == c.DriveState.OPERATION_ENABLED
        permille = self.torque_to_permille(joint_torque) if enabled else 0
        return c.make_rpdo1(self.node_id, int(controlword), permille)

    def on_tpdo1(self, data: bytes, sync: int) -> None:
        statusword, torque_pm, velocity = c.parse_tpdo1(data)
        fb = self.feedback
        fb.statusword = statusword
        fb.state = c.state_of(statusword)
        j = self.joint
        fb.torque = torque_pm / c.PERMILLE * self.rated_torque_nm * j.gear_ratio * j.sign
        fb.velocity = velocity * TWO_PI / self.counts_per_rev / j.gear_ratio * j.sign
        fb.sync = sync

    def on_tpdo2(self, data: bytes) -> None:
        j = self.joint
        self.feedback.position = c.parse_tpdo2(data) * TWO_PI / self.counts_per_rev / j.gear_ratio * j.sign


@dataclass
class GroupStats:
    ticks: int = 0
    feedback_received: int = 0  # TPDO1 frames that arrived, in time or not
    feedback_ok: int = 0  # TPDO1 in time for the next tick
    feedback_missed: int = 0  # a drive's TPDO1 absent at the next tick (late or lost)
    feedback_late: int = 0  # a TPDO1 answering an older SYNC
    malformed: int = 0  # frames of a wrong length or content
    emcy: int = 0
    heartbeats: int = 0
    faults_latched: int = 0
    recoveries: int = 0
    unexpected: int = 0  # frames nobody expects in the cyclic phase
    per_node_missed: dict[int, int] = field(default_factory=dict)


class DriveGroup(LatchedFaults):
    """Every drive on one bus, exchanged as one batch per tick."""

    device_name = "drive"
    fault_log = log

    def __init__(
        self,
        transport: CanTransport,
        drives: Sequence[ElmoDrive],
        params: HardwareParams,
        heartbeat_timeout_s: float,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if not drives:
            raise ValueError("a drive group needs at least one drive")
        self.transport = transport
        self.drives = list(drives)
        self.params = params
        self.heartbeat_timeout_s = heartbeat_timeout_s
        self.clock = clock
        self._by_id = {d.node_id: d for d in self.drives}
        if len(self._by_id) != len(self.drives):
            raise ValueError("duplicate node id")
        if params.host_node_id in self._by_id:
            raise ValueError("the host node id collides with a drive")
        self.period_s = 1.0 / params.rate_hz
        self.sync_count = 0
        self.faults: list[str] = []
        self.stats = GroupStats(per_node_missed={d.node_id: 0 for d in self.drives})
        self._next_heartbeat_s = 0.0
        self._consecutive_missed = {d.node_id: 0 for d in self.drives}
        self._reset_pending: set[int] = set()
        self._cyclic = False
        self._host_heartbeat = c.make_heartbeat(params.host_node_id, c.NmtState.OPERATIONAL)

    # --- faults ---------------------------------------------------------------------------

    # --- start-up ---------------------------------------------------------------------------

    def _sdo(self, drive: ElmoDrive) -> SdoClient:
        return SdoClient(self.transport, drive.node_id, self.params.sdo_timeout_s, on_other=self._dispatch, idle=self._heartbeat_if_due)

    def _heartbeat_if_due(self) -> None:
        now = self.clock()
        if now >= self._next_heartbeat_s:
            self.transport.send(self._host_heartbeat)
            self._next_heartbeat_s = now + self.params.host_heartbeat_period_s

    def start(self, reset_communication: bool = True) -> None:
        """Reset communication, wait for every boot-up, configure every drive, go operational.

        ``reset_communication=False`` skips the reset and the wait, for slaves already in
        PRE-OPERATIONAL that do not announce a boot-up on reset. Blocking (SDO); raises
        :class:`DriveError` or :class:`SdoError` on failure.
        """
        self._cyclic = False
        for d in self.drives:
            d.feedback = Feedback()
        if reset_communication:
            self._reset_communication()
        timeout_ms = max(1, round(self.heartbeat_timeout_s * 1000))
        producer_ms = max(1, round(self.params.drive_heartbeat_period_s * 1000))
        cycle_us = round(self.period_s * 1e6)
        for d in self.drives:
            d.configure(self._sdo(d), self.params.host_node_id, timeout_ms, producer_ms, self.params.position_every, cycle_us)
        self._heartbeat_if_due()  # the drives' consumers start on this first heartbeat
        self.transport.send(c.make_nmt(c.NmtCommand.START))
        now = self.clock()
        for d in self.drives:
            d.feedback.last_heartbeat_s = now
            self._consecutive_missed[d.node_id] = 0
        self.sync_count = 0
        self._cyclic = True

    def _reset_communication(self) -> None:
        self.transport.send(c.make_nmt(c.NmtCommand.RESET_COMMUNICATION))
        booted: set[int] = set()
        deadline = self.clock() + BOOTUP_TIMEOUT_S
        while booted != set(self._by_id):
            remaining = deadline - self.clock()
            if remaining <= 0:
                missing = sorted(set(self._by_id) - booted)
                raise DriveError(f"no boot-up from node(s) {missing}")
            frame = self.transport.recv(min(remaining, 0.01))
            if frame is None:
                if self.transport.broken:
                    raise DriveError(self.transport.fault)
                continue
            base, node = c.split_id(frame.can_id)
            if base == c.HEARTBEAT_BASE and node in self._by_id and frame.data[:1] == b"\x00":
                booted.add(node)

    def recover(self) -> None:
        """Recovery on command: clear latched faults, restart and reconfigure, reset drive faults.

        The drives stay disabled; the next armed :meth:`exchange` enables them.
        """
        self.stats.recoveries += 1
        self.transport.clear_fault()
        self.faults.clear()
        try:
            self.start()
        except (DriveError, SdoError) as exc:
            self.latch(f"recovery failed: {exc}")
            return
        self._reset_pending = {d.node_id for d in self.drives}

    def enable(self, timeout_s: float | None = None) -> None:
        """Run zero-torque exchanges until every drive shows OPERATION ENABLED."""
        deadline = self.clock() + (timeout_s if timeout_s is not None else self.params.enable_timeout_s)
        zeros = [0.0] * len(self.drives)
        next_tick = self.clock()
        while True:
            self.exchange(zeros, armed=True)
            if self.faulted:
                raise DriveError("; ".join(self.faults))
            if all(d.feedback.state == c.DriveState.OPERATION_ENABLED for d in self.drives):
                return
            if self.clock() > deadline:
                states = {d.node_id: (d.feedback.state.name if d.feedback.state is not None else "unknown") for d in self.drives}
                raise DriveError(f"drives not enabled in time: {states}")
            next_tick += self.period_s
            time.sleep(max(0.0, next_tick - self.clock()))

    # --- receiving ----------------------------------------------------------------------------

    def _dispatch(self, frame: c.Frame) -> None:
        base, node = c.split_id(frame.can_id)
        drive = self._by_id.get(node)
        if drive is None:
            if frame.can_id not in (c.SYNC_ID, c.NMT_ID) and node != self.params.host_node_id:
                self.stats.unexpected += 1
            return
        try:
            if base == c.TPDO_BASE[0]:
                self.stats.feedback_received += 1
                if drive.feedback.sync == self.sync_count:
                    self.stats.feedback_late += 1  # a second answer: the first was late
                drive.on_tpdo1(frame.data, self.sync_count)
            elif base == c.TPDO_BASE[1]:
                drive.on_tpdo2(frame.data)
            elif base == c.HEARTBEAT_BASE:
                self._on_heartbeat(drive, c.parse_heartbeat(frame.data))
            elif base == c.EMCY_BASE:
                self._on_emcy(c.parse_emcy(node, frame.data))
            elif self._cyclic:
                self.stats.unexpected += 1
        except ValueError as exc:
            self.stats.malformed += 1
            log.warning("malformed frame", extra={"fields": {"can_id": frame.can_id, "error": str(exc)}})

    def _on_heartbeat(self, drive: ElmoDrive, state: c.NmtState) -> None:
        self.stats.heartbeats += 1
        fb = drive.feedback
        previous, fb.nmt = fb.nmt, state
        fb.last_heartbeat_s = self.clock()
        if not self._cyclic:
            return
        if state == c.NmtState.BOOTUP:
            self.latch(f"node {drive.node_id} rebooted")
        elif previous == c.NmtState.OPERATIONAL and state != c.NmtState.OPERATIONAL:
            # (a PRE-OPERATIONAL heartbeat sent before the START arrived is no transition)
            self.latch(f"node {drive.node_id} left OPERATIONAL ({state.name})")

    def _on_emcy(self, emcy: c.Emergency) -> None:
        self.stats.emcy += 1
        self._by_id[emcy.node_id].feedback.last_emcy = emcy
        if emcy.is_reset:
            log.info("EMCY reset", extra={"fields": {"node": emcy.node_id}})
            return
        self.latch(emcy.describe())

    def _check_liveness(self, now: float) -> None:
        limit_ticks = max(1, math.ceil(self.heartbeat_timeout_s / self.period_s))
        for d in self.drives:
            fb = d.feedback
            if fb.last_heartbeat_s >= 0 and now - fb.last_heartbeat_s > self.heartbeat_timeout_s:
                self.latch(f"node {d.node_id} heartbeat lost")
            if self._consecutive_missed[d.node_id] >= limit_ticks:
                self.latch(f"node {d.node_id} feedback lost")
            if fb.state == c.DriveState.FAULT and d.node_id not in self._reset_pending:
                self.latch(f"node {d.node_id} in FAULT")

    # --- the cyclic exchange ----------------------------------------------------------------------

    def exchange(self, torques: Sequence[float], armed: bool, quick_stop: bool = False) -> None:
        """One tick: read what arrived, then send every drive's command and one SYNC.

        ``torques`` are joint torques [N m] in drive order; they are applied only while
        ``armed``, no fault is latched and the drive shows OPERATION ENABLED.
        ``quick_stop`` sends the CiA 402 quick stop (zero torque, QUICK STOP ACTIVE).
        """
        now = self.clock()
        for frame in self.transport.poll():
            self._dispatch(frame)
        stats = self.stats
        if self.sync_count > 0:
            for d in self.drives:
                if d.feedback.sync == self.sync_count:
                    stats.feedback_ok += 1
                    self._consecutive_missed[d.node_id] = 0
                else:
                    stats.feedback_missed += 1
                    stats.per_node_missed[d.node_id] += 1
                    self._consecutive_missed[d.node_id] += 1
        if self.transport.fault:
            self.latch(self.transport.fault)
        self._check_liveness(now)
        if self.faulted:
            target = c.DriveState.SWITCH_ON_DISABLED
        elif quick_stop:
            target = c.DriveState.QUICK_STOP_ACTIVE
        elif armed:
            target = c.DriveState.OPERATION_ENABLED
        else:
            target = c.DriveState.READY_TO_SWITCH_ON
        frames = []
        for d, torque in zip(self.drives, torques, strict=True):
            reset = d.node_id in self._reset_pending
            if reset and d.feedback.state not in (c.DriveState.FAULT, None):
                self._reset_pending.discard(d.node_id)
                reset = False
            frames.append(d.make_command(torque, target, fault_reset=reset))
        frames.append(c.make_sync())
        if now >= self._next_heartbeat_s:
            frames.append(self._host_heartbeat)
            self._next_heartbeat_s = now + self.params.host_heartbeat_period_s
        self.transport.send_batch(frames)
        self.sync_count += 1
        stats.ticks += 1

    def stop(self) -> None:
        """Zero torque, power stages off, drives back to PRE-OPERATIONAL (best effort)."""
        frames = [c.make_rpdo1(d.node_id, int(c.Controlword.DISABLE_VOLTAGE), 0) for d in self.drives]
        frames.append(c.make_sync())
        frames.append(c.make_nmt(c.NmtCommand.ENTER_PRE_OPERATIONAL))
        self.transport.send_batch(frames)
        self._cyclic = False

    def summary(self) -> dict[str, float]:
        s = self.stats
        expected = s.feedback_ok + s.feedback_missed
        return {
            "ticks": s.ticks,
            "feedback_received": s.feedback_received,
            "feedback_ok": s.feedback_ok,
            "feedback_missed": s.feedback_missed,
            "feedback_late": s.feedback_late,
            "missed_fraction": (s.feedback_missed / expected) if expected else 0.0,
            "malformed": s.malformed,
            "emcy": s.emcy,
            "faults_latched": s.faults_latched,
            "recoveries": s.recoveries,
            "unexpected": s.unexpected,
            "tx_frames": self.transport.tx_frames,
            "rx_frames": self.transport.rx_frames,
            "tx_errors": self.transport.tx_errors,
            "error_frames": self.transport.error_frames,
            "bus_off": self.transport.bus_off,
        }
