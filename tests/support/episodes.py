"""A minimal episode specification for tests that need one to carry, not to play."""

from __future__ import annotations

from agos.runtime.schemas import EpisodeSpec, TownRef, VehicleSpec


def minimal_spec(episode_id: str) -> EpisodeSpec:
    """An easy grid-s7 episode with a red sedan at the origin and one UAV waypoint (asset hash zeros)."""
    car = VehicleSpec(model="sedan", colour="red", position_world_m=(0.0, 0.0, 0.0), yaw_rad=0.0)
    return EpisodeSpec(episode_id=episode_id, town=TownRef(generator="grid", seed=7, town_id="grid-s7"),
                       asset_sha256="0" * 64, difficulty="easy", region_world_m=(0.0, 0.0, 100.0, 100.0), target=car,
                       uav_start_waypoint="u0", ugv_start_waypoint="a0", active_uav_waypoints=["u0"], seed=1)
