"""What every device wrapper shares: its health (`ok`, `fault`, `off`) and last error."""
from __future__ import annotations

import logging
from typing import Any, Literal

from ..protocol import DeviceError

log = logging.getLogger("rvs.devices")

Health = Literal["ok", "fault", "off"]


class Device:
    """Health bookkeeping shared by every device."""

    name = "device"

    def __init__(self) -> None:
        self.health: Health = "off"
        self.last_error = ""

    def _fault(self, exc: BaseException) -> None:
        self.health = "fault"
        self.last_error = str(exc)
        log.error("%s: %s", self.name, exc)

    def require_healthy(self) -> None:
        """ERR 503 naming the device and its last error, unless it is ok."""
        if self.health != "ok":
            detail = f": {self.last_error}" if self.last_error else ""
            raise DeviceError(f"{self.name} is {self.health}{detail}")

    def require(self) -> Any:
        """The driver, or ERR 503 naming the device and its last error."""
        self.require_healthy()
        return self.driver  # type: ignore[attr-defined]

    def health_items(self) -> dict[str, str]:
        """What status shows for this device."""
        return {f"dev.{self.name}": self.health}

    def open(self) -> None: ...
    def close(self) -> None: ...
    def check(self) -> None: ...
    def reset(self) -> None: ...
    def park(self) -> None: ...
