"""Foot: the hop-height regulator and the cable spool controller.

The foot spring is compressed by a cable wound on a spool (the foot motor after its
gearbox). A cable only pulls, so energy enters the hop one way: in flight the spool
winds the spring to a preload ``d`` [m]; at touchdown the spool unwinds past the
fully extended foot so the cable stays slack and the spring's stored ``k d^2 / 2`` [J] is released
into the stance (the foot compresses further on its own meanwhile, so there is
time to unwind). At lift-off the spring is fully extended again.

Hop height: with ``E = M g h`` the hop energy (``h``: CoM rise from touchdown to
apex [m], measured in flight from the ballistic prediction ``z + vz^2 / 2g``), the
next hop has ``E' = E - L + k d^2 / 2`` for the per-hop loss ``L`` [J] (the foot's
impacts, the extension stop). The regulator picks, during each flight,

    k d^2 / 2 = L_hat + gain * M g (h_ref - h)

and after each hop updates the loss estimate from what actually happened
(``L_obs = M g (h_prev - h) + k d_released^2 / 2``). ``L_hat`` starts at the
reduced model's prediction. The released preload is the spring compression
measured at touchdown, not the command.

Spool: position control of the spool angle [rad] (``JointSensors.foot_motor_pos``)
with the spring force as feed-forward while the cable holds it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from onboard.contracts.params import ControlParams


@dataclass(frozen=True)
class FootPhysics:
    """What the regulator needs from the robot model (read from the MJCF)."""

    total_mass: float  # [kg]
    gravity: float  # [m/s^2]
    spring_k: float  # [N/m]
    spool_radius: float  # cable length per spool angle [m/rad]
    travel: float  # spring travel [m]


class HopRegulator:
    def __init__(self, params: ControlParams, phys: FootPhysics, loss_nominal: float) -> None:
        """``loss_nominal``: the per-hop energy loss [J] the reduced model predicts."""
        if phys.spool_radius <= 0 or phys.spring_k <= 0:
            raise ValueError("spool radius and spring stiffness must be positive")
        self.phys = phys
        self.loss = max(0.0, loss_nominal)  # [J] current estimate
        self._mg = phys.total_mass * phys.gravity
        self.retune(params)
        self.preload_cmd = self._preload_for(params.hop_height)  # [m]
        self._released = math.nan  # spring compression at the last touchdown [m]
        self._h_prev = math.nan  # hop height of the flight before the last stance [m]
        self._h_now = math.nan  # hop height of the current flight [m]

    def retune(self, params: ControlParams) -> None:
        """New gains; the learnt loss and the current hop carry on."""
        self.p = params
        self.hop_height = params.hop_height  # [m] the apex rise aimed at (raised for a flip's flight)
        self._dmax = min(params.preload_max, self.phys.travel)

    def _preload_for(self, h: float) -> float:
        energy = self.loss + self.p.hop_gain * self._mg * (self.hop_height - h)
        d = math.sqrt(max(0.0, 2.0 * energy / self.phys.spring_k))
        return min(d, self._dmax)

    # --- events ----------------------------------------------------------------

    def in_flight(self, hop_height: float) -> None:
        """Every flight tick: ``hop_height`` [m] = predicted apex minus touchdown height."""
        if math.isfinite(hop_height):
            self._h_now = hop_height
            self.preload_cmd = self._preload_for(hop_height)

    def on_touchdown(self, compression: float) -> None:
        """At touchdown: the compression [m] the cable was holding (the release)."""
        self._released = max(0.0, compression)
        self._h_prev = self._h_now
        self._h_now = math.nan

    def on_apex(self, hop_height: float) -> None:
        """At the apex after a stance: learn the loss of the last hop."""
        if not (math.isfinite(self._h_prev) and math.isfinite(self._released) and math.isfinite(hop_height)):
            return
        observed = self._mg * (self._h_prev - hop_height) + 0.5 * self.phys.spring_k * self._released**2
        self.loss += self.p.loss_adapt * (max(0.0, observed) - self.loss)
        self._released = math.nan

    # --- spool torque -------------------------------------------------------------

    def spool_torque(self, stance: bool, foot_pos: float, spool_pos: float, spool_vel: float) -> float:
        """Spool torque [N m] (gearbox output); positive winds (compresses the spring)."""
        r = self.phys.spool_radius
        if stance:
            # unwind at once to ``release_slack`` of cable beyond the fully extended
            # foot: the reflected spool inertia is too large to follow the spring's
            # extension, so the cable must be out of the way before it starts
            target = -self.p.release_slack / r
            ff = 0.0
        else:
            target = self.preload_cmd / r
            # hold the spring force once the cable carries it
            ff = r * self.phys.spring_k * min(max(foot_pos, 0.0), self.preload_cmd)
        return ff + self.p.spool_kp * (target - spool_pos) - self.p.spool_kd * spool_vel
