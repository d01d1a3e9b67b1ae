"""Single acquisitions: grab-tof and grab-stereo, each written as a product."""
from rvs_server.imaging.commands import module

__all__ = ["module"]
