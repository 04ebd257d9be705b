"""Parameters of the platform under the algorithms: safety limits every command passes, messaging,
the hardware's drives and boards, motion capture, the recorder and the viewer.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Annotated, Literal

from msgspec import Meta



from onboard.contracts.params.base import (Cpu, FOOT_TORQUE_PEAK, LOOP_HZ_MAX, Name, NodeId, PER_NODE, Port, Request,
                                           RtPriority, WHEEL_NO_LOAD_SPEED, WHEEL_TORQUE_PEAK, _Section, above,
                                           within)


@dataclass(frozen=True)
class SafetyLimits(_Section, section="safety"):
    """Limits every torque command passes through before it can reach a motor."""

    wheel_torque_max: Annotated[float, above(0.0, WHEEL_TORQUE_PEAK)] = 1.5  # [N m] per wheel, KV115 on 50.8 V, thesis lines 170-190
    foot_torque_max: Annotated[float, above(0.0, FOOT_TORQUE_PEAK)] = 10.0  # [N m] foot cable motor after the 3:1 gearbox
    wheel_speed_max: Annotated[float, above(0.0, WHEEL_NO_LOAD_SPEED)] = 600.0  # [rad/s] beyond this the motor has no torque left
    tilt_max: Annotated[float, above(0.0, math.pi / 2)] = math.radians(45.0)  # [rad] body z from vertical: a fall
    command_stale_s: Annotated[float, above(0.0, 0.1)] = 0.010  # [s] hardware/twin zero torque when no newer command
    estimate_stale_s: Annotated[float, above(0.0, 0.1)] = 0.005  # [s] control disarms on an older estimate
    reference_stale_s: Annotated[float, above(0.0, 10.0)] = 0.5  # [s] control falls back to hopping in place
    heartbeat_timeout_s: Annotated[float, above(0.0, 1.0)] = 0.100  # [s] Teensy / drive heartbeat consumer bound


@dataclass(frozen=True)
class MessagingParams(_Section, section="messaging"):
    endpoint: Name = "tcp/127.0.0.1:7447"  # the well-known local router endpoint
    status_period_s: Annotated[float, above(0.0, 60.0)] = 0.5  # how often a service refreshes its rate figures
    # Batches per link queue for the real_time and interactive_high priorities. An express
    # message takes a batch of its own, so Zenoh's default of 2 (and 1 ms wait) drops 1 kHz
    # samples whenever a receiver is ~3 ms late; 16 rides out a 16 ms stall, costs memory
    # only while a receiver lags, and latest-value readers skip what queued.
    link_queue_batches: Annotated[int, within(1, 1024)] = 16


@dataclass(frozen=True)
class HardwareParams(_Section, section="hardware"):
    """The ``hardware`` service and its drivers (ELMO drives over CAN, Teensy over serial).

    Joint order everywhere: wheel 0, wheel 1, wheel 2, foot. Per-joint tuples are
    drive settings (motor torque constant, current clamp) of the real robot; the
    emulators use the same values. Gear ratios come from the MJCF model.
    """

    backend: Literal["can", "teensy", "archer-firmware"] = "can"  # "can": ELMO drives over CANopen; "teensy": framed serial; "archer-firmware": ARCHER's flywheel board over UDP ([archer_firmware])
    rate_hz: Annotated[float, within(1.0, LOOP_HZ_MAX)] = 1000.0  # exchange rate with the drives / the Teensy [Hz]
    rt_priority: RtPriority = 70  # SCHED_FIFO priority of the exchange thread, below control (0: leave the scheduler alone)
    cpu: Cpu = -1  # CPU the exchange thread is pinned to (-1: no pinning)
    # CAN (python-can arguments; the emulator prints them)
    can_interface: Name = "socketcand"
    can_channel: Name = "can0"
    can_host: str = "127.0.0.1"  # socketcand only
    can_port: Port = 29536  # socketcand only
    can_bitrate: Annotated[int, within(10_000, 1_000_000)] = 1_000_000  # [bit/s] classic CAN tops out at 1 Mbit/s
    node_ids: Annotated[tuple[NodeId, ...], PER_NODE] = (1, 2, 3, 4)  # CANopen node of each joint
    host_node_id: NodeId = 127  # the host's heartbeat identifier 0x700 + id
    host_heartbeat_period_s: Annotated[float, above(0.0, 1.0)] = 0.025  # drives fault after SafetyLimits.heartbeat_timeout_s
    drive_heartbeat_period_s: Annotated[float, above(0.0, 1.0)] = 0.050  # drive heartbeat producer time (0x1017)
    position_every: Annotated[int, within(1, 1000)] = 10  # position PDO on every n-th SYNC (bus budget)
    sdo_timeout_s: Annotated[float, above(0.0, 10.0)] = 0.5  # [s] per SDO response
    enable_timeout_s: Annotated[float, above(0.0, 60.0)] = 1.0  # [s] to reach OPERATION ENABLED
    torque_constant: Annotated[tuple[Annotated[float, above(0.0, 1.0)], ...], PER_NODE] = (0.083, 0.083, 0.083, 0.083)  # [N m/A] KV115 wheels
    current_max: Annotated[tuple[Annotated[float, above(0.0, 100.0)], ...], PER_NODE] = (12.0, 12.0, 12.0, 12.0)  # [A] drive current clamp
    joint_sign: Annotated[tuple[Literal[1, -1], ...], PER_NODE] = (1, 1, 1, 1)  # motor direction vs joint direction
    # Teensy
    serial_port: str = ""  # e.g. /dev/ttyACM0 or the pty the emulator prints
    teensy_mode: Literal["torque", "attitude"] = "torque"  # "torque" or "attitude" (the Teensy runs the PD)
    reconnect_min_s: Annotated[float, above(0.0, 10.0)] = 0.05  # [s] first retry after the port vanished
    reconnect_max_s: Annotated[float, above(0.0, 60.0)] = 1.0  # [s] backoff ceiling
    link_timeout_s: Annotated[float, above(0.0, 10.0)] = 0.1  # [s] no sensor frame for this long: link lost
    recover_request: Request = 0  # operator command: set a new value to clear latched faults and re-initialise

    def _relations(self) -> list[str]:
        if self.reconnect_min_s > self.reconnect_max_s:
            return [f"hardware.reconnect_min_s: above reconnect_max_s ({self.reconnect_min_s} > {self.reconnect_max_s})"]
        return []


@dataclass(frozen=True)
class ArcherFirmwareParams(_Section, section="archer_firmware"):
    """ARCHER's own flywheel-board firmware over UDP (``docs/archer_firmware_protocol.md``).

    Read by the computer-side driver (``drivers/archer_firmware``) and by its emulator,
    which also takes the firmware's configuration from here: the attitude PD gains, the
    current clamp and the foot board's hop cycle. Addresses default to loopback; the
    robot's (board 10.0.0.7, computer 10.0.0.6) belong in its deployment config only.
    """

    board_host: Name = "127.0.0.1"  # the flywheel Teensy
    board_port: Port = 4333  # the firmware's UDP port
    computer_host: Name = "127.0.0.1"  # the address the computer binds (the firmware answers there)
    computer_port: Port = 4333
    # computer side
    link_timeout_s: Annotated[float, above(0.0, 10.0)] = 0.100  # [s] no reply this long while commanding: fault (latched)
    reply_late_s: Annotated[float, above(0.0, 1.0)] = 0.002  # [s] a reply arriving later than this after its request is late
    reply_missing_s: Annotated[float, above(0.0, 10.0)] = 0.050  # [s] a request unanswered this long counts as missing
    # The board answers only what it receives and has no motors-off packet: while disarmed the computer
    # sends the reset command every tick (motors off, and the board answers with its state, which the
    # estimator needs to arm on). False: silence while disarmed (no state until armed; the watchdog stops the motors).
    poll_disarmed: bool = True
    # the firmware (what the emulator runs; the real board has them in its own configuration)
    rate_hz: Annotated[float, within(1.0, LOOP_HZ_MAX)] = 1000.0  # [Hz] the board's control loop
    watchdog_s: Annotated[float, above(0.0, 10.0)] = 0.100  # [s] no valid packet this long: motors off
    kp_tilt: Annotated[float, within(0.0, 500.0)] = 60.0  # [N m] per unit of quaternion error vector, roll and pitch
    kp_yaw: Annotated[float, within(0.0, 500.0)] = 4.0  # [N m] per unit of quaternion error vector, yaw
    kd_tilt: Annotated[float, within(0.0, 50.0)] = 3.0  # [N m s/rad] roll and pitch
    kd_yaw: Annotated[float, within(0.0, 50.0)] = 0.25  # [N m s/rad] yaw
    torque_constant: Annotated[float, above(0.0, 10.0)] = 0.083  # [N m/A] wheel motors
    current_max: Annotated[float, above(0.0, 100.0)] = 12.0  # [A] wheel current clamp
    # the foot board's hop cycle (spool position control, as the foot Teensy runs it)
    foot_preload_m: Annotated[float, within(0.0, 0.2)] = 0.03  # [m] spring compression wound in during flight, released at touchdown
    foot_spool_kp: Annotated[float, within(0.0, 1000.0)] = 10.0  # [N m/rad]
    foot_spool_kd: Annotated[float, within(0.0, 100.0)] = 0.2  # [N m s/rad]
    foot_release_slack_m: Annotated[float, within(0.0, 0.2)] = 0.015  # [m] at touchdown unwind this much cable past the extended foot
    # hop height from the contact switch: a fixed preload gains more per hop than the impact loses
    # (measured on the twin: apex 0.51 -> 0.86 m in 5 s, then the spring bottoms out; 0.015 m: the
    # hop dies), so the board scales the preload by the flight time it measured (apex rise g T^2 / 8)
    foot_hop_height_m: Annotated[float, within(0.0, 0.5)] = 0.12  # [m] apex rise the preload is regulated to (0: fixed preload)
    foot_hop_gain: Annotated[float, within(0.0, 1.0)] = 0.5  # fraction of the hop-height error corrected per hop
    foot_min_flight_s: Annotated[float, within(0.0, 1.0)] = 0.05  # [s] a shorter flight is the foot bouncing at touchdown, not a hop


# Sections owned by each layer follow; each is registered in SECTIONS below.


@dataclass(frozen=True)
class RecorderParams(_Section, section="recorder"):
    """The flight recorder (``recorder`` service): every topic to rotating MCAP files."""

    directory: str = ""  # "" = $STATE_DIRECTORY/recordings under systemd, else ./recordings
    chunk_s: Annotated[float, above(0.0, 86_400.0)] = 10.0  # finalize the file and start the next after this long [s]
    chunk_bytes: Annotated[int, within(1, 2**40)] = 64 * 1024 * 1024  # ... or once this many message bytes are written
    flush_s: Annotated[float, within(0.0, 3600.0)] = 1.0  # close an MCAP chunk this often, so a crash loses at most this [s]
    compression: Literal["zstd", "lz4", "none"] = "zstd"  # "zstd", "lz4" or "none"
    keep_bytes: Annotated[int, within(0, 2**50)] = 8 * 1024 * 1024 * 1024  # delete the oldest finished files beyond this
    status_period_s: Annotated[float, above(0.0, 3600.0)] = 5.0  # record every live service's status this often [s] (a query costs them CPU)
    scene: bool = True  # also write the Foxglove scene channels (services/scene.py, drawn as [view] says) beside the raw topics


@dataclass(frozen=True)
class ViewParams(_Section, section="view"):
    """The live viewer bridge (``view`` service): the stack's topics to a Foxglove WebSocket server."""

    host: Name = "127.0.0.1"  # bind address; the default serves this machine only (reach it over an SSH tunnel)
    port: Annotated[int, within(0, 65535)] = 8765  # Foxglove's default port; 0: any free port (logged)
    variant: Literal["indoor", "outdoor", "sim15nm"] = "indoor"  # robot model drawn (robot_description variant)
    max_rate_hz: Annotated[float, above(0.0, 1000.0)] = 30.0  # [Hz] at most this per channel: fast topics send their latest
    event_queue: Annotated[int, within(1, 100_000)] = 256  # slow and event topics: messages kept between two sends
    obstacle_height_m: Annotated[float, above(0.0, 10.0)] = 0.5  # [m] obstacles drawn as prisms this tall
    reference_samples: Annotated[int, within(2, 10_000)] = 200  # points drawn along the reference curve
    message_backlog: Annotated[int, within(1, 1_000_000)] = 256  # per client: the SDK drops the oldest beyond it
    lockstep_wait_s: Annotated[float, within(0.0, 3600.0)] = 60.0  # [s] `archer sim --view` in lockstep waits this long for a viewer


