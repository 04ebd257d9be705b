"""Latched faults shared by every device driver: set by the driver, cleared only on command."""

from __future__ import annotations

import logging


class LatchedFaults:
    """Mixin: ``self.faults`` (list of reasons) and ``self.stats.faults_latched`` must exist."""

    faults: list[str]
    device_name: str = "device"
    fault_log: logging.Logger = logging.getLogger("archer.drivers")

    @property
    def faulted(self) -> bool:
        return bool(self.faults)

    def latch(self, reason: str) -> None:
        if reason not in self.faults:
            self.faults.append(reason)
            self.stats.faults_latched += 1  # type: ignore[attr-defined]
            self.fault_log.error(f"{self.device_name} fault latched: {reason}", extra={"fields": {"reason": reason}})
