"""The system commands: status, version, help, check, standby, sleep, break, continue, abort, reset,
reinit, logbook, quit, auth, subscribe; products (storage.py: sizes and the retention rule)."""
from rvs_server.system import storage  # noqa: F401  (registers products on the module)
from rvs_server.system.commands import module

__all__ = ["module"]
