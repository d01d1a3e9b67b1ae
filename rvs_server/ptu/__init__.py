"""The pan-tilt unit's command: move-ptu."""
from rvs_server.ptu.commands import module

__all__ = ["module"]
