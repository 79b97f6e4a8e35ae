"""OpenDRIVE (.xodr) importer: an ASAM OpenDRIVE road description as a :class:`LaneNetwork`.

:func:`load_lane_network` reads the plan view (line, arc, spiral, poly3 and paramPoly3 reference
line geometries), lane offsets, lane sections and lane widths (``<width>``, or ``<border>`` read as
the t coordinate of the lane's outer edge), and the lane-, road- and junction-level links, and turns
every ``driving`` lane (and both directions of every ``bidirectional`` lane) of every lane section
into one :class:`~agos.world.towns.lanes.Lane`:

* the centre line is sampled at most ``step_m`` apart (along the lane itself, denser on the outside
  of tight curves), section ends included, first to last in the direction of travel: right lanes
  (negative ids) along increasing s and left lanes along decreasing s, swapped for ``rule="LHT"``;
* lane ids are ``r{road}.s{section}.{lane}`` (``.rev`` appended for the second direction of a
  bidirectional lane), ``section`` being the section's index in the road's ``<lanes>`` sorted by s;
* successors follow the links in the direction of travel, within a road and across road and
  junction links (``contactPoint`` flips handled by joining lane ends and letting each lane's
  direction decide who continues into whom);
* ``in_junction`` is set for roads inside a junction, ``parking_offset_m`` for the outermost driving
  lane of a side next to a wide (>= 2 m) parking / shoulder / border / stop lane, signed: positive to
  the right of the direction of travel (negative for left-hand traffic).

Everything skipped or repaired (tiny geometries, unsupported geometry types, zero-width lanes,
links to missing roads or lanes, ...) is recorded in ``LaneNetwork.warnings`` as
``"FILE: road ID: reason"``; a road that cannot be read at all is skipped with such a warning. A
file that is not XML, has no ``<OpenDRIVE>`` root or yields no driving lane raises
:class:`OpenDriveError`.
"""

from __future__ import annotations

import copy
import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from agos.world.towns.lanes import Lane, LaneNetwork

DEFAULT_WIDTH_M = 3.5
"""Width used for a lane that has neither usable ``<width>`` nor ``<border>`` records."""
MIN_GEOMETRY_M = 1e-3
"""Plan-view geometries shorter than this are skipped (the next one starts from its own x, y, hdg)."""
MIN_SECTION_M = 1e-3
"""Lane sections shorter than this are skipped; the links through them are bridged."""
PARKING_LANE_TYPES = frozenset({"parking", "shoulder", "border", "stop"})
PARKING_MIN_WIDTH_M = 2.0
PARKING_MARGIN_M = 1.2
DRIVING_TYPES = frozenset({"driving", "bidirectional"})
MAX_GEOMETRY_M = 1e6
"""A plan view (or one geometry) longer than 1000 km is taken for a corrupt number (the road is skipped)."""
SUSPECT_CURVATURE = 1.0
"""A geometry turning tighter than a 1 m radius is kept but reported."""

_GL_X, _GL_W = np.polynomial.legendre.leggauss(6)
_MAX_INTERVALS = 200_000


class OpenDriveError(ValueError):
    """An OpenDRIVE file that cannot be turned into a lane network (the message names the file)."""


class _RoadProblem(Exception):
    """A problem that makes one road unusable; it is skipped with a warning."""


# ---------------------------------------------------------------------------------------------
# numeric helpers


def _cumulative_integral(fn, targets: np.ndarray, max_step: float) -> np.ndarray:
    """Integral of ``fn`` from 0 to each of ``targets`` (all >= 0), by Gauss-Legendre on a fine grid."""
    tmax = float(targets.max()) if targets.size else 0.0
    if tmax <= 0.0:
        return np.zeros(targets.shape, dtype=complex)
    n = max(1, math.ceil(min(tmax / max_step, _MAX_INTERVALS)))
    grid = np.union1d(np.concatenate(([0.0], targets)), np.linspace(0.0, tmax, n + 1))
    a, b = grid[:-1], grid[1:]
    half = (b - a) / 2
    nodes = ((a + b) / 2)[:, None] + half[:, None] * _GL_X[None, :]
    pieces = (fn(nodes) @ _GL_W) * half
    cum = np.concatenate(([0.0], np.cumsum(pieces)))
    return cum[np.searchsorted(grid, targets)]


def _arc_length_table(speed, p_max: float, length_hint: float) -> tuple[np.ndarray, np.ndarray]:
    """Grid of parameter values on [0, p_max] and the arc length from 0 to each."""
    n = min(_MAX_INTERVALS, max(64, math.ceil(length_hint / 0.05)))
    grid = np.linspace(0.0, p_max, n + 1)
    a, b = grid[:-1], grid[1:]
    half = (b - a) / 2
    nodes = ((a + b) / 2)[:, None] + half[:, None] * _GL_X[None, :]
    pieces = (speed(nodes) @ _GL_W) * half
    return grid, np.concatenate(([0.0], np.cumsum(pieces)))


