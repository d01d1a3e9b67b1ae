"""Commands that exist only on the simulated world: sim-fault, sun."""
from rvs_server.simulation.commands import module

__all__ = ["module"]
