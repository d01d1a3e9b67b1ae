"""Exceptions every driver raises, so the server can map any device's trouble to one reply.

Drivers never import the server; the server maps DeviceFault to `ERR 503 device` and DeviceTimeout
to `ERR 504 timeout`, with the device's name and what it said.
"""
from __future__ import annotations


class DeviceFault(Exception):
    """A device is missing, not responding, or reported an error."""

    device = "device"

    def __init__(self, message: str, device: str | None = None):
        super().__init__(message)
        if device is not None:
            self.device = device


class DeviceTimeout(DeviceFault):
    """A device did not answer within its configured time."""
