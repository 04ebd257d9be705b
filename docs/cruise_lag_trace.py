"""Where the CoM lands against the reference (docs/model_error.md, the cruise lean): at each impact the
low level's error to the reference sample (what the tube measures), split along the reference's velocity
(negative: behind) and across it, with and without the hop map's cruise lean fed forward.
Usage: python docs/cruise_lag_trace.py SCENARIO SEED MODEL_ERROR CRUISE_FEEDFORWARD [perception]
"""
import math
import sys

import numpy as np

from onboard.contracts.params import ControlParams
from sim_twin import lockstep as ls

scen, seed, error, ff = sys.argv[1], int(sys.argv[2]), sys.argv[3], float(sys.argv[4])
perception = sys.argv[5] if len(sys.argv) > 5 else "truth"
runner = ls.LockstepRunner(ls.RunConfig(scenario=scen, seed=seed, estimator="kalman", model_error=error, perception=perception,
                                        control_params=ControlParams(cruise_feedforward=ff)))
plug = runner.controller
ctrl = plug.ctrl
inner = plug.step
errors, along, across = [], [], []
last = [0]


def step(now_ns, state, ref, joints=None, *rest):
    out = inner(now_ns, state, ref, joints, *rest)
    if ctrl.tube_monitor.impacts != last[0]:  # an impact this tick: the last flight's prediction, split
        last[0] = ctrl.tube_monitor.impacts
        _, xi, yi = ctrl.predicted_impact
        rx, ry, rvx, rvy = ctrl.reference_at_impact
        errors.append(ctrl.last_impact_error)
        speed = math.hypot(rvx, rvy)
        if speed > 0.1:  # a reference that moves: the lag has a direction
            ex, ey = xi - rx, yi - ry
            along.append((ex * rvx + ey * rvy) / speed)
            across.append(abs(-ex * rvy + ey * rvx) / speed)
    return out


plug.step = step
m = runner.run().metrics
print(f"impacts {len(errors)}: error p50 {np.percentile(errors, 50):.3f} p95 {np.percentile(errors, 95):.3f} m; "
      f"reference moving (> 0.1 m/s) at {len(along)}: along mean {np.mean(along):+.3f} m, across mean {np.mean(across):.3f} m")
print({k: m[k] for k in ("falls", "goal_reached", "final_goal_error_m", "max_wheel_speed_rad_s", "rms_tracking_error_m",
                         "contract_violations") if k in m})
