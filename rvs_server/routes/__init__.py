"""Image-based routes: drive, route-record, route-follow, route-connect, route-list, route-go."""
from rvs_server.routes.commands import module

__all__ = ["module"]