class _Piecewise:
    """A piecewise cubic in s: record k applies from ``starts[k]``, in ``ds = s - starts[k]``."""

    def __init__(self, starts: list[float], coefs: list[tuple[float, float, float, float]]):
        order = np.argsort(np.asarray(starts, dtype=float), kind="stable")
        self.starts = np.asarray(starts, dtype=float)[order]
        self.coefs = np.asarray(coefs, dtype=float).reshape(-1, 4)[order]

    def __call__(self, s: np.ndarray, *, closing: bool = False) -> np.ndarray:
        """Values at ``s``; with ``closing`` the last station takes the record in force just before it
        (a record that starts exactly at a section's end belongs to what follows)."""
        idx = np.searchsorted(self.starts, s, side="right") - 1
        if closing and len(s) > 1:
            idx[-1] = np.searchsorted(self.starts, s[-1], side="left") - 1
        idx = np.clip(idx, 0, len(self.starts) - 1)
        t = np.maximum(s - self.starts[idx], 0.0)
        c = self.coefs[idx]
        return c[:, 0] + t * (c[:, 1] + t * (c[:, 2] + t * c[:, 3]))

    def all_zero(self) -> bool:
        return bool(np.all(self.coefs == 0.0))


# ---------------------------------------------------------------------------------------------
# reference line


