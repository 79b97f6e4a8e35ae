"""A minimal episode specification for tests that need one to carry, not to play; small cameras for tests
that play one but do not depend on what its images show."""

from __future__ import annotations

from agos.runtime.schemas import EpisodeSpec, TownRef, VehicleSpec

SMALL_CAMERAS = {"nadir_px": 64, "ground_px": 64, "reference_px": 32, "map_px": 64}
"""``cameras=`` for ``episode_config`` (or ``CameraConfig(**SMALL_CAMERAS)``): 64 px views and 32 px
references, a render about a quarter of the default's cost; for tests whose promise is not about the images."""


def minimal_spec(episode_id: str) -> EpisodeSpec:
    """An easy grid-s7 episode with a red sedan at the origin and one UAV waypoint (asset hash zeros)."""
    car = VehicleSpec(model="sedan", colour="red", position_world_m=(0.0, 0.0, 0.0), yaw_rad=0.0)
    return EpisodeSpec(episode_id=episode_id, town=TownRef(generator="grid", seed=7, town_id="grid-s7"),
                       asset_sha256="0" * 64, difficulty="easy", region_world_m=(0.0, 0.0, 100.0, 100.0), target=car,
                       uav_start_waypoint="u0", ugv_start_waypoint="a0", active_uav_waypoints=["u0"], seed=1)


def grid_episodes() -> list[EpisodeSpec]:
    """Three episodes (easy, mid, hard with a two-tone look-alike, so rich only) that every check of an
    episode file passes on grid-s7, made from its nodes in a second (not sampled: not checked solvable)."""
    from agos.world.towns.asset import open_town

    town = open_town("grid-s7")
    anchors = sorted(n for n, kind in town.roads.anchors.items() if kind == "cruise")
    specs = []
    for i, (difficulty, anchor) in enumerate(zip(("easy", "mid", "hard"), anchors[::97], strict=False)):
        x, y = (float(v) for v in town.roads.positions_world_m[anchor])
        region = (x - 75.0, y - 75.0, x + 75.0, y + 75.0)
        active = town.uav_grid.inside(region) or sorted(town.uav_grid.nodes)[:1]
        target = VehicleSpec(model="sedan", colour="red", position_world_m=(x, y, 0.0), yaw_rad=0.5)
        lookalike = VehicleSpec(model="suv", colour="red", position_world_m=(x + 5, y, 0.0), yaw_rad=0.0, roof="white")
        specs.append(EpisodeSpec(
            episode_id=f"grid-s7-{difficulty}-{i:03d}-v1", town=TownRef(generator="grid", seed=7, town_id="grid-s7"),
            asset_sha256=town.sha256, difficulty=difficulty, region_world_m=region, target=target,
            distractors=[lookalike] if difficulty == "hard" else [], uav_start_waypoint=active[0],
            ugv_start_waypoint=town.roads.anchor_id(anchor), active_uav_waypoints=active, seed=i))
    return specs
