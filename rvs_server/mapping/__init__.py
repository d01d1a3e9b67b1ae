"""DEMs, ortho-images and hazard maps: dem-full[-tof], dem-update[-tof], dem-full-fused.

Other capabilities use mapping through the names below and nothing else (tests/core/
test_import_directions.py holds them to it): navigate runs the mapping workflows and writes their
maps (and, from a fused one, what the fusion found); routes points the PTU and reads the stereo
intrinsics.
"""
from rvs_server.mapping.commands import MappingSettings, WorkflowArgs, check_workflow, module, write_maps
from rvs_server.mapping.steps import (
    fusion_record,
    leave_camera_as_acquired,
    operations,
    point_ptu,
    stereo_intrinsics,
)

__all__ = ["module", "MappingSettings", "WorkflowArgs", "check_workflow", "write_maps", "operations",
           "leave_camera_as_acquired", "point_ptu", "stereo_intrinsics", "fusion_record"]
