"""OpenDRIVE importer: reference-line geometry, lane placement, links, warnings, errors, CARLA towns."""

from __future__ import annotations

import math
from pathlib import Path

import networkx as nx
import numpy as np
import pytest

from agos.world.towns.lanes import LaneNetwork
from agos.world.towns.opendrive import OpenDriveError, load_lane_network

MAPS = Path(__file__).resolve().parents[2] / "shared" / "maps"
W = 3.5


def _lane(lid: int, *, kind: str = "driving", width: str | None = None, link: str = "") -> str:
    width = width if width is not None else f'<width sOffset="0" a="{W}" b="0" c="0" d="0"/>'
    return f'<lane id="{lid}" type="{kind}" level="false"><link>{link}</link>{width}</lane>'


def _section(left: str = "", right: str = "", s: float = 0.0) -> str:
    return (f'<laneSection s="{s}"><left>{left}</left><center><lane id="0" type="none"/></center>'
            f"<right>{right}</right></laneSection>")


def _road(rid: str, geometry: str, length: float, *, sections: str | None = None, link: str = "",
          junction: str = "-1", offset: str = "", rule: str = "") -> str:
    sections = sections if sections is not None else _section(_lane(1), _lane(-1))
    rule_attr = f' rule="{rule}"' if rule else ""
    return (f'<road name="" length="{length}" id="{rid}" junction="{junction}"{rule_attr}><link>{link}</link>'
            f"<planView>{geometry}</planView><lanes>{offset}{sections}</lanes></road>")


def _line(x: float, y: float, hdg: float, length: float, s: float = 0.0) -> str:
    return f'<geometry s="{s}" x="{x}" y="{y}" hdg="{hdg}" length="{length}"><line/></geometry>'


def _load(tmp_path: Path, *roads: str, junctions: str = "", name: str = "test.xodr", **kw) -> LaneNetwork:
    path = tmp_path / name
    path.write_text(f'<?xml version="1.0"?>\n<OpenDRIVE><header revMajor="1" revMinor="4"/>{"".join(roads)}'
                    f"{junctions}</OpenDRIVE>")
    return load_lane_network(path, **kw)


def _left_normal(hdg: float) -> np.ndarray:
    return np.array([-math.sin(hdg), math.cos(hdg)])


def _spacing(centre: np.ndarray) -> np.ndarray:
    return np.linalg.norm(np.diff(centre, axis=0), axis=1)


# -- geometry --------------------------------------------------------------------------------


def test_straight_road_places_lanes_and_directions(tmp_path):
    net = _load(tmp_path, _road("1", _line(0, 0, 0, 100), 100))
    assert set(net.lanes) == {"r1.s0.-1", "r1.s0.1"}
    right, left = net.lanes["r1.s0.-1"], net.lanes["r1.s0.1"]
    np.testing.assert_allclose(right.centre_m[:, 1], -1.75, atol=1e-9)
    np.testing.assert_allclose(left.centre_m[:, 1], 1.75, atol=1e-9)
    np.testing.assert_allclose(right.centre_m[[0, -1], 0], [0, 100], atol=1e-9)  # right lane travels +x
    np.testing.assert_allclose(left.centre_m[[0, -1], 0], [100, 0], atol=1e-9)  # left lane travels -x
    assert len(right.centre_m) == 201 and _spacing(right.centre_m).max() <= 0.5 + 1e-9
    np.testing.assert_allclose(right.width_m, W)
    assert right.road_id == "1" and not right.in_junction and right.successors == [] and right.parking_offset_m is None
    assert net.warnings == []
    coarse = _load(tmp_path, _road("1", _line(0, 0, 0, 100), 100), step_m=2.0)
    assert len(coarse.lanes["r1.s0.-1"].centre_m) == 51


def test_arc_end_point(tmp_path):
    geo = '<geometry s="0" x="0" y="0" hdg="0" length="100"><arc curvature="0.01"/></geometry>'
    net = _load(tmp_path, _road("1", geo, 100))
    # reference line end: x = sin(kL)/k, y = (1 - cos(kL))/k with kL = 1 rad; lane -1 lies 1.75 m to its right
    end = np.array([math.sin(1.0) / 0.01, (1 - math.cos(1.0)) / 0.01]) - 1.75 * _left_normal(1.0)
    right = net.lanes["r1.s0.-1"]
    np.testing.assert_allclose(right.centre_m[-1], end, atol=1e-6)
    np.testing.assert_allclose(net.lanes["r1.s0.1"].centre_m[0], end + 3.5 * _left_normal(1.0), atol=1e-6)
    assert _spacing(right.centre_m).max() <= 0.5 + 1e-9  # the outer (left) lane is sampled denser than the reference
    assert _spacing(net.lanes["r1.s0.1"].centre_m).max() <= 0.5 + 1e-9


