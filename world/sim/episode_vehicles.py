"""An episode's vehicles in a scene: a :class:`VehicleSpec` drawn with its attributes, by a look that can.

The rich look draws every body type and attribute. The flat look refuses (never ignores) what it
cannot draw, a bus or any attribute: an episode whose look-alike differs from the target only in
an attribute would show two identical vehicles, and a hard episode would silently lose its point.
:func:`check_look` says so before anything is added (:class:`LookMismatch`, an invalid episode);
episodes sampled with the flat look never carry either (world/episodes/lookalikes.py).
"""

from __future__ import annotations

from agos.runtime.schemas import EpisodeSpec, VehicleSpec
from agos.world.sim.scene import Scene
from agos.world.towns.catalog import BODY_TYPES
from agos.world.towns.look.vehicles import VehicleAttributes


class LookMismatch(ValueError):
    """An episode names a vehicle the configured look cannot draw."""


def attributes_of(vehicle: VehicleSpec) -> VehicleAttributes:
    return VehicleAttributes(roof=vehicle.roof, rack=vehicle.rack, stripe=vehicle.stripe)


def flat_refusal(vehicle: VehicleSpec) -> str | None:
    """Why the flat look cannot draw a vehicle, or None if it can."""
    if vehicle.model not in BODY_TYPES:
        return f"a {vehicle.model} (the flat look has no such box model)"
    if attributes_of(vehicle) != VehicleAttributes():
        return "vehicle attributes (roof, rack, stripe)"
    return None


def check_look(spec: EpisodeSpec, look: str) -> None:
    """Raise :class:`LookMismatch` naming the episode unless ``look`` draws all its vehicles."""
    if look == "rich":
        return
    for role, vehicle in (("target", spec.target), *(("look-alike", d) for d in spec.distractors)):
        reason = flat_refusal(vehicle)
        if reason is not None:
            raise LookMismatch(f"episode {spec.episode_id}: its {role} needs look = \"rich\" ({reason}); "
                               f"this run's look is {look!r}")


def add_vehicle(scene: Scene, vehicle: VehicleSpec) -> int:
    """Add one episode vehicle with its attributes; return its body id."""
    return scene.add_vehicle(vehicle.model, vehicle.colour, vehicle.position_world_m, vehicle.yaw_rad,
                             attributes=attributes_of(vehicle))


def add_episode_vehicles(scene: Scene, spec: EpisodeSpec) -> list[int]:
    """Check the look, then add the target and its look-alikes: body ids, the target's first."""
    check_look(spec, scene.look)
    return [add_vehicle(scene, v) for v in (spec.target, *spec.distractors)]
