"""The heuristic UGV's second look: where the UAV saw its match (the point its message names) and
whether the six views see that place, on box-built vehicles ray-cast in a synthetic street
(tests/support/boxcars.py)."""

from __future__ import annotations

from agos.agents.heuristic.ugv import point_in_sight, uav_point
from agos.runtime.schemas import MessageRecord

from support import boxcars

RED, GREY = (200, 30, 25), (120, 120, 125)
CELL = [(0.0, 0.0), (20.0, 0.0), (20.0, 20.0), (0.0, 20.0)]


def message(sender: str, text: str) -> MessageRecord:
    return MessageRecord(sender=sender, receiver="ugv" if sender == "uav" else "uav", text=text,  # type: ignore[arg-type]
                         sent_sim_time_s=1.0, delivered_sim_time_s=1.0)


def test_the_uav_point_is_the_latest_inside_the_candidate() -> None:
    texts = [message("uav", "Candidate in cell B2; please verify. Look near (5.0, 6.5) m."),
             message("ugv", "Look near (7.0, 7.0) m."),  # not the UAV's
             message("uav", "Candidate in cell C3; please verify. Look near (-12.5, 3.0) m.")]  # another cell
    assert uav_point(texts, CELL) == (5.0, 6.5)
    assert uav_point(texts[:1] + [message("uav", "Candidate near (12.25, 18.0) m.")], CELL) == (12.25, 18.0)
    assert uav_point([message("uav", "Candidate in cell B2; please verify.")], CELL) is None


def test_a_point_behind_a_truck_next_to_the_ugv_is_hidden() -> None:
    truck = boxcars.placed(boxcars.box_truck(GREY), 4.5, 0.0)  # right in front of the camera
    target = boxcars.placed(boxcars.car(RED, length_m=4.6, width_m=1.8, height_m=1.4), 15.0, 0.0)
    assert not point_in_sight([boxcars.ground_view([truck, target])], (15.0, 0.0), half_length_m=2.3)


def test_an_open_street_and_the_target_standing_at_the_point_are_in_sight() -> None:
    target = boxcars.placed(boxcars.car(RED, length_m=4.6, width_m=1.8, height_m=1.4), 15.0, 0.0)
    assert point_in_sight([boxcars.ground_view([])], (15.0, 0.0), half_length_m=2.3)
    assert point_in_sight([boxcars.ground_view([target])], (15.0, 0.0), half_length_m=2.3)  # seen end-on
    # out of every view (behind the camera) is not in sight
    assert not point_in_sight([boxcars.ground_view([target])], (-15.0, 0.0), half_length_m=2.3)


def test_the_uav_refuses_only_the_points_the_ugv_rejected_and_goes_back_to_its_best_weaker_match() -> None:
    """The heuristic UAV's memory: candidate C00k is its k-th annotation, so a rejection refuses
    that annotation's point (4 m), not the cell around it; weaker detections of one vehicle merge
    (best score kept), and the best one neither annotated nor refused is where it flies back to."""
    from types import SimpleNamespace

    from agos.agents.heuristic.uav import HeuristicUav, _Memory

    uav = HeuristicUav()
    mem = _Memory(profile=None, top_m=None)  # type: ignore[arg-type]
    mem.annotated = [(0.0, 0.0), (40.0, 0.0)]
    cands = [SimpleNamespace(candidate_id="C001", status="rejected", center_world_m=(5.0, 5.0)),
             SimpleNamespace(candidate_id="C002", status="pending", center_world_m=(45.0, 5.0)),
             SimpleNamespace(candidate_id="C003", status="rejected", center_world_m=(90.0, 90.0))]  # not its own
    obs = SimpleNamespace(coordination=SimpleNamespace(candidates=cands))
    points, centres = uav._refused(obs, mem)  # type: ignore[arg-type]
    assert points == [(0.0, 0.0)] and centres == [(90.0, 90.0)]
    for point, score in (((10.0, 0.0), 0.6), ((11.0, 1.0), 0.7), ((2.0, 0.0), 0.74), ((40.5, 0.0), 0.73)):
        uav._remember(mem, point, score)
    assert mem.remembered == [((10.0, 0.0), 0.7), ((2.0, 0.0), 0.74), ((40.5, 0.0), 0.73)]
    # (2, 0) is the rejected vehicle, (40.5, 0) the one under verification: back to (10, 0)
    assert uav._best_remembered(obs, mem) == ((10.0, 0.0), 0.7)  # type: ignore[arg-type]
    painted = HeuristicUav(paint_only=True)  # the floor refuses 12 m around every rejected centre
    assert painted._refused(obs, mem) == ([], [(5.0, 5.0), (90.0, 90.0)])  # type: ignore[arg-type]
