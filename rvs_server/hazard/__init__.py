"""Dynamic hazard detection: hazard-start / hazard-stop, a background activity that looks along the
rover's path frame after frame and stops any drive short of a hazard the maps did not know."""
from rvs_server.hazard.commands import module
from rvs_server.hazard.settings import HazardSettings

__all__ = ["module", "HazardSettings"]
