"""Commands that exist only on the simulated world: sim-fault, sun, astronaut, sim-rock."""
from rvs_server.simulation.commands import module

__all__ = ["module"]
