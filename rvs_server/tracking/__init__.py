"""3-D target tracking: track3d-detect (a job that searches for a person around the rover) and
track3d-start / track3d-stop (a background activity that follows it, the PTU kept on it)."""
from rvs_server.tracking.commands import TrackingSettings, module

__all__ = ["module", "TrackingSettings"]
