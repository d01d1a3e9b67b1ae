"""The system commands: status, version, help, check, standby, sleep, break, continue, abort, reset,
reinit, logbook, quit, auth, subscribe."""
from rvs_server.system.commands import module

__all__ = ["module"]