@dataclass(frozen=True)
class MocapParams(_Section, section="mocap"):
    """The ``mocap`` service: a motion capture system's pose through ``motioncapture``.

    ``stamp_ns`` of a published pose is the capture time on the stack's monotonic
    clock: the receive time minus ``latency_s`` (the motioncapture 1.1 bindings report
    no per-frame latency or timestamp, so the lab measures it once and sets it here).
    """

    system: Literal["optitrack", "vicon", "qualisys", "vrpn"] = "optitrack"  # motioncapture backend
    host: Name = "127.0.0.1"  # the mocap server (the lab's address belongs in the robot's config)
    port: Annotated[int, within(0, 65535)] = 0  # the server's command port (0: the system's default, e.g. NatNet 1510)
    rigid_body: Name = "archer"  # the robot's rigid body name in the mocap software
    rigid_body_id: Annotated[int, within(0, 65535)] = 1  # NatNet streaming id (the emulator's; the service matches by name)
    latency_s: Annotated[float, within(0.0, 1.0)] = 0.005  # [s] capture to receive: exposure, processing, network
    rate_hz: Annotated[float, within(1.0, 1000.0)] = 120.0  # [Hz] the system's frame rate (emulator's stream rate)
    quat_norm_tolerance: Annotated[float, above(0.0, 0.5)] = 1e-3  # |norm - 1| beyond which a pose is refused
    connect_timeout_s: Annotated[float, above(0.0, 60.0)] = 2.0  # [s] a NatNet server must answer NAT_CONNECT within this
    reconnect_s: Annotated[float, above(0.0, 60.0)] = 1.0  # [s] wait before connecting again after a failure