def test_spiral_end_heading_and_position(tmp_path):
    geo = '<geometry s="0" x="0" y="0" hdg="0" length="100"><spiral curvStart="0" curvEnd="0.02"/></geometry>'
    net = _load(tmp_path, _road("1", geo, 100))
    # heading 0.0001 s^2 -> 1.0 rad at s = 100; position by a fine independent quadrature
    s = np.linspace(0, 100, 2_000_001)
    th = 0.0001 * s**2
    ref_end = np.array([np.trapezoid(np.cos(th), s), np.trapezoid(np.sin(th), s)])
    right = net.lanes["r1.s0.-1"]
    assert np.linalg.norm(right.centre_m[-1] - (ref_end - 1.75 * _left_normal(1.0))) < 0.01
    d = right.centre_m[-1] - right.centre_m[-2]
    assert math.atan2(d[1], d[0]) == pytest.approx(1.0, abs=0.01)
    # the left lane starts where the right lane ends, 3.5 m across
    assert np.linalg.norm(net.lanes["r1.s0.1"].centre_m[0] - right.centre_m[-1]) == pytest.approx(3.5, abs=1e-6)


def test_param_poly3_normalized_straight_line(tmp_path):
    geo = ('<geometry s="0" x="10" y="20" hdg="1.5707963267948966" length="100"><paramPoly3 aU="0" bU="100" cU="0" '
           'dU="0" aV="0" bV="0" cV="0" dV="0" pRange="normalized"/></geometry>')
    net = _load(tmp_path, _road("1", geo, 100))
    right = net.lanes["r1.s0.-1"]  # heading north: right is +x
    np.testing.assert_allclose(right.centre_m[0], [11.75, 20], atol=1e-6)
    np.testing.assert_allclose(right.centre_m[-1], [11.75, 120], atol=1e-6)
    np.testing.assert_allclose(_spacing(right.centre_m), 0.5, atol=1e-6)
    assert net.warnings == []


def test_param_poly3_arc_length_and_poly3_curve(tmp_path):
    # a quarter circle of radius 20 as a paramPoly3 in arcLength range is not exact; use a parabola instead
    length = 50.0
    c = 0.004
    u = np.linspace(0, length, 400_001)
    arc = np.concatenate([[0], np.cumsum(np.hypot(np.diff(u), np.diff(c * u**2)))])
    u_end = np.interp(length, arc, u)
    poly3 = f'<geometry s="0" x="0" y="0" hdg="0" length="{length}"><poly3 a="0" b="0" c="{c}" d="0"/></geometry>'
    net = _load(tmp_path, _road("1", poly3, length))
    hdg_end = math.atan(2 * c * u_end)
    expect = np.array([u_end, c * u_end**2]) - 1.75 * _left_normal(hdg_end)
    assert np.linalg.norm(net.lanes["r1.s0.-1"].centre_m[-1] - expect) < 0.01
    # the same parabola as a paramPoly3 with p in [0, length] along u
    pp = (f'<geometry s="0" x="0" y="0" hdg="0" length="{length}"><paramPoly3 aU="0" bU="{u_end / length}" cU="0" dU="0" '
          f'aV="0" bV="0" cV="{c * (u_end / length) ** 2}" dV="0" pRange="arcLength"/></geometry>')
    net2 = _load(tmp_path, _road("1", pp, length), name="pp.xodr")
    assert np.linalg.norm(net2.lanes["r1.s0.-1"].centre_m[-1] - expect) < 0.01


def test_tiny_geometry_skipped_with_warning(tmp_path):
    geo = _line(0, 0, 0.5, 1e-9) + _line(0, 0, 0, 50, s=1e-9)
    net = _load(tmp_path, _road("7", geo, 50))
    np.testing.assert_allclose(net.lanes["r7.s0.-1"].centre_m[-1], [50, -1.75], atol=1e-6)
    assert any("road 7" in w and "skipped" in w and "geometry" in w for w in net.warnings)


def test_lane_offset_shifts_lanes(tmp_path):
    offset = '<laneOffset s="0" a="1.0" b="0.01" c="0" d="0"/>'
    net = _load(tmp_path, _road("1", _line(0, 0, 0, 100), 100, offset=offset))
    right, left = net.lanes["r1.s0.-1"], net.lanes["r1.s0.1"]
    np.testing.assert_allclose(right.centre_m[0], [0, 1.0 - 1.75], atol=1e-9)
    np.testing.assert_allclose(right.centre_m[-1], [100, 2.0 - 1.75], atol=1e-9)
    np.testing.assert_allclose(left.centre_m[0], [100, 2.0 + 1.75], atol=1e-9)


