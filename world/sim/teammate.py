"""The UGV as its teammate sees it in the reference: one top-down picture of the ground vehicle.

The UAV's prompt carries, beside the target's references, a picture of its own teammate seen from
above, so that a model can tell the UGV apart from the cars it searches among (docs/AGENTS.md).

Contract: :func:`teammate_top_view` returns that picture as an :class:`ImageFrame` named
:data:`TEAMMATE_TOP`: the UGV's vehicle (:data:`UGV_MODEL` in :data:`UGV_PAINT`, with a roof rack
for its sensors in the rich look, which draws attributes) rendered alone in the studio, far from
the town, by the same nearly orthographic camera as the target's ``ref_top`` (background removed,
``metres_per_px`` set, nose towards the top of the image). The vehicle is added for the render and
removed again, so the scene is left as it was found. The picture depends only on the scene (its
look and renderer) and the reference size, so each scene renders it once and reuses it.

The UGV is not drawn in the town (its cameras ride on a platform the renderer does not show), so
today the picture says what the teammate looks like, not where it is in a view.
"""

from __future__ import annotations

import weakref
from typing import Final

import numpy as np

from agos.runtime.episode_config import CameraConfig
from agos.runtime.schemas import ImageFrame
from agos.world.sim import sensors
from agos.world.sim.scene import STUDIO_OFFSET_M, Scene
from agos.world.towns.look.vehicles import VehicleAttributes

TEAMMATE_TOP: Final = "teammate_top"
"""The frame's name (``Observation.teammate_reference.name``)."""
UGV_MODEL: Final = "suv"
UGV_PAINT: Final = "white"
UGV_RICH_ATTRIBUTES: Final = VehicleAttributes(rack=True)
"""A roof rack (the sensor mount) where the look draws attributes; the flat look draws none."""

_cache: weakref.WeakKeyDictionary[Scene, dict[int, ImageFrame]] = weakref.WeakKeyDictionary()


def teammate_top_view(scene: Scene, cam: CameraConfig) -> ImageFrame:
    """The UGV seen from straight above, alone, ``cam.reference_px`` pixels a side (see the module)."""
    per_scene = _cache.setdefault(scene, {})
    frame = per_scene.get(cam.reference_px)
    if frame is None:
        frame = per_scene[cam.reference_px] = _render(scene, cam.reference_px)
    return frame


def _render(scene: Scene, size_px: int) -> ImageFrame:
    centre = np.asarray(STUDIO_OFFSET_M, dtype=np.float64)
    yaw = 0.0
    attributes = UGV_RICH_ATTRIBUTES if scene.look == "rich" else None
    uid = scene.add_vehicle(UGV_MODEL, UGV_PAINT, (float(centre[0]), float(centre[1]), 0.0), yaw,
                            attributes=attributes)
    try:
        return sensors.isolated_view(scene, uid, sensors.top_view_camera(TEAMMATE_TOP, centre, yaw), centre, yaw,
                                     size_px)
    finally:
        scene.remove(uid)
