"""The hopping rover: hop, hop-plan, hop-map, with the hop's reconstruction (structure from motion),
estimate, landing plan, store and pictures."""
from rvs_server.hopping.commands import module

__all__ = ["module"]