def test_widths_cubic_records_and_border(tmp_path):
    right = (_lane(-1, width='<width sOffset="0" a="3" b="0" c="0" d="0"/><width sOffset="50" a="3" b="0.02" c="0" d="0"/>')
             + _lane(-2, width='<border sOffset="0" a="-7" b="0" c="0" d="0"/>'))
    net = _load(tmp_path, _road("1", _line(0, 0, 0, 100), 100, sections=_section("", right)))
    lane1, lane2 = net.lanes["r1.s0.-1"], net.lanes["r1.s0.-2"]
    assert lane1.width_m[0] == pytest.approx(3.0) and lane1.width_m[-1] == pytest.approx(4.0)
    # lane -2's outer edge is at t = -7: its width is 7 - width(-1)
    assert lane2.width_m[0] == pytest.approx(4.0) and lane2.width_m[-1] == pytest.approx(3.0)
    assert lane2.centre_m[0, 1] == pytest.approx(-5.0) and lane2.centre_m[-1, 1] == pytest.approx(-5.5)


def test_bidirectional_and_left_hand_traffic(tmp_path):
    net = _load(tmp_path, _road("1", _line(0, 0, 0, 20), 20, sections=_section("", _lane(-1, kind="bidirectional"))))
    assert set(net.lanes) == {"r1.s0.-1", "r1.s0.-1.rev"}
    np.testing.assert_allclose(net.lanes["r1.s0.-1.rev"].centre_m, net.lanes["r1.s0.-1"].centre_m[::-1])
    lht = _load(tmp_path, _road("1", _line(0, 0, 0, 20), 20, rule="LHT"), name="lht.xodr")
    assert lht.lanes["r1.s0.-1"].centre_m[0, 0] == pytest.approx(20)  # right lane now travels -x
    assert lht.lanes["r1.s0.1"].centre_m[0, 0] == pytest.approx(0)


def test_parking_offset_next_to_wide_parking_lane(tmp_path):
    park = '<width sOffset="0" a="2.5" b="0" c="0" d="0"/>'
    narrow = '<width sOffset="0" a="0.3" b="0" c="0" d="0"/>'
    sections = _section(_lane(1) + _lane(2, kind="parking", width=park),
                        _lane(-1) + _lane(-2) + _lane(-3, kind="shoulder", width=narrow))
    net = _load(tmp_path, _road("1", _line(0, 0, 0, 50), 50, sections=sections))
    assert net.lanes["r1.s0.1"].parking_offset_m == pytest.approx(W / 2 + 1.2)
    assert net.lanes["r1.s0.-1"].parking_offset_m is None  # not the outermost driving lane
    assert net.lanes["r1.s0.-2"].parking_offset_m is None  # shoulder too narrow


def test_zero_width_driving_lane_skipped_with_warning(tmp_path):
    zero = '<width sOffset="0" a="0" b="0" c="0" d="0"/>'
    sections = _section("", _lane(-1) + _lane(-2, width=zero))
    net = _load(tmp_path, _road("5", _line(0, 0, 0, 30), 30, sections=sections))
    assert set(net.lanes) == {"r5.s0.-1"}
    assert any(w.startswith("test.xodr: road 5:") and "zero width" in w for w in net.warnings)


def test_single_side_section_inherits_the_other_side(tmp_path):
    first = _section(_lane(1), _lane(-1, link='<successor id="-1"/>'))
    second = ('<laneSection s="30" singleSide="true"><center><lane id="0" type="none"/></center><right>'
              + _lane(-1, width='<width sOffset="0" a="3.5" b="0.01" c="0" d="0"/>', link='<predecessor id="-1"/>')
              + "</right></laneSection>")
    net = _load(tmp_path, _road("1", _line(0, 0, 0, 60), 60, sections=first + second))
    assert set(net.lanes) == {"r1.s0.1", "r1.s0.-1", "r1.s1.1", "r1.s1.-1"}
    assert net.lanes["r1.s1.1"].successors == ["r1.s0.1"]
    np.testing.assert_allclose(net.lanes["r1.s1.1"].centre_m[:, 1], 1.75)
    assert net.lanes["r1.s1.-1"].width_m[-1] == pytest.approx(3.8)


# -- links -----------------------------------------------------------------------------------


