"""Lockstep trace at each touchdown (docs/model_error.md, the wheels' momentum): speed, the wheels' speeds,
the angular impulse the wheels were commanded over the flight before and the stance after, and the
momentum governor's cap.
Usage: python docs/momentum_trace.py SCENARIO SEED MODEL_ERROR [WHEEL_SHARE_LO]   (0: the governor off)
"""
import math
import sys

import numpy as np

from onboard.contracts.params import ControlParams
from sim_twin import lockstep as ls

scen, seed, error = sys.argv[1], int(sys.argv[2]), sys.argv[3]
params = ControlParams() if len(sys.argv) < 5 else ControlParams(momentum_wheel_share_lo=float(sys.argv[4]))
runner = ls.LockstepRunner(ls.RunConfig(scenario=scen, seed=seed, estimator="kalman", model_error=error, control_params=params))
plug = runner.controller
ctrl = plug.ctrl
inner = plug.step
phase = ["flight"]
impulse = {"flight": np.zeros(3), "stance": np.zeros(3)}
dt = 1.0 / ctrl.p.rate_hz
print("t [s]  speed [m/s]  wheels at touchdown [rad/s]  flight impulse  stance impulse [N m s]  cap [m/s]")


def step(now_ns, state, ref, joints=None, *rest):
    out = inner(now_ns, state, ref, joints, *rest)
    now = "flight" if ctrl.phase.phase == "flight" else "stance"
    impulse[now] += np.array(out.wheel_torque) * dt
    if now != phase[0] and now == "stance":  # a touchdown: the flight before it, the stance before that
        cap = ctrl.momentum.cap
        print(f"{now_ns / 1e9:6.3f} {math.hypot(*state.velocity[:2]):5.2f}  {np.round(state.wheel_vel, 1)}  "
              f"{np.round(impulse['flight'], 3)}  {np.round(impulse['stance'], 3)}  {'-' if cap == math.inf else round(cap, 3)}")
        impulse["flight"][:] = 0.0
        impulse["stance"][:] = 0.0
    phase[0] = now
    return out


plug.step = step
m = runner.run().metrics
print({k: m[k] for k in ("falls", "goal_reached", "final_goal_error_m", "max_wheel_speed_rad_s", "rms_tracking_error_m")})
