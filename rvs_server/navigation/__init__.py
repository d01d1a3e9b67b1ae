"""Path planning and the rover's pose: plan-path, pose and the navigate loop."""
from rvs_server.navigation import navigate as _navigate  # noqa: F401  registers `navigate` on the module
from rvs_server.navigation.commands import module

__all__ = ["module"]
