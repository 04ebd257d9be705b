"""Lockstep trace at each touchdown (docs/model_error.md): the stack's estimate, the true CoM, the commanded and
achieved impact tilt, and the lean disturbance the balance observer sees, with the CoM D off the spine.
Usage: python docs/model_error_trace.py SCENARIO D BALANCE_GAIN [SEED]
"""
import sys
import numpy as np
from onboard.geometry import quaternion as qt
from sim_twin import lockstep as ls
from onboard.contracts.params import ControlParams
scen, off, gain = sys.argv[1], float(sys.argv[2]), float(sys.argv[3])
seed = int(sys.argv[4]) if len(sys.argv) > 4 else 0
cfg = ls.RunConfig(scenario=scen, seed=seed, estimator="kalman", model_error=f"com_x={off}",
                   control_params=ControlParams(balance_gain=gain))
r = ls.LockstepRunner(cfg)
plug = r.controller; ctrl = plug.ctrl
inner = plug.step
rows = []; prev = ["flight"]
foot = r.model.body("foot").id
def step(now_ns, state, ref, joints=None, *a):
    out = inner(now_ns, state, ref, joints, *a)
    ph = ctrl.phase.phase
    if ph != "flight" and prev[0] == "flight":
        d = r.data; com, _ = r.truth.com(d)
        w, x, y, z = d.qpos[3:7]
        lean = qt.body_z(state.quat)
        rows.append((now_ns / 1e9, state.position[0], com[0], ctrl.reference_at_impact[0], ctrl.eta[0], 2 * (x * z + w * y),
                     com[0] - d.xpos[foot][0], ctrl.balance.beta_x, state.velocity[0], state.velocity[1], lean[0], lean[1]))
    prev[0] = ph
    return out
plug.step = step
res = r.run()
a = np.array(rows)
last = a[a[:, 0] > a[-1, 0] - 5.0].mean(axis=0)
print(f"{scen} offset={off} gain={gain}: goal_err={res.metrics['final_goal_error_m']} falls={res.metrics['falls']} | last 5 s mean at touchdown: "
      f"est_x={last[1]:+.4f} true_x={last[2]:+.4f} ref_x={last[3]:+.4f} eta_cmd={last[4]:+.4f} tilt={last[5]:+.4f} com-foot={last[6]:+.4f} beta={last[7]:+.4f}")
# the observer's view of every pair of touchdowns but the first (the drop from standing): (v' - a v) / b - eta
bp = ctrl.balance
obs = (a[2:, 8:10] - bp.a_vel * a[1:-1, 8:10]) / bp.b_vel - a[1:-1, 10:12]
moving = np.hypot(a[1:-1, 8], a[1:-1, 9]) > 0.1
print(f"observed lean disturbance (x, y): mean {obs.mean(axis=0).round(4)} std {obs.std(axis=0).round(4)} over {len(obs)} pairs; "
      f"touchdowns faster than 0.1 m/s: {obs[moving].mean(axis=0).round(4) if moving.any() else '-'}; D / L = {off / bp.lever:.4f}")
