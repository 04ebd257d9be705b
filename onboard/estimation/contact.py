"""The foot's contact as the state estimator tracks it: the switch debounced, and the hybrid
model's events applied to the CoM filter (thesis 5.5, lines 2751-2755: projectile dynamics in
flight, the foot pinned in stance; the impact map of the hopping robot's hybrid model).

Part of :class:`~onboard.estimation.estimator.StateEstimator`, which feeds every contact
reading (the foot switch, or without a foot sensor the specific force with hysteresis in level)
in two steps around its CoM step, so that the reading at an IMU interval's end picks that
interval's dynamics: :meth:`FootContact.switch_reading` takes the raw switch (a lift-off adds
the stance velocity's slow errors to the CoM as uncertainty), then :meth:`FootContact.debounce`
applies the impact map at the switch's closure (:meth:`onboard.estimation.leg_model.LegModel.impact`),
takes it back when the switch reopens before the contact is confirmed (a bounce), and confirms
a change of contact after ``contact_on_samples`` / ``contact_off_samples`` consecutive readings.
"""

from __future__ import annotations

from onboard.contracts.params import EstimatorParams
from onboard.estimation.attitude_filter import AttitudeFilter
from onboard.estimation.com_filter import ComFilter
from onboard.estimation.input_gate import InputGate
from onboard.estimation.leg_model import LegModel, Rot
from onboard.geometry.quaternion import Vec3


class FootContact:
    """Raw switch, debounced contact and the impact not yet confirmed."""

    def __init__(self, p: EstimatorParams, leg: LegModel, com: ComFilter, gate: InputGate) -> None:
        self._leg = leg
        self._com = com
        self._gate = gate
        self._on_samples = p.contact_on_samples
        self._off_samples = p.contact_off_samples
        self._impact_var = p.impact_vel_std_m_s ** 2
        self._liftoff_var = p.liftoff_vel_std_m_s ** 2
        self.contact = False  # debounced
        self._run = 0  # consecutive readings that disagree with it
        self.switch = False  # the raw contact reading
        self.switch_on_ns = 0  # when the switch last closed
        self._impact: Vec3 | None = None  # applied, not yet confirmed
        self._free_foot = (0.0, 0.0)  # foot compression and rate at the last no-contact reading

    def switch_reading(self, reading: bool, t: int, s: float, sd: float, att_ready: bool) -> bool:
        """The raw switch at ``t`` with the foot at compression ``s`` [m] and rate ``sd`` [m/s];
        whether it closed."""
        closed = reading and not self.switch
        if not reading:
            self._free_foot = (s, sd)
            if self.switch and att_ready:
                # lift-off: the stance velocity carries the leg kinematics' slow errors
                # (the ground gives as the load goes) into the flight
                self._com.add_impulse(0.0, 0.0, 0.0, self._liftoff_var, t)
        elif closed:
            self.switch_on_ns = t
        self.switch = reading
        return closed

    def debounce(self, reading: bool, closed: bool, rot: Rot, att: AttitudeFilter) -> bool:
        """After the CoM step of the same reading: the impact map, a bounce taken back, the
        debounced contact; whether a touchdown was confirmed now."""
        if closed and not self.contact and att.initialized:
            # the impact map applies at once, taken back if the debounce refuses the contact
            dv = self._leg.impact(rot, att.omega, self._free_foot, self._com.velocity)
            self._com.add_impulse(dv[0], dv[1], dv[2], self._impact_var, self.switch_on_ns)
            self._impact = dv
        if reading == self.contact:
            self._run = 0
            if self._impact is not None:  # the switch reopened before the contact was confirmed
                dvx, dvy, dvz = self._impact
                self._com.add_impulse(-dvx, -dvy, -dvz, 0.0, self.switch_on_ns)
                self._impact = None
                self._gate.count("contact_bounces")
            return False
        self._run += 1
        needed = self._off_samples if self.contact else self._on_samples
        if self._run < needed:
            return False
        self._run = 0
        self.contact = reading
        if self.contact and self._impact is not None:
            self._impact = None
            self._gate.count("touchdowns")
        return self.contact
