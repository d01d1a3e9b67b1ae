"""DEMs, ortho-images and hazard maps: dem-full[-tof], dem-update[-tof], and the workflow steps
(`steps.operations`) that navigate reuses."""
from rvs_server.mapping.commands import module

__all__ = ["module"]