@dataclass
class _Geometry:
    s0: float
    x: float
    y: float
    hdg: float
    length: float
    kind: str
    p: dict[str, float]
    _table: tuple[np.ndarray, np.ndarray] | None = None

    def local(self, ds: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Position (u along the start heading, v to its left) and heading change at ``ds``."""
        if self.kind == "line":
            return ds, np.zeros_like(ds), np.zeros_like(ds)
        if self.kind == "arc":
            k = self.p["curvature"]
            if abs(k) < 1e-12:
                return ds, np.zeros_like(ds), np.zeros_like(ds)
            th = k * ds
            return np.sin(th) / k, (1.0 - np.cos(th)) / k, th
        if self.kind == "spiral":
            k0 = self.p["curvStart"]
            c = (self.p["curvEnd"] - k0) / self.length
            kmax = max(abs(k0), abs(self.p["curvEnd"]), 1e-9)
            z = _cumulative_integral(lambda t: np.exp(1j * (k0 * t + 0.5 * c * t * t)), ds, min(2.0, 0.5 / kmax))
            return z.real, z.imag, k0 * ds + 0.5 * c * ds * ds
        if self.kind == "poly3":
            a, b, c, d = (self.p[k] for k in "abcd")
            if self._table is None:
                self._table = _arc_length_table(lambda u: np.sqrt(1.0 + (b + u * (2 * c + 3 * d * u)) ** 2),
                                                self.length, self.length)
            grid, arc = self._table
            u = np.interp(ds, arc, grid)
            v = a + u * (b + u * (c + u * d))
            return u, v, np.arctan(b + u * (2 * c + 3 * d * u))
        # paramPoly3, reparametrised by arc length (exactly p = ds or ds / length for a well-formed file)
        au, bu, cu, du = (self.p[k] for k in ("aU", "bU", "cU", "dU"))
        av, bv, cv, dv = (self.p[k] for k in ("aV", "bV", "cV", "dV"))
        p_max = self.length if self.p["arcLength"] else 1.0
        if self._table is None:
            self._table = _arc_length_table(
                lambda q: np.hypot(bu + q * (2 * cu + 3 * du * q), bv + q * (2 * cv + 3 * dv * q)), p_max, self.length)
        grid, arc = self._table
        total = arc[-1]
        q = np.interp(ds / self.length * total, arc, grid) if total > 1e-12 else np.zeros_like(ds)
        u = au + q * (bu + q * (cu + q * du))
        v = av + q * (bv + q * (cv + q * dv))
        th = np.arctan2(bv + q * (2 * cv + 3 * dv * q), bu + q * (2 * cu + 3 * du * q))
        return u, v, th

    def evaluate(self, ds: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        u, v, th = self.local(np.clip(ds, 0.0, self.length))
        ch, sh = math.cos(self.hdg), math.sin(self.hdg)
        return self.x + u * ch - v * sh, self.y + u * sh + v * ch, self.hdg + th


class ReferenceLine:
    """A road's plan view: x, y and heading at any s (geometries clamped to their own extent)."""

    def __init__(self, geometries: list[_Geometry]):
        if not geometries:
            raise ValueError("no geometry")
        self.geometries = geometries
        self.starts = np.array([g.s0 for g in geometries])
        self.length = geometries[-1].s0 + geometries[-1].length

    def evaluate(self, s, *, closing: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """x, y, heading at ``s``; with ``closing`` the last station is evaluated on the geometry ending there."""
        s = np.atleast_1d(np.asarray(s, dtype=float))
        idx = np.searchsorted(self.starts, s, side="right") - 1
        if closing and len(s) > 1:
            idx[-1] = np.searchsorted(self.starts, s[-1], side="left") - 1
        idx = np.clip(idx, 0, len(self.geometries) - 1)
        x, y, h = np.empty_like(s), np.empty_like(s), np.empty_like(s)
        for k in np.unique(idx):
            m = idx == k
            g = self.geometries[k]
            x[m], y[m], h[m] = g.evaluate(s[m] - g.s0)
        return x, y, h


# ---------------------------------------------------------------------------------------------
# parsed road model


@dataclass
class _LaneDef:
    lane_id: int
    kind: str
    width: _Piecewise | None
    border: _Piecewise | None
    succ: list[int]
    pred: list[int]


@dataclass
class _Section:
    index: int
    s0: float
    s1: float
    lanes: dict[int, _LaneDef]


@dataclass
class _Link:
    element_type: str
    element_id: str
    contact: str | None


@dataclass
class _Road:
    road_id: str
    junction: str
    lht: bool
    ref: ReferenceLine
    offset: _Piecewise | None
    sections: list[_Section]
    links: dict[str, _Link] = field(default_factory=dict)

    @property
    def in_junction(self) -> bool:
        return self.junction not in ("", "-1")

    def end_section(self, end: str) -> _Section:
        return self.sections[0] if end == "start" else self.sections[-1]

    def end_point(self, end: str) -> np.ndarray:
        x, y, _ = self.ref.evaluate(0.0 if end == "start" else self.ref.length)
        return np.array([x[0], y[0]])


def _strip_namespaces(root: ET.Element) -> None:
    for el in root.iter():
        if isinstance(el.tag, str) and "}" in el.tag:
            el.tag = el.tag.rsplit("}", 1)[1]


def _num(el: ET.Element, name: str, default: float | None = None) -> float:
    raw = el.get(name)
    if raw is None:
        if default is None:
            raise _RoadProblem(f"<{el.tag}> lacks attribute '{name}'")
        return default
    try:
        value = float(raw)
    except ValueError:
        raise _RoadProblem(f"<{el.tag}> attribute {name}={raw!r} is not a number") from None
    if not math.isfinite(value):
        raise _RoadProblem(f"<{el.tag}> attribute {name}={raw!r} is not finite")
    return value


def _cubic(el: ET.Element) -> tuple[float, float, float, float]:
    return (_num(el, "a", 0.0), _num(el, "b", 0.0), _num(el, "c", 0.0), _num(el, "d", 0.0))


_GEOMETRY_PARAMS = {
    "line": (),
    "arc": ("curvature",),
    "spiral": ("curvStart", "curvEnd"),
    "poly3": ("a", "b", "c", "d"),
    "paramPoly3": ("aU", "bU", "cU", "dU", "aV", "bV", "cV", "dV"),
}


class _Loader:
    def __init__(self, path: Path, step_m: float):
        self.path = path
        self.name = path.name
        self.step_m = step_m
        self.warnings: list[str] = []
        self.roads: dict[str, _Road] = {}
        self.lane_types: dict[tuple[str, int, int], str] = {}
        """(road, section index, lane id) -> lane type, for every lane of every kept section."""
        self.emitted: dict[tuple[str, int, int], list[tuple[Lane, int]]] = {}
        """(road, section index, lane id) -> the Lanes made from it and their direction (+1: along s)."""
        self.skipped_driving: set[tuple[str, int, int]] = set()

    def warn(self, where: str, reason: str) -> None:
        self.warnings.append(f"{self.name}: {where}: {reason}")

    def fail(self, reason: str) -> OpenDriveError:
        return OpenDriveError(f"{self.name}: {reason}")

    # -- parsing ------------------------------------------------------------------------------

    def load(self) -> LaneNetwork:
        try:
            root = ET.parse(self.path).getroot()
        except ET.ParseError as exc:
            raise self.fail(f"not a valid XML file ({exc})") from None
        except OSError as exc:
            raise self.fail(f"cannot read file ({exc.strerror or exc})") from None
        _strip_namespaces(root)
        if root.tag != "OpenDRIVE":
            raise self.fail(f"root element is <{root.tag}>, expected <OpenDRIVE>")
        for el in root.findall("road"):
            rid = el.get("id")
            where = f"road {rid}" if rid is not None else "road ?"
            if rid is None:
                self.warn(where, "road without id skipped")
                continue
            if rid in self.roads:
                self.warn(where, "duplicate road id, later definition skipped")
                continue
            try:
                self.roads[rid] = self.parse_road(el, rid)
            except _RoadProblem as exc:
                self.warn(where, f"{exc}; road skipped")
        with np.errstate(all="ignore"):  # overflow from absurd coefficients is caught as non-finite output
            lanes = self.build_lanes()
        if not lanes:
            hint = "; ".join(w.split(": ", 1)[1] for w in self.warnings[:3])
            raise self.fail("no driving lane found" + (f" ({hint})" if hint else ""))
        joins = self.collect_joins(root)
        self.resolve_joins(joins)
        network = LaneNetwork(lanes, self.warnings)
        try:
            network.check()
        except ValueError as exc:  # an importer bug rather than a file problem, but name the file
            raise self.fail(f"inconsistent lane network: {exc}") from exc
        return network

    def parse_road(self, el: ET.Element, rid: str) -> _Road:
        where = f"road {rid}"
        ref = self.parse_plan_view(el, where)
        stated = el.get("length")
        try:
            stated_len = float(stated) if stated is not None else None
        except ValueError:
            stated_len = None
        if stated_len is None or not math.isfinite(stated_len):
            self.warn(where, f"road length {stated!r} unreadable, using the plan view length {ref.length:.3f} m")
        elif abs(stated_len - ref.length) > max(0.01, 1e-4 * ref.length):
            self.warn(where, f"road length {stated_len:g} m differs from the plan view length {ref.length:.3f} m; "
                             "using the plan view")
        lanes_el = el.find("lanes")
        if lanes_el is None:
            raise _RoadProblem("no <lanes>")
        offsets = lanes_el.findall("laneOffset")
        offset = None
        if offsets:
            offset = _Piecewise([_num(o, "s") for o in offsets], [_cubic(o) for o in offsets])
            if offset.all_zero():
                offset = None
        sections = self.parse_sections(lanes_el, ref.length, where)
        rule = (el.get("rule") or "RHT").strip().upper()
        road = _Road(rid, (el.get("junction") or "-1").strip(), rule == "LHT", ref, offset, sections)
        link = el.find("link")
        if link is not None:
            for kind in ("predecessor", "successor"):
                target = link.find(kind)
                if target is None:
                    continue
                etype = (target.get("elementType") or "road").strip().lower()
                eid = target.get("elementId")
                if eid is None:
                    self.warn(where, f"{kind} link without elementId ignored")
                    continue
                contact = target.get("contactPoint")
                road.links[kind] = _Link(etype, eid.strip(), contact.strip().lower() if contact else None)
        return road

    def parse_plan_view(self, el: ET.Element, where: str) -> ReferenceLine:
        pv = el.find("planView")
        if pv is None:
            raise _RoadProblem("no <planView>")
        geoms: list[_Geometry] = []
        for g in pv.findall("geometry"):
            s0, length = _num(g, "s"), _num(g, "length")
            kinds = [c for c in g if c.tag in _GEOMETRY_PARAMS]
            if not kinds:
                other = [c.tag for c in g if isinstance(c.tag, str)]
                raise _RoadProblem(f"geometry type {other[0]!r} not supported" if other else f"empty geometry at s={s0:g}")
            shape = kinds[0]
            if length > MAX_GEOMETRY_M:
                raise _RoadProblem(f"geometry at s={s0:g} has implausible length {length:g} m")
            if length < MIN_GEOMETRY_M:
                self.warn(where, f"{shape.tag} geometry at s={s0:g} of length {length:.3g} m skipped")
                continue
            params = {k: _num(shape, k, 0.0 if shape.tag != "arc" else None) for k in _GEOMETRY_PARAMS[shape.tag]}
            if shape.tag == "paramPoly3":
                prange = (shape.get("pRange") or "").strip().lower()
                if not prange:
                    self.warn(where, f"paramPoly3 at s={s0:g} without pRange, assuming 'normalized'")
                elif prange not in ("arclength", "normalized", "normal"):
                    self.warn(where, f"paramPoly3 at s={s0:g} has pRange={prange!r}, assuming 'normalized'")
                params["arcLength"] = 1.0 if prange == "arclength" else 0.0
            kmax = max((abs(params[k]) for k in ("curvature", "curvStart", "curvEnd") if k in params), default=0.0)
            if kmax > SUSPECT_CURVATURE:
                self.warn(where, f"{shape.tag} geometry at s={s0:g} (length {length:.3g} m) has curvature up to "
                                 f"{kmax:g} 1/m (radius {1 / kmax:.3g} m); kept")
            geoms.append(_Geometry(s0, _num(g, "x"), _num(g, "y"), _num(g, "hdg"), length, shape.tag, params))
        if not geoms:
            raise _RoadProblem("no usable plan view geometry")
        order = np.argsort([g.s0 for g in geoms], kind="stable")
        if np.any(order != np.arange(len(geoms))):
            self.warn(where, "plan view geometries not sorted by s; sorted")
            geoms = [geoms[i] for i in order]
        for a, b in zip(geoms, geoms[1:], strict=False):
            gap = b.s0 - (a.s0 + a.length)
            if abs(gap) > 0.01:
                self.warn(where, f"plan view s {'gap' if gap > 0 else 'overlap'} of {abs(gap):.3g} m at s={b.s0:g}")
        ref = ReferenceLine(geoms)
        if ref.length > MAX_GEOMETRY_M:
            raise _RoadProblem(f"plan view ends at implausible s={ref.length:g} m")
        return ref

    def parse_lane(self, lane_el: ET.Element, section_s0: float, where: str) -> _LaneDef | None:
        try:
            lid = int(lane_el.get("id", ""))
        except ValueError:
            self.warn(where, f"lane with id {lane_el.get('id')!r} skipped")
            return None
        kind = (lane_el.get("type") or "none").strip()
        widths = lane_el.findall("width")
        borders = lane_el.findall("border")
        width = _Piecewise([section_s0 + _num(w, "sOffset", 0.0) for w in widths], [_cubic(w) for w in widths]) \
            if widths else None
        border = _Piecewise([section_s0 + _num(b, "sOffset", 0.0) for b in borders], [_cubic(b) for b in borders]) \
            if borders and not widths else None
        succ: list[int] = []
        pred: list[int] = []
        link = lane_el.find("link")
        if link is not None:
            for tag, into in (("successor", succ), ("predecessor", pred)):
                for t in link.findall(tag):
                    try:
                        into.append(int(t.get("id", "")))
                    except ValueError:
                        self.warn(where, f"lane {lid}: {tag} link with id {t.get('id')!r} ignored")
        return _LaneDef(lid, kind, width, border, succ, pred)

    def parse_sections(self, lanes_el: ET.Element, road_len: float, where: str) -> list[_Section]:
        raw = lanes_el.findall("laneSection")
        if not raw:
            raise _RoadProblem("no <laneSection>")
        starts = [_num(sec, "s") for sec in raw]
        order = list(np.argsort(starts, kind="stable"))
        if order != list(range(len(raw))):
            self.warn(where, "lane sections not sorted by s; sorted")
        sections: list[_Section] = []
        prev: _Section | None = None
        for pos, k in enumerate(order):
            el = raw[k]
            s0 = min(max(starts[k], 0.0), road_len)
            s1 = road_len if pos == len(order) - 1 else min(max(starts[order[pos + 1]], 0.0), road_len)
            lanes: dict[int, _LaneDef] = {}
            present = set()
            for side_name, sign in (("left", 1), ("right", -1)):
                side = el.find(side_name)
                if side is None:
                    continue
                present.add(sign)
                for lane_el in side.findall("lane"):
                    lane = self.parse_lane(lane_el, s0, f"{where}: section {pos}")
                    if lane is None:
                        continue
                    if lane.lane_id == 0 or (lane.lane_id > 0) != (sign > 0):
                        self.warn(where, f"section {pos}: lane {lane.lane_id} listed under <{side_name}> skipped")
                        continue
                    if lane.lane_id in lanes:
                        self.warn(where, f"section {pos}: duplicate lane {lane.lane_id} skipped")
                        continue
                    lanes[lane.lane_id] = lane
            single = (el.get("singleSide") or "false").strip().lower() == "true"
            if single and prev is not None:
                for sign in (1, -1):
                    if sign in present:
                        continue
                    for lid, old in prev.lanes.items():
                        if (lid > 0) == (sign > 0):
                            inherited = copy.deepcopy(old)
                            inherited.pred, inherited.succ = [lid], []
                            if not old.succ:
                                old.succ = [lid]
                            lanes[lid] = inherited
            section = _Section(pos, s0, s1, lanes)
            sections.append(section)
            prev = section
        return self.drop_short_sections(sections, where)

    def drop_short_sections(self, sections: list[_Section], where: str) -> list[_Section]:
        kept: list[_Section] = []
        for i, sec in enumerate(sections):
            if sec.s1 - sec.s0 >= MIN_SECTION_M:
                kept.append(sec)
                continue
            self.warn(where, f"lane section {sec.index} at s={sec.s0:g} is {sec.s1 - sec.s0:.3g} m long; skipped, "
                             "links through it bridged")
            before = kept[-1] if kept else None
            after = sections[i + 1] if i + 1 < len(sections) else None
            if after is not None:
                for lane in after.lanes.values():
                    lane.pred = list(dict.fromkeys(p for m in lane.pred if m in sec.lanes for p in sec.lanes[m].pred))
            if before is not None:
                for lane in before.lanes.values():
                    lane.succ = list(dict.fromkeys(q for m in lane.succ if m in sec.lanes for q in sec.lanes[m].succ))
        if not kept:
            raise _RoadProblem("no lane section of positive length")
        return kept

    # -- lanes --------------------------------------------------------------------------------

    def section_profile(self, road: _Road, sec: _Section, s: np.ndarray, where: str, report: bool
                        ) -> tuple[dict[int, np.ndarray], dict[int, np.ndarray]]:
        """Width and centre t of every lane of a section at the stations ``s``."""
        base = road.offset(s, closing=True) if road.offset is not None else np.zeros_like(s)
        widths: dict[int, np.ndarray] = {}
        centres: dict[int, np.ndarray] = {}
        for sign in (1, -1):
            inner = base
            for lid in sorted((i for i in sec.lanes if (i > 0) == (sign > 0)), key=abs):
                lane = sec.lanes[lid]
                if lane.width is not None:
                    w = lane.width(s, closing=True)
                elif lane.border is not None:
                    w = sign * (lane.border(s, closing=True) - inner)
                else:
                    if report:
                        self.warn(where, f"section {sec.index}: lane {lid} ({lane.kind}) has no width, using "
                                         f"{DEFAULT_WIDTH_M} m")
                    w = np.full_like(s, DEFAULT_WIDTH_M)
                if np.any(w < -1e-6):
                    if report:
                        self.warn(where, f"section {sec.index}: lane {lid} has negative width (down to {w.min():.3g} m); "
                                         "clipped to 0")
                    w = np.maximum(w, 0.0)
                widths[lid] = w
                centres[lid] = inner + sign * w / 2
                inner = inner + sign * w
        return widths, centres

    def build_lanes(self) -> dict[str, Lane]:
        lanes: dict[str, Lane] = {}
        for road in self.roads.values():
            where = f"road {road.road_id}"
            for sec in road.sections:
                for lid, lane in sec.lanes.items():
                    self.lane_types[(road.road_id, sec.index, lid)] = lane.kind.lower()
                driving = [lid for lid, lane in sec.lanes.items() if lane.kind.lower() in DRIVING_TYPES]
                for lid in driving:
                    lane = sec.lanes[lid]
                    if lane.width is not None and lane.width.all_zero():
                        self.warn(where, f"section {sec.index}: driving lane {lid} has zero width; skipped")
                        self.skipped_driving.add((road.road_id, sec.index, lid))
                driving = [lid for lid in driving if (road.road_id, sec.index, lid) not in self.skipped_driving]
                if not driving:
                    continue
                self.build_section(road, sec, driving, lanes, where)
        return lanes

    def build_section(self, road: _Road, sec: _Section, driving: list[int], lanes: dict[str, Lane], where: str) -> None:
        n = max(2, math.ceil((sec.s1 - sec.s0) / self.step_m - 1e-9) + 1)
        previous = math.inf
        for attempt in range(4):
            s = np.linspace(sec.s0, sec.s1, n)
            x, y, h = road.ref.evaluate(s, closing=True)
            widths, centres = self.section_profile(road, sec, s, where, report=attempt == 0)
            nx_, ny_ = -np.sin(h), np.cos(h)
            points = {lid: np.stack([x + centres[lid] * nx_, y + centres[lid] * ny_], axis=1) for lid in driving}
            worst = max(float(np.linalg.norm(np.diff(p, axis=0), axis=1).max()) for p in points.values())
            if not math.isfinite(worst) or worst <= self.step_m * 1.001 or attempt == 3 or worst > 0.9 * previous:
                break  # dense enough, or a jump that sampling cannot close
            previous = worst
            n = min(max(n + 1, math.ceil((n - 1) * worst / self.step_m * 1.02) + 1), 8 * n)
        if not all(np.all(np.isfinite(points[lid])) and np.all(np.isfinite(widths[lid])) for lid in driving):
            self.warn(where, f"section {sec.index}: non-finite lane geometry (absurd coefficients); its driving lanes "
                             f"{sorted(driving)} skipped")
            self.skipped_driving.update((road.road_id, sec.index, lid) for lid in driving)
            return
        for lid in driving:
            w = widths[lid]
            if np.any(w <= 1e-6):
                share = float(np.mean(w <= 1e-6))
                self.warn(where, f"section {sec.index}: driving lane {lid} has zero width over {share:.0%} of its "
                                 "length; kept")
            sign = 1 if lid > 0 else -1
            forward = -1 if sign > 0 else 1
            if road.lht:
                forward = -forward
            directions = [forward]
            if sec.lanes[lid].kind.lower() == "bidirectional":
                directions.append(-forward)
            parking = self.parking_offset(road, sec, lid, widths)
            for k, direction in enumerate(directions):
                lane_id = f"r{road.road_id}.s{sec.index}.{lid}" + (".rev" if k == 1 else "")
                pts, wid = (points[lid], w) if direction > 0 else (points[lid][::-1], w[::-1])
                offset = None
                if parking is not None:
                    offset = parking if sign * direction < 0 else -parking
                lanes[lane_id] = Lane(lane_id, np.ascontiguousarray(pts), np.ascontiguousarray(wid), [],
                                      road.in_junction, road.road_id, offset)
                self.emitted.setdefault((road.road_id, sec.index, lid), []).append((lanes[lane_id], direction))
        if not road.in_junction:  # same-direction neighbours on this section allow lane changes
            for lid in sorted(driving):
                for neighbour in (lid - 1, lid + 1):
                    if neighbour in driving and neighbour != 0 and (neighbour > 0) == (lid > 0):
                        lanes[f"r{road.road_id}.s{sec.index}.{lid}"].lane_changes.append(
                            f"r{road.road_id}.s{sec.index}.{neighbour}")

    def parking_offset(self, road: _Road, sec: _Section, lid: int, widths: dict[int, np.ndarray]) -> float | None:
        """Offset of a parking row beside the outermost driving lane of a side (unsigned), or None."""
        if road.in_junction:
            return None
        sign = 1 if lid > 0 else -1
        for other, lane in sec.lanes.items():
            if (other > 0) == (sign > 0) and abs(other) > abs(lid) and lane.kind.lower() in DRIVING_TYPES \
                    and (road.road_id, sec.index, other) not in self.skipped_driving:
                return None
        outer = sec.lanes.get(lid + sign)
        if outer is None or outer.kind.lower() not in PARKING_LANE_TYPES:
            return None
        if float(np.median(widths[lid + sign])) < PARKING_MIN_WIDTH_M:
            return None
        return float(np.median(widths[lid])) / 2 + PARKING_MARGIN_M

    # -- links --------------------------------------------------------------------------------

    def contact_of(self, road: _Road, kind: str, link: _Link, other: _Road) -> str:
        if link.contact in ("start", "end"):
            return link.contact
        mine = road.end_point("start" if kind == "predecessor" else "end")
        guess = min(("start", "end"), key=lambda e: float(np.linalg.norm(other.end_point(e) - mine)))
        self.warn(f"road {road.road_id}", f"{kind} link to road {other.road_id} has contactPoint "
                                          f"{link.contact!r}; inferred {guess!r} from the geometry")
        return guess

    def collect_joins(self, root: ET.Element) -> dict[tuple, str]:
        """Pairs of lane ends (road, section, lane, 'start'|'end') that touch, each with the road to name."""
        joins: dict[tuple, str] = {}
        junction_ids = {(j.get("id") or "").strip() for j in root.findall("junction")}

        def join(a: tuple, b: tuple, where: str) -> None:
            key = (a, b) if a <= b else (b, a)
            joins.setdefault(key, where)

        for road in self.roads.values():
            rid = road.road_id
            secs = road.sections
            for i, sec in enumerate(secs):
                for lid, lane in sec.lanes.items():
                    if i + 1 < len(secs):
                        for m in lane.succ:
                            join((rid, sec.index, lid, "end"), (rid, secs[i + 1].index, m, "start"), f"road {rid}")
                    if i > 0:
                        for m in lane.pred:
                            join((rid, sec.index, lid, "start"), (rid, secs[i - 1].index, m, "end"), f"road {rid}")
            for kind, end in (("predecessor", "start"), ("successor", "end")):
                sec = road.end_section(end)
                lane_ids = {lid: (lane.pred if kind == "predecessor" else lane.succ) for lid, lane in sec.lanes.items()}
                link = road.links.get(kind)
                if link is None:
                    dangling = sorted(lid for lid, ids in lane_ids.items() if ids
                                      and sec.lanes[lid].kind.lower() in DRIVING_TYPES)
                    if dangling:
                        self.warn(f"road {rid}", f"lanes {dangling} have {kind} lane links but the road has no "
                                                 f"{kind}; ignored")
                    continue
                if link.element_type != "road":
                    if link.element_type != "junction":
                        self.warn(f"road {rid}", f"{kind} of element type {link.element_type!r} ignored")
                    elif link.element_id not in junction_ids:
                        self.warn(f"road {rid}", f"{kind} junction {link.element_id} does not exist; link dropped")
                    continue
                other = self.roads.get(link.element_id)
                if other is None:
                    self.warn(f"road {rid}", f"{kind} road {link.element_id} does not exist (or was skipped); link dropped")
                    continue
                contact = self.contact_of(road, kind, link, other)
                other_sec = other.end_section(contact)
                for lid, ids in lane_ids.items():
                    for m in ids:
                        join((rid, sec.index, lid, end), (other.road_id, other_sec.index, m, contact), f"road {rid}")
        for junction in root.findall("junction"):
            self.junction_joins(junction, join)
        return joins

    def junction_joins(self, junction: ET.Element, join) -> None:
        jid = (junction.get("id") or "?").strip()
        for conn in junction.findall("connection"):
            inc_id = (conn.get("incomingRoad") or "").strip()
            con_id = (conn.get("connectingRoad") or conn.get("linkedRoad") or "").strip()
            cid = conn.get("id", "?")
            where = f"road {inc_id or '?'}"
            what = f"junction {jid} connection {cid}"
            inc, con = self.roads.get(inc_id), self.roads.get(con_id)
            if inc is None or con is None:
                missing = [r or "(none)" for r, obj in ((inc_id, inc), (con_id, con)) if obj is None]
                self.warn(where, f"{what}: road {', '.join(missing)} does not exist (or was skipped); dropped")
                continue
            links = conn.findall("laneLink")
            if not links:
                self.warn(where, f"{what} to road {con_id} has no laneLink; dropped")
                continue
            contact = (conn.get("contactPoint") or "").strip().lower()
            ends = [end for kind, end in (("predecessor", "start"), ("successor", "end"))
                    if (lk := inc.links.get(kind)) is not None and lk.element_type == "junction" and lk.element_id == jid]
            if contact not in ("start", "end") or len(ends) != 1:
                # ambiguous: take the pair of ends that lie closest together
                cands = [(i, c) for i in (ends or ["start", "end"])
                         for c in ([contact] if contact in ("start", "end") else ["start", "end"])]
                inc_end, contact_new = min(cands, key=lambda p: float(np.linalg.norm(inc.end_point(p[0])
                                                                                      - con.end_point(p[1]))))
                if contact not in ("start", "end") or not ends:
                    self.warn(where, f"{what}: contact points inferred from the geometry (incoming {inc_end}, "
                                     f"connecting road {con_id} {contact_new})")
                contact = contact_new
            else:
                inc_end = ends[0]
            inc_sec, con_sec = inc.end_section(inc_end), con.end_section(contact)
            for ll in links:
                try:
                    a, b = int(ll.get("from", "")), int(ll.get("to", ""))
                except ValueError:
                    self.warn(where, f"{what}: laneLink from={ll.get('from')!r} to={ll.get('to')!r} ignored")
                    continue
                join((inc_id, inc_sec.index, a, inc_end), (con_id, con_sec.index, b, contact), where)

    def resolve_joins(self, joins: dict[tuple, str]) -> None:
        for (a, b), where in joins.items():
            ka, kb = a[:3], b[:3]
            ta, tb = self.lane_types.get(ka), self.lane_types.get(kb)
            da, db = ta in DRIVING_TYPES, tb in DRIVING_TYPES
            if not (da or db):
                continue
            if not (da and db):
                drv, oth, toth = (a, b, tb) if da else (b, a, ta)
                why = f"lane {oth[2]} of road {oth[0]} does not exist" if toth is None \
                    else f"lane {oth[2]} of road {oth[0]} is of type {toth!r}"
                self.warn(where, f"link from driving lane {_lid(drv)} dropped: {why}")
                continue
            la, lb = self.emitted.get(ka, []), self.emitted.get(kb, [])
            if not la or not lb:
                gone = ka if not la else kb
                self.warn(where, f"link between {_lid(a)} and {_lid(b)} dropped: lane {_lid(gone)} was skipped")
                continue
            made = False
            for lane_a, dir_a in la:
                for lane_b, dir_b in lb:
                    if _exits(dir_a, a[3]) and not _exits(dir_b, b[3]):
                        _add(lane_a, lane_b)
                        made = True
                    if _exits(dir_b, b[3]) and not _exits(dir_a, a[3]):
                        _add(lane_b, lane_a)
                        made = True
            if not made:
                self.warn(where, f"link between {_lid(a)} ({a[3]}) and {_lid(b)} ({b[3]}) dropped: "
                                 "their directions of travel conflict")


def _lid(end: tuple) -> str:
    return f"r{end[0]}.s{end[1]}.{end[2]}"


def _exits(direction: int, end: str) -> bool:
    """Whether a lane travelling ``direction`` along s leaves through its ``end``."""
    return (end == "end") == (direction > 0)


def _add(lane: Lane, succ: Lane) -> None:
    if succ.lane_id not in lane.successors:
        lane.successors.append(succ.lane_id)


def load_lane_network(path: Path, *, step_m: float = 0.5) -> LaneNetwork:
    """Read an OpenDRIVE file into a :class:`LaneNetwork` (centre-line points at most ``step_m`` apart).

    Raises :class:`OpenDriveError` for a file that is not XML, has no ``<OpenDRIVE>`` root or has no
    driving lane; everything skipped or repaired on the way is listed in ``network.warnings``.
    """
    if not (step_m > 0 and math.isfinite(step_m)):
        raise ValueError(f"step_m must be a positive number, got {step_m!r}")
    return _Loader(Path(path), float(step_m)).load()
