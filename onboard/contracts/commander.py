"""One commander for the motors: the rule every torque consumer applies.

A consumer of motor commands (the twin, the hardware service) takes them from one
instance of the control service only: the one whose liveliness token is declared,
identified by the instance id its status reports and every command carries
(``TorqueCommand.commander``). A command from any other instance is refused and
counted, whatever it says; while no commander is alive, every command is refused (a
publisher without a token is nobody's commander). A takeover therefore needs the
first commander's token to be gone: a crash, a stop, a lost link.

The instance id is in every command, so anyone on the bus can copy it. Commands from the live
commander must also form one stream: each sequence number after the last one obeyed. A command
whose number is not (a replay, a second publisher under the same id, interleaving with the real
one) is refused and counted as a second stream; a stream that went quiet for
``RESTART_GAP_NS`` may start again from a lower number (the control service restarts its loop
process under the same instance for new parameters). This stops a copier, not a forger who
also outruns the real stream: on the robot only the ``control`` user may put commands at all
(the router's access control, ``services/runtime/zenoh_configs.py``).

Pure bookkeeping: the service feeds it liveliness and status replies from Zenoh and
asks it about each command as it arrives.
"""

from __future__ import annotations

NO_LIVE_COMMANDER = "no_live_commander"
FOREIGN_COMMANDER = "foreign_commander"
UNKNOWN_COMMANDER = "unknown_commander"  # alive, but its instance id is not known yet
SECOND_STREAM = "commander_second_stream"  # the live commander's id, but a sequence number not after the last obeyed
RESTART_GAP_NS = 50_000_000  # [ns] a commander silent this long may begin a new stream (a restarted loop: seconds)


class CommanderLatch:
    """Which commander instance the motors obey, and what was refused."""

    def __init__(self) -> None:
        self.alive = False  # a commander's liveliness token is declared
        self.instance: str | None = None  # the live commander's instance id, once its status said
        self.refused: dict[str, int] = {NO_LIVE_COMMANDER: 0, FOREIGN_COMMANDER: 0, UNKNOWN_COMMANDER: 0, SECOND_STREAM: 0}
        self.latches = 0  # how many commander instances were obeyed in turn
        self._last_seq = -1  # of the last command obeyed (-1: none yet from this commander)
        self._last_ns = 0  # when it arrived

    def commander_appeared(self) -> None:
        self.alive = True

    def commander_gone(self) -> None:
        self.alive = False
        self.instance = None
        self._last_seq = -1

    def commander_identified(self, instance: str) -> bool:
        """The live commander's status named ``instance``; False when it is not the one
        already latched (two tokens at once: the first keeps the motors)."""
        if not self.alive or not instance:
            return False
        if self.instance is None:
            self.instance = instance
            self.latches += 1
            return True
        return self.instance == instance

    def refusal(self, commander: str, seq: int, now_ns: int) -> str | None:
        """Why a command from ``commander`` numbered ``seq``, arriving at ``now_ns`` [ns], must not
        reach the motors (None: obey it)."""
        if not self.alive:
            reason = NO_LIVE_COMMANDER
        elif self.instance is None:
            reason = UNKNOWN_COMMANDER
        elif commander != self.instance:
            reason = FOREIGN_COMMANDER
        elif seq <= self._last_seq and now_ns - self._last_ns < RESTART_GAP_NS:
            reason = SECOND_STREAM
        else:
            self._last_seq, self._last_ns = seq, now_ns
            return None
        self.refused[reason] += 1
        return reason