def test_lane_sections_link_within_a_road(tmp_path):
    sections = (_section(_lane(1), _lane(-1, link='<successor id="-2"/>'))
                + _section(_lane(1, link='<predecessor id="1"/>'), _lane(-1) + _lane(-2, link='<predecessor id="-1"/>'), s=40))
    net = _load(tmp_path, _road("1", _line(0, 0, 0, 100), 100, sections=sections))
    assert net.lanes["r1.s0.-1"].successors == ["r1.s1.-2"]
    assert net.lanes["r1.s1.1"].successors == ["r1.s0.1"]
    assert net.lanes["r1.s1.-1"].successors == []
    np.testing.assert_allclose(net.lanes["r1.s0.-1"].centre_m[-1], [40, -1.75])
    np.testing.assert_allclose(net.lanes["r1.s1.-2"].centre_m[0], [40, -5.25])


def test_roads_linked_end_to_start_and_end_to_end(tmp_path):
    sec = _section(_lane(1, link='<predecessor id="1"/><successor id="-1"/>'),
                   _lane(-1, link='<predecessor id="-1"/><successor id="1"/>'))
    road1 = _road("1", _line(0, 0, 0, 50), 50, sections=sec,
                  link=('<predecessor elementType="road" elementId="2" contactPoint="end"/>'
                        '<successor elementType="road" elementId="3" contactPoint="end"/>'))
    road2 = _road("2", _line(-50, 0, 0, 50), 50,
                  sections=_section(_lane(1, link='<successor id="1"/>'), _lane(-1, link='<successor id="-1"/>')),
                  link='<successor elementType="road" elementId="1" contactPoint="start"/>')
    # road 3 is drawn backwards (from x=100 to x=50): its end touches road 1's end
    road3 = _road("3", _line(100, 0, math.pi, 50), 50,
                  sections=_section(_lane(1, link='<successor id="-1"/>'), _lane(-1, link='<successor id="1"/>')),
                  link='<successor elementType="road" elementId="1" contactPoint="end"/>')
    net = _load(tmp_path, road1, road2, road3)
    assert net.lanes["r2.s0.-1"].successors == ["r1.s0.-1"]  # right lane continues into the next road's right lane
    assert net.lanes["r1.s0.1"].successors == ["r2.s0.1"]
    assert net.lanes["r1.s0.-1"].successors == ["r3.s0.1"]  # end-to-end: direction flips
    assert net.lanes["r3.s0.-1"].successors == ["r1.s0.1"]
    np.testing.assert_allclose(net.lanes["r1.s0.-1"].centre_m[-1], net.lanes["r3.s0.1"].centre_m[0], atol=1e-9)
    assert net.warnings == []


def test_junction_connection_creates_successors(tmp_path):
    road1 = _road("1", _line(0, 0, 0, 50), 50, link='<successor elementType="junction" elementId="100"/>',
                  sections=_section(_lane(1), _lane(-1, link='<successor id="-1"/>')))
    road2 = _road("2", _line(60, 0, 0, 50), 50, link='<predecessor elementType="junction" elementId="100"/>',
                  sections=_section(_lane(1), _lane(-1)))
    conn = _road("10", _line(50, 0, 0, 10), 10, junction="100",
                 link=('<predecessor elementType="road" elementId="1" contactPoint="end"/>'
                       '<successor elementType="road" elementId="2" contactPoint="start"/>'),
                 sections=_section(_lane(1, link='<predecessor id="1"/>'), _lane(-1, link='<successor id="-1"/>')))
    junction = ('<junction id="100" name="j"><connection id="0" incomingRoad="1" connectingRoad="10" contactPoint="start">'
                '<laneLink from="-1" to="-1"/></connection><connection id="1" incomingRoad="2" connectingRoad="10" '
                'contactPoint="end"><laneLink from="1" to="1"/></connection></junction>')
    net = _load(tmp_path, road1, road2, conn, junctions=junction)
    assert net.lanes["r1.s0.-1"].successors == ["r10.s0.-1"]
    assert net.lanes["r10.s0.-1"].successors == ["r2.s0.-1"]
    assert net.lanes["r2.s0.1"].successors == ["r10.s0.1"]
    assert net.lanes["r10.s0.1"].successors == ["r1.s0.1"]
    assert net.lanes["r10.s0.-1"].in_junction and not net.lanes["r1.s0.-1"].in_junction
    assert net.warnings == []


