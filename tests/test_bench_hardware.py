"""``archer bench hardware``: every figure from one window of counter snapshots, none whole-run."""

from __future__ import annotations

import pytest

from services.bench.hardware import window_figures

NS = 1_000_000_000
BITRATE = 1_000_000


def snapshot(t_s: float, *, ticks: int, received: int, ok: int, missed: int, bits: float,
             syncs: int, rpdos: int, no_rpdo: int, joints: int, commands: int) -> dict:
    extra = {"hw.ticks": ticks, "hw.feedback_received": received, "hw.feedback_ok": ok, "hw.feedback_missed": missed,
             "hw.feedback_late": 0, "hw.bus_bits": bits, "hw.faults": 0, "loop.overruns": 0, "watchdog.trips": 0,
             # whole-run load since the bus opened, start-up included: the old figure
             "hw.bus_load": 0.5}
    drives = {str(i): {"syncs": syncs // 2, "rpdos": rpdos // 2, "sync_without_rpdo": no_rpdo // 2} for i in (1, 2)}
    return {"status": {"stamp_ns": int(t_s * NS), "extra": extra, "last_error": ""},
            "emulator": {"counters": {"drives": drives}, "monotonic_s": t_s + 0.001},
            "joints": joints, "commands": commands}


def test_figures_are_differences_over_the_window_not_whole_run_totals() -> None:
    # start-up before the window: 3000 ticks with 900 missed feedback checks and 400 SYNCs
    # without a command; in the 2 s window, 2000 ticks of 2 drives: 4 feedback and 2 commands late
    start = snapshot(10.0, ticks=3000, received=5100, ok=5100, missed=900, bits=1.0e6,
                     syncs=6000, rpdos=5600, no_rpdo=400, joints=2990, commands=2995)
    end = snapshot(12.0, ticks=5000, received=9098, ok=9096, missed=904, bits=1.0e6 + 1.6e6,
                   syncs=10000, rpdos=9598, no_rpdo=402, joints=4986, commands=4995)
    fig = window_figures(start, end, n_drives=2, bitrate=BITRATE)
    assert fig["duration_s"] == pytest.approx(2.0) and fig["emulator_window_s"] == pytest.approx(2.0)
    assert fig["ticks"] == 2000 and fig["tick_rate_hz"] == pytest.approx(1000.0)
    assert fig["feedback_frames_expected"] == 4000
    assert fig["feedback_frames_received"] == 3998  # counted where they arrive, not ticks x drives
    assert fig["feedback_in_time"] == 3996 and fig["feedback_late_or_lost"] == 4
    assert fig["command_frames_due"] == 4000 and fig["command_frames_received"] == 3998
    assert fig["command_late_or_lost"] == 2
    assert fig["late_or_lost_fraction"] == pytest.approx(6 / 8000)  # start-up's 1300 misses are not in it
    assert fig["torque_commands_published"] == 2000 and fig["joints_messages"] == 1996
    assert fig["bus_load_measured"] == pytest.approx(0.8)  # 1.6 Mbit in 2 s on 1 Mbit/s, not the whole-run 0.5
