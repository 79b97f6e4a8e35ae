"""Where a candidate lies on the ground: Ego-to-Allo projection (E2A) and what replaces it in the
paper's no_e2a ablation.

Contract: a pure function of the annotated grid cell and the nadir view it was read from (pose and
intrinsics); it renders nothing and changes nothing. It returns the candidate's region (a polygon in
world metres) and its centre. ACG's d_{e,j} is the distance from the target to that region (0
inside it), CErr the distance from the target to that centre (world/sim/record.py).

- With E2A the region is the cell's ground quadrilateral and the centre its centroid.
- Without E2A the paper keeps the cell only as metadata and puts the candidate centre at the UAV's
  ground footprint (paper, line 1051). The candidate is then that one point, the centre of the
  whole view's footprint, and its region is the point itself: d_{e,j} is the distance from the
  target to the footprint's centre (equal to the centre error), not 0 for every target anywhere
  in the ~92 m footprint, which would give no_e2a an ACG its candidates did not earn.
"""

from __future__ import annotations

import numpy as np

from agos.runtime.camera import cell_polygon_world, footprint_world
from agos.runtime.geometry import Point, centroid
from agos.runtime.schemas import CameraIntrinsics


def candidate_region(cell: str, world_from_camera: np.ndarray, intrinsics: CameraIntrinsics, *,
                     e2a: bool) -> tuple[list[Point], Point]:
    """The candidate's ground region and centre for ``cell`` of the nadir view taken from
    ``world_from_camera`` (raises ValueError for a malformed cell). With ``e2a`` the cell's ground
    polygon and its centroid; without, ``([c], c)`` with ``c`` the centre of the view's footprint."""
    if e2a:
        polygon = cell_polygon_world(cell, world_from_camera, intrinsics)
        return polygon, centroid(polygon)
    centre = centroid(footprint_world(world_from_camera, intrinsics))
    return [centre], centre
