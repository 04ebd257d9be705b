"""Identification (offline/identification.py, archer identify): the fits recover known parameters
from synthetic data within their stated uncertainty; the command, end to end on a lockstep recording
of the identification routine on a twin with a known model error, recovers it and writes a file the
stack and the twin both load; a recording it cannot use gets a clear error."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from offline import identification as idf
from onboard.contracts import messages as m
from robot_description import identified as ident
from robot_description import params as rd
from services.cli.main import main
from sim_twin import model_error as me
from sim_twin.record import write_mcap

NO_PRIORS = idf.IdentifyOptions(wheel_inertia_sigma=0.0, imu_mount_sigma=0.0, com_model_sigma=0.0, settle_s=0.5)


def _synthetic(k: tuple[float, ...], b: tuple[float, ...], c: tuple[float, ...], d: tuple[float, float], seed: int,
               duration: float = 20.0) -> idf.Series:
    """Wheels integrated at 1 kHz under known torques (speed noise 0.2 rad/s, as the drives'), and
    touchdowns whose foot lands under the CoM offset by ``d`` up to a neutral-point term and 0.5 mm of scatter."""
    robot = rd.robot_params()
    rng = np.random.default_rng(seed)
    dt, j = 1e-3, robot.wheel_spin_inertia
    t = np.arange(int(duration / dt)) * dt
    tau = np.stack([0.15 * np.sin(2 * np.pi * f1 * t) + 0.1 * np.sin(2 * np.pi * f2 * t) + 0.05 * np.sin(2 * np.pi * 0.2 * t + i)
                    for i, (f1, f2) in enumerate(((5.3, 11.7), (6.1, 13.3), (7.9, 15.1)))], axis=1)
    w = np.zeros((len(t), 3))
    theta = np.zeros((len(t), 3))
    for n in range(1, len(t)):  # the torque of sample n-1 acts over [t_{n-1}, t_n)
        acc = (np.array(k) * tau[n - 1] - np.array(b) * w[n - 1] - np.array(c) * np.sign(w[n - 1])) / j
        w[n] = w[n - 1] + acc * dt
        theta[n] = theta[n - 1] + w[n - 1] * dt + 0.5 * acc * dt * dt
    # touchdowns every 0.35 s: a tilt that puts the true CoM over the foot, velocity v, a v = 0.05 v
    lever = robot.leg_length - robot.foot_radius
    c_true = np.array(robot.com_offset_body) + np.array([d[0], d[1], lever])
    t_td = np.arange(0.5, duration, 0.35)
    quats, vels = [], []
    for _ in t_td:
        v = np.array([*rng.normal(0.0, 0.1, 2), 0.0])
        target = 0.05 * v[:2] + rng.normal(0.0, 5e-4, 2)  # horizontal CoM - foot in world
        # small rotation about x, y placing R c_true's horizontal part at the target (first order)
        ry = (target[0] - c_true[0]) / c_true[2]
        rx = -(target[1] - c_true[1]) / c_true[2]
        half = 0.5 * math.hypot(rx, ry)
        s = math.sin(half) / (2 * half) if half > 0 else 0.5
        quats.append([math.cos(half), rx * s, ry * s, 0.0])
        vels.append(v)
    return idf.Series(
        t_joints=t, wheel_pos=theta, wheel_vel=w + rng.normal(0.0, 0.2, w.shape), t_imu=t, gyro=np.zeros((len(t), 3)),
        t_cmd=t, wheel_torque=tau, t_state=t_td.copy(), quat=np.array(quats), velocity=np.array(vels), t_touchdown=t_td,
        has_pose=True)


def test_fits_recover_known_parameters_within_their_uncertainty() -> None:
    k, b, c, d = (0.9, 1.0, 1.05), (1e-3, 2e-4, 5e-4), (2e-3, 1e-3, 3e-3), (0.006, -0.004)
    result = idf.identify(_synthetic(k, b, c, d, seed=1), rd.robot_params(), NO_PRIORS)
    for i in range(3):
        for name, truth in (("wheel_torque_constant", k[i] - 1.0), ("wheel_viscous", b[i]), ("wheel_coulomb", c[i])):
            e = result.params[name][i]
            assert abs(e.value - truth) <= 3.0 * e.sigma, (name, i, e, truth)
        assert result.sigma("wheel_torque_constant", i) < 0.01  # the dither makes k sharp
    assert abs(result.value("actuator_delay")) <= 3.0 * result.sigma("actuator_delay")  # none in the data
    for name, truth in (("com_x", d[0]), ("com_y", d[1])):
        assert abs(result.value(name) - truth) <= 3.0 * result.sigma(name) and result.sigma(name) < 5e-4, name


def test_stated_uncertainty_is_honest_over_many_synthetic_draws() -> None:
    """The 1-sigma of the fit covers the truth about 2 times in 3 (not 10 %, not 100 %)."""
    z = []
    for seed in range(12):
        r = idf.identify(_synthetic((1.0,) * 3, (3e-4,) * 3, (2e-3,) * 3, (0.003, 0.0), seed=seed, duration=8.0),
                         rd.robot_params(), NO_PRIORS)
        z += [(e.value - 3e-4) / e.sigma for e in r.params["wheel_viscous"]]
        z.append((r.value("com_x") - 0.003) / r.sigma("com_x"))
    share = float(np.mean(np.abs(z) <= 1.0))
    assert 0.45 <= share <= 0.9, (share, z)


def test_identify_end_to_end_on_a_lockstep_recording(tmp_path, capsys) -> None:
    """The routine on a twin with a known model error, recorded by archer sim, identified by
    archer identify; the file loads in robot_description (the stack) and as a --model-error profile."""
    config = tmp_path / "identify.toml"
    config.write_text("[control]\nidentify = true\n")
    rec, out = tmp_path / "routine.mcap", tmp_path / "robot.toml"
    assert main(["sim", "--scenario", "hop-in-place", "--duration", "14", "--config", str(config), "--quiet",
                 "--model-error", "wheel_viscous=0.001;com_x=0.01", "--record", str(rec)]) == 0
    capsys.readouterr()
    assert main(["identify", str(rec), "--out", str(out), "--json"]) == 0
    report = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    got = report["identified"]
    assert abs(got["com_x"]["value"][0] - 0.01) <= 2.0 * got["com_x"]["sigma"][0]
    assert abs(got["com_y"]["value"][0]) <= 2.0 * got["com_y"]["sigma"][0]
    for v, s in zip(got["wheel_viscous"]["value"], got["wheel_viscous"]["sigma"]):
        assert abs(v - 0.001) <= 2.0 * s and s < 3e-4
    for v, s in zip(got["wheel_torque_constant"]["value"], got["wheel_torque_constant"]["sigma"]):
        assert abs(v) <= 2.0 * s
    assert abs(got["spring_stiffness"]["value"][0]) <= 2.0 * got["spring_stiffness"]["sigma"][0] < 0.03  # none drawn
    params = ident.load(out)
    robot = ident.apply(rd.robot_params(), params)
    assert robot.com_offset_body[0] - rd.robot_params().com_offset_body[0] == pytest.approx(got["com_x"]["value"][0], abs=1e-6)
    draw = me.draw(me.load_profile(str(out)), 0)  # the twin built as identified
    assert draw.values["wheel_viscous"] == pytest.approx(tuple(got["wheel_viscous"]["value"]), rel=1e-4)
    assert draw.values["com_x"][0] == pytest.approx(got["com_x"]["value"][0], rel=1e-4)


def _joints(stamp: int, vel: float = 0.0) -> m.JointSensors:
    return m.JointSensors(stamp_ns=stamp, wheel_pos=[0.0] * 3, wheel_vel=[vel, 0.0, 0.0], wheel_torque=[0.0] * 3,
                          foot_pos=0.0, foot_vel=0.0, foot_contact=False)


def test_bad_recordings_get_a_clear_error(tmp_path, capsys) -> None:
    imu = m.ImuSample(stamp_ns=1, quat=[1.0, 0.0, 0.0, 0.0], gyro=[0.0] * 3, accel=[0.0, 0.0, 9.81])
    only_imu = tmp_path / "imu.mcap"
    write_mcap(only_imu, [("imu", i * 1_000_000, imu) for i in range(1, 50)])
    assert main(["identify", str(only_imu)]) == 1
    assert "lacks topics joints, torque_cmd, state" in capsys.readouterr().err
    empty = tmp_path / "empty.mcap"
    write_mcap(empty, [])
    assert main(["identify", str(empty)]) == 1
    assert "lacks topics" in capsys.readouterr().err
    nan = tmp_path / "nan.mcap"
    write_mcap(nan, [("joints", i * 1_000_000, _joints(i * 1_000_000, math.nan if i == 3 else 0.0)) for i in range(1, 10)])
    assert main(["identify", str(nan)]) == 1
    err = capsys.readouterr().err
    assert "invalid samples" in err and "1 on joints" in err
    assert main(["identify", str(tmp_path / "none")]) == 1
    assert "No such file" in capsys.readouterr().err
    # a non-finite value handed to the fit directly (not through the decoder) is refused too
    good = {"joints": [_joints(1), _joints(2, math.nan)], "imu": [imu], "torque_cmd": [
        m.TorqueCommand(stamp_ns=1, wheel_torque=[0.0] * 3, foot_torque=0.0, armed=True)], "state": [], "phase": []}
    with pytest.raises(idf.IdentificationError, match="lacks topics state"):
        idf.series_from_messages(good)
    good["state"] = [m.StateEstimate(stamp_ns=1, position=[0.0] * 3, velocity=[0.0] * 3, quat=[1.0, 0, 0, 0], omega=[0.0] * 3,
                                     wheel_vel=[0.0] * 3, foot_pos=0.0, foot_vel=0.0, contact=False, phase="flight",
                                     pos_vel_cov=[0.0] * 36, att_cov=[0.0] * 3)]
    with pytest.raises(idf.IdentificationError, match="non-finite wheel_vel"):
        idf.series_from_messages(good)
    # a recording too short to fit
    short = idf.series_from_messages({**good, "joints": [_joints(i * 1_000_000) for i in range(1, 200)]})
    with pytest.raises(idf.IdentificationError, match="usable windows"):
        idf.identify(short, rd.robot_params())


def test_routine_excitation_is_bounded_and_the_profile_reads_per_wheel_values(tmp_path) -> None:
    from onboard.low_level.tracking.excitation import heading_swing, wheel_dither

    t = np.linspace(0.0, 20.0, 20001)
    dither = np.array([wheel_dither(x, 0.2) for x in t])
    assert np.all(np.abs(dither) <= 0.2 + 1e-12) and np.all(np.abs(dither).max(axis=0) > 0.15)
    assert abs(heading_swing(1.25, 0.5, 5.0) - 0.5) < 1e-12 and heading_swing(3.0, 0.5, 0.0) == 0.0
    bad = tmp_path / "bad.toml"
    bad.write_text("[factors]\nwheel_viscous = [0.001, 0.002]\n")
    with pytest.raises(ValueError, match="a list of 3 numbers"):
        me.load_profile(str(bad))
    with pytest.raises(ValueError, match="no \\[identified\\] table"):
        ident.load(bad)