_Coeff = Annotated[float, within(-100.0, 100.0)]
_Metres = Annotated[float, within(-1000.0, 1000.0)]
_Byte = Annotated[int, within(0, 255)]


@dataclass(frozen=True)
class CameraOverheadParams(_Section, section="camera_overhead"):
    """The ``camera_overhead`` service (drivers.camera_overhead): obstacles from a camera looking down at the
    floor (thesis 7.2). Defaults: the twin's rendered camera (sim_twin.overhead_camera.default_camera and
    default_markers); the lab's config sets its ZED 2's intrinsics and its markers' surveyed poses."""

    source: Name = "0"  # cv2.VideoCapture source: a camera index ("0") or a video file's path
    crop_left: bool = False  # a ZED 2 in UVC mode sends both eyes side by side: keep the left one
    rate_hz: Annotated[float, above(0.0, 120.0)] = 4.0  # [Hz] frames processed and obstacles published (thesis: 4 Hz)
    fx: Annotated[float, above(0.0, 1e5)] = 560.0  # [px] focal lengths and principal point
    fy: Annotated[float, above(0.0, 1e5)] = 560.0
    cx: Annotated[float, within(0.0, 1e5)] = 480.0
    cy: Annotated[float, within(0.0, 1e5)] = 360.0
    dist: Annotated[tuple[_Coeff, ...], Meta(min_length=5, max_length=5)] = (-0.08, 0.02, 0.0, 0.0, 0.0)  # OpenCV k1, k2, p1, p2, k3
    # ArUco markers (DICT_4X4_50) on the floor, one entry each in every marker_* tuple: id, centre, yaw
    marker_ids: tuple[Annotated[int, within(0, 49)], ...] = (0, 1, 2, 3, 4, 5)
    marker_x: tuple[_Metres, ...] = (-0.4, 3.0, 6.4, -0.4, 3.0, 6.4)  # [m]
    marker_y: tuple[_Metres, ...] = (2.4, 2.6, 2.4, -2.4, -2.6, -2.4)  # [m]
    marker_yaw: tuple[Annotated[float, within(-7.0, 7.0)], ...] = (0.0, 0.3, 0.0, 1.2, 0.0, -0.5)  # [rad]
    marker_size: Annotated[float, above(0.0, 10.0)] = 0.4  # [m] side of every marker's black square
    min_markers: Annotated[int, within(2, 1000)] = 2  # markers a frame must show to calibrate the floor
    hsv_low: Annotated[tuple[_Byte, ...], Meta(min_length=3, max_length=3)] = (5, 120, 120)  # the obstacles' colour (OpenCV HSV: H 0-179)
    hsv_high: Annotated[tuple[_Byte, ...], Meta(min_length=3, max_length=3)] = (25, 255, 255)
    min_area_px: Annotated[int, within(1, 10_000_000)] = 40  # smaller blobs are noise
    obstacle_height_m: Annotated[float, within(0.0, 10.0)] = 1.0  # [m] the obstacles' height (their tops' plane: a tighter footprint)
    accel_sigma: Annotated[float, above(0.0, 100.0)] = 1.0  # [m/s^2] how hard an obstacle may be pushed (the tracks' process noise)
    measure_sigma: Annotated[float, above(0.0, 1.0)] = 0.02  # [m] centroid measurement noise
    gate_m: Annotated[float, above(0.0, 10.0)] = 0.6  # [m] a blob farther from a track's prediction is another obstacle
    max_missed: Annotated[int, within(0, 1000)] = 8  # frames a track may go unseen before it ends
    names_file: str = ""  # JSON from `archer obstacles init`: named obstacles seed the tracks

    def _relations(self) -> list[str]:
        n = len(self.marker_ids)
        if not len(self.marker_x) == len(self.marker_y) == len(self.marker_yaw) == n:
            return [f"camera_overhead: marker_ids, marker_x, marker_y and marker_yaw need one entry per marker ({n})"]
        if len(set(self.marker_ids)) != n:
            return ["camera_overhead.marker_ids: a marker id twice"]
        return []


