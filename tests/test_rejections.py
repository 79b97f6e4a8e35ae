"""non_finite_field: the fast sum agrees with the plain walk (runtime/rejections.py)."""

from __future__ import annotations

import math

import msgspec

from agos.runtime.rejections import _first_non_finite, non_finite_field
from agos.runtime.schemas import CameraIntrinsics, CoordinationState, ImageFrame, Pose, Waypoint


class Nested(msgspec.Struct):
    name: str
    pose: Pose | None
    frames: list[ImageFrame]
    waypoints: list[Waypoint]
    by_name: dict[str, Pose]
    numbers: tuple[float, int, float]
    loose: list[object]
    coordination: CoordinationState
    inner: Nested | None = None


def sample() -> Nested:
    pose = Pose(position_world_m=(1.0, 2.0, 3.0), yaw_rad=0.5)
    frame = ImageFrame(name="rgb", kind="rgb", encoding="png", data=b"\x7f\xf0" * 8,
                       intrinsics=CameraIntrinsics(width_px=4, height_px=4, fx_px=2.0, fy_px=2.0, cx_px=2.0, cy_px=2.0),
                       world_from_camera=[0.5] * 16, depth_scale_m=None, metres_per_px=0.25)
    waypoints = [Waypoint(waypoint_id=f"w{i}", position_world_m=(i, 1.0, 0.0), kind="road",
                          path_length_m=None if i % 2 else 3.0, distance_to_candidate_m=1.5) for i in range(3)]
    coordination = CoordinationState(run_id="r", episode_id="e", sim_time_s=4.0, poses={"uav": pose})
    inner = Nested(name="in", pose=None, frames=[], waypoints=[], by_name={}, numbers=(1.0, 2, 3.0), loose=[],
                   coordination=coordination)
    return Nested(name="out", pose=pose, frames=[frame], waypoints=waypoints, by_name={"a": pose},
                  numbers=(1.0, 2, 3.0), loose=["x", 1.0, None, [2.0, "y"]], coordination=coordination, inner=inner)


def float_slots(value, path=()):
    """Every float in ``value`` as a path of (kind, key) steps."""
    if isinstance(value, float):
        yield path
    elif isinstance(value, msgspec.Struct):
        for name in value.__struct_fields__:
            yield from float_slots(getattr(value, name), (*path, ("attr", name)))
    elif isinstance(value, (list, tuple)):
        for i, item in enumerate(value):
            yield from float_slots(item, (*path, ("item", i)))
    elif isinstance(value, dict):
        for k, item in value.items():
            yield from float_slots(item, (*path, ("item", k)))


def replaced(value, path, new):
    """``value`` with the float at ``path`` replaced by ``new`` (tuples rebuilt, the rest in place)."""
    (kind, key), rest = path[0], path[1:]
    child = getattr(value, key) if kind == "attr" else value[key]
    child = new if not rest else replaced(child, rest, new)
    if kind == "attr":
        setattr(value, key, child)
    elif isinstance(value, tuple):
        return (*value[:key], child, *value[key + 1:])
    else:
        value[key] = child
    return value


def test_finite_message_passes():
    assert non_finite_field(sample()) is None
    assert non_finite_field([1e308, 1e308]) is None  # finite numbers whose sum overflows
    assert non_finite_field([10**400, 1.0]) is None  # an int too large for a float


def test_every_float_slot_is_found_with_the_walks_path():
    slots = list(float_slots(sample()))
    assert len(slots) > 40
    for path in slots:
        for bad in (math.nan, math.inf, -math.inf):
            value = replaced(sample(), path, bad)
            expected = _first_non_finite(value, "$")
            assert expected is not None
            assert non_finite_field(value) == expected


def test_plain_containers():
    assert non_finite_field({"a": [1.0, (2.0, math.nan)]}) == "$.a[1][1]"
    assert non_finite_field([1, math.inf]) == "$[1]"
    assert non_finite_field((math.inf, -math.inf)) == "$[0]"
    assert non_finite_field("nan") is None
