"""Look-alikes of hard episodes: the cue each one differs in, and the pairs a viewer can tell apart.

A look-alike differs from its target in exactly one cue (its *kind*):

* ``type``: the target's paint and attributes on another body type;
* ``paint``: the target's body type and attributes in a near paint (:data:`NEAR_COLOURS`);
* ``attribute``: the target's body type and paint with one attribute added or taken away
  (a roof in a contrasting colour, a roof rack or a stripe; the rich look only).

The flat look keeps the vocabulary and the draws it always had (six box types, ``type`` and
``paint`` look-alikes, every pair), so its episodes stay what they were for a seed. The rich look
samples a pair as a look-alike only where :data:`CUE_GROUND_PCT` says a viewer can tell the two
apart from the ground at confirmation distance (at least :data:`MIN_CUE_PCT`): the table is what
``bench/bench_cues.py`` measured and prints, pasted here; a pair missing from it is never sampled.
Change it only with a new bench run (meshes, attributes or the ground camera changed).
"""

from __future__ import annotations

from itertools import combinations

from agos.world.towns.catalog import BODY_TYPES, NEAR_COLOURS
from agos.world.towns.look.vehicles import RICH_BODY_TYPES

LookalikeKind = str
KINDS: tuple[LookalikeKind, ...] = ("type", "paint", "attribute")
ATTRIBUTES: tuple[str, ...] = ("roof", "rack", "stripe")
"""Checkable attributes (:class:`~agos.world.towns.look.vehicles.VehicleAttributes`); ``plain`` names a
vehicle without them in the pairs below."""
PLAIN = "plain"
MIN_CUE_PCT = 90.0
"""Ground accuracy a pair needs to be sampled as a look-alike (issue 22, item 8)."""

# rich look, ground 256 px, 300 crops a class, seed 1 (bench/bench_cues.py); pairs below 90 are not sampled
CUE_GROUND_PCT: dict[tuple[LookalikeKind, str, str], float] = {
    ('attribute', 'plain', 'rack'): 98.2,
    ('attribute', 'plain', 'roof'): 85.8,
    ('attribute', 'plain', 'stripe'): 92.5,
    ('paint', 'blue', 'navy'): 91.5,
    ('paint', 'green', 'olive'): 96.2,
    ('paint', 'maroon', 'red'): 94.2,
    ('paint', 'orange', 'red'): 95.8,
    ('paint', 'orange', 'yellow'): 98.8,
    ('type', 'box_truck', 'bus'): 99.0,
    ('type', 'box_truck', 'hatchback'): 99.7,
    ('type', 'box_truck', 'pickup'): 100.0,
    ('type', 'box_truck', 'sedan'): 100.0,
    ('type', 'box_truck', 'suv'): 100.0,
    ('type', 'box_truck', 'van'): 99.5,
    ('type', 'bus', 'hatchback'): 100.0,
    ('type', 'bus', 'pickup'): 99.8,
    ('type', 'bus', 'sedan'): 100.0,
    ('type', 'bus', 'suv'): 100.0,
    ('type', 'bus', 'van'): 98.7,
    ('type', 'hatchback', 'pickup'): 96.3,
    ('type', 'hatchback', 'sedan'): 92.2,
    ('type', 'hatchback', 'suv'): 94.7,
    ('type', 'hatchback', 'van'): 98.2,
    ('type', 'pickup', 'sedan'): 97.2,
    ('type', 'pickup', 'suv'): 86.8,
    ('type', 'pickup', 'van'): 99.2,
    ('type', 'sedan', 'suv'): 97.2,
    ('type', 'sedan', 'van'): 99.7,
    ('type', 'suv', 'van'): 98.8,
}
"""(kind, a, b) with a < b -> % of ground crops told apart (rich look, bench/bench_cues.py, the command
in its docstring). Below the floor at 256 px: pickup vs SUV (end on, the two share a silhouette) and
the two-tone roof (a car's roof is at or above the ground camera); 384 px does not lift them to 90."""


def _pair(a: str, b: str) -> tuple[str, str]:
    return (a, b) if a <= b else (b, a)


def pair_key(kind: LookalikeKind, a: str, b: str) -> tuple[LookalikeKind, str, str]:
    """The table key of an unordered pair."""
    return (kind, *_pair(a, b))


def pairs(look: str) -> dict[LookalikeKind, list[tuple[str, str]]]:
    """Every pair of each kind the look can draw (the bench measures these), a < b."""
    types = RICH_BODY_TYPES if look == "rich" else tuple(BODY_TYPES)
    out: dict[LookalikeKind, list[tuple[str, str]]] = {
        "type": list(combinations(sorted(types), 2)),
        "paint": sorted({_pair(a, b) for a, bs in NEAR_COLOURS.items() for b in bs}),
    }
    if look == "rich":
        out["attribute"] = [(PLAIN, name) for name in ATTRIBUTES]
    return out


def separable(kind: LookalikeKind, a: str, b: str, *, look: str) -> bool:
    """Whether the sampler may use ``b`` as a look-alike of ``a`` in ``look``: always in the flat
    look (today's episodes), in the rich look only at :data:`MIN_CUE_PCT` or more in the table."""
    if look != "rich":
        return True
    return CUE_GROUND_PCT.get(pair_key(kind, a, b), 0.0) >= MIN_CUE_PCT