def test_links_to_missing_roads_and_lanes_dropped_with_warning(tmp_path):
    road = _road("4", _line(0, 0, 0, 20), 20, link='<successor elementType="road" elementId="99" contactPoint="start"/>',
                 sections=_section("", _lane(-1, link='<successor id="-1"/>')))
    other = _road("5", _line(20, 0, 0, 20), 20, link='<predecessor elementType="road" elementId="4" contactPoint="end"/>',
                  sections=_section("", _lane(-1, link='<predecessor id="-3"/>')))
    net = _load(tmp_path, road, other)
    assert net.lanes["r4.s0.-1"].successors == []
    assert any(w.startswith("test.xodr: road 4:") and "99" in w for w in net.warnings)
    assert any(w.startswith("test.xodr: road 5:") and "lane -3 of road 4 does not exist" in w for w in net.warnings)


# -- errors ----------------------------------------------------------------------------------


def test_malformed_files_raise_open_drive_error(tmp_path):
    bad = tmp_path / "broken.xodr"
    bad.write_text("<OpenDRIVE><road id='1'>")
    with pytest.raises(OpenDriveError, match=r"^broken\.xodr: not a valid XML"):
        load_lane_network(bad)
    wrong = tmp_path / "wrong.xodr"
    wrong.write_text("<svg/>")
    with pytest.raises(OpenDriveError, match=r"wrong\.xodr: root element is <svg>"):
        load_lane_network(wrong)
    with pytest.raises(OpenDriveError, match=r"missing\.xodr: cannot read"):
        load_lane_network(tmp_path / "missing.xodr")
    clothoid = '<geometry s="0" x="0" y="0" hdg="0" length="10"><clothoid/></geometry>'
    with pytest.raises(OpenDriveError, match=r"empty\.xodr: no driving lane found \(road 12: geometry type 'clothoid'"):
        _load(tmp_path, _road("12", clothoid, 10), name="empty.xodr")


def test_unsupported_road_is_skipped_with_warning(tmp_path):
    clothoid = '<geometry s="0" x="0" y="0" hdg="0" length="10"><clothoid/></geometry>'
    net = _load(tmp_path, _road("12", clothoid, 10), _road("13", _line(0, 0, 0, 10), 10))
    assert set(net.lanes) == {"r13.s0.-1", "r13.s0.1"}
    assert "test.xodr: road 12: geometry type 'clothoid' not supported; road skipped" in net.warnings


# -- real maps -------------------------------------------------------------------------------

TOWNS = {"Town01": 100, "Town02": 80, "Town04": 100, "Town06": 100, "Town07": 100, "Town10HD": 100}
"""Town -> fewer driving lanes than this would be wrong (Town02 has 88)."""
SUCCESSOR_CONNECTED = {"Town01", "Town02", "Town07", "Town10HD"}
"""Towns whose successor graph alone is mostly strongly connected; the Town04 / Town06 highways are
rings of parallel lanes that meet only through lane changes."""


def _scc_fraction(net: LaneNetwork, *, lane_changes: bool) -> float:
    g = nx.DiGraph()
    for lane in net.lanes.values():
        g.add_node(lane.lane_id)
        g.add_edges_from((lane.lane_id, s) for s in lane.successors)
    if lane_changes:  # adjacent same-side lanes of one section (both ways)
        for lid in net.lanes:
            if lid.endswith(".rev"):
                continue
            head, k = lid.rsplit(".", 1)
            nb = f"{head}.{int(k) + (1 if int(k) > 0 else -1)}"
            if nb in net.lanes:
                g.add_edge(lid, nb)
                g.add_edge(nb, lid)
    return len(max(nx.strongly_connected_components(g), key=len)) / g.number_of_nodes()


@pytest.mark.skipif(not (MAPS / "carla").is_dir(), reason="shared CARLA maps not available")
@pytest.mark.parametrize("town", sorted(TOWNS))
def test_carla_towns_load_connected(town):
    """How fast they load is a benchmark figure, not a test: bench/bench_world.py, the lane network of the
    largest against parsing its XML (``make bench``)."""
    net = load_lane_network(MAPS / "carla" / f"{town}.xodr")
    assert len(net.lanes) > TOWNS[town]
    assert all(_spacing(lane.centre_m).max() <= 0.6 for lane in net.lanes.values())
    assert _scc_fraction(net, lane_changes=True) > 0.8
    if town in SUCCESSOR_CONNECTED:
        assert _scc_fraction(net, lane_changes=False) > 0.8


@pytest.mark.skipif(not (MAPS / "opendrive-samples").is_dir(), reason="shared OpenDRIVE samples not available")
def test_odd_samples_load_or_raise_open_drive_error():
    for path in sorted((MAPS / "opendrive-samples").glob("*.xodr")):
        try:
            net = load_lane_network(path)
        except OpenDriveError as exc:
            assert str(exc).startswith(path.name)
            continue
        assert net.lanes
        assert all(w.startswith(f"{path.name}: ") for w in net.warnings)