@dataclass(frozen=True)
class CameraParams(_Section, section="camera"):
    """The ``camera`` service: the D435 through librealsense (``drivers/realsense``).

    Depth at ``width`` x ``height`` @ ``fps`` (one of the D435's modes), colour aligned to
    it, the SDK's decimation and spatial filters; one frame a hop, the one captured nearest
    the apex (``capture = "apex"``), or every frame (``"every"``: bench, recordings). A
    frame's ``stamp_ns`` is its sensor timestamp mapped onto the stack's clock.
    """

    source: Literal["device", "file"] = "device"  # a camera over USB, or a recording played back
    serial: str = ""  # the camera's serial number ("": the first D435 found)
    file: str = ""  # source = "file": a librealsense recording (.db3, as librealsense 2.59 records)
    file_real_time: bool = True  # play a recording at its own pace (False: every frame, as fast as read)
    width: Annotated[int, within(1, 4096)] = 848  # depth mode [px]
    height: Annotated[int, within(1, 4096)] = 480
    fps: Annotated[int, within(1, 300)] = 30  # [Hz]
    color: bool = True  # colour stream, aligned to depth, published on `color`
    color_width: Annotated[int, within(1, 4096)] = 848
    color_height: Annotated[int, within(1, 4096)] = 480
    color_fps: Annotated[int, within(1, 300)] = 30
    decimation: Annotated[int, within(1, 8)] = 2  # the SDK's decimation filter (1: off); 848x480 -> 424x240
    spatial: bool = True  # the SDK's spatial edge-preserving filter
    capture: Literal["apex", "every"] = "apex"
    apex_tolerance_s: Annotated[float, above(0.0, 1.0)] = 0.05  # [s] a frame further from the apex is not its frame
    min_latency_s: Annotated[float, within(0.0, 1.0)] = 0.010  # [s] exposure to host that no frame beats (clock map)
    clock_window: Annotated[int, within(1, 100_000)] = 300  # frames over which the clock offset is the smallest delay
    # [s] a camera's frame in global time (librealsense's, on the host's wall clock) keeps it as its capture time
    # however late it came, up to this old at receipt; an older one is dropped (counted `stale_frames`). A
    # recording's frames (source = "file") go through the offset
    global_time_max_age_s: Annotated[float, within(0.0, 60.0)] = 2.0
    state_max_age_s: Annotated[float, above(0.0, 10.0)] = 0.05  # [s] an estimate further from the frame cannot pose it
    robot_variant: Literal["indoor", "outdoor", "sim15nm"] = "outdoor"  # MJCF whose camera site is the extrinsic
    reopen_s: Annotated[float, above(0.0, 60.0)] = 1.0  # [s] wait before opening the camera again after a failure
