"""Generated textures of the rich look: façades, shop fronts, roofs, roads, paving, grass, leaves.

Every texture is a tileable RGB image drawn with numpy alone (no downloaded assets, no float
filters whose rounding could differ between machines) from a name and the town's texture seed:
the same (name, seed) gives the same bytes. :func:`texture_file` writes it once to a cache keyed
by the sha256 of its pixels (``loadTexture`` takes a file path only).

Each texture has a physical tile (:data:`TILE_M` for ground-like ones, metres per repeat) or,
for façades, a repeat of ``BAYS_PER_TILE`` window bays by ``STOREYS_PER_TILE`` storeys, so the
meshes set their UVs in world metres or in bays and storeys (UVs above 1 repeat the tile).
"""

from __future__ import annotations

import functools
import hashlib
import os
import zlib
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

Image = np.ndarray
"""(H, W, 3) uint8 RGB, row 0 at the top (v = 1 in UV terms)."""

BAYS_PER_TILE = 4
STOREYS_PER_TILE = 4
SHOP_BAYS_PER_TILE = 3
TILE_M: dict[str, float] = {"asphalt": 5.0, "lot": 6.0, "paving": 2.0, "grass": 5.0, "roof_gravel": 8.0,
                            "roof_membrane": 8.0, "metal": 2.0, "leaves_a": 3.0, "leaves_b": 3.0, "kerb": 1.0}
"""Metres covered by one repeat of each ground-like texture."""
FACADES: tuple[str, ...] = ("brick_red", "brick_brown", "plaster_cream", "plaster_ochre", "glass_blue",
                            "glass_teal", "concrete_ribbon")
"""Façade styles (upper storeys); each has a storey height and a bay width (:data:`FACADE_MODULE_M`)."""
GROUND_FLOORS: tuple[str, ...] = ("shop_a", "shop_b", "lobby")
FACADE_MODULE_M: dict[str, tuple[float, float]] = {
    "brick_red": (3.4, 3.2), "brick_brown": (3.2, 3.1), "plaster_cream": (3.3, 3.2), "plaster_ochre": (3.0, 3.1),
    "glass_blue": (3.0, 3.7), "glass_teal": (3.0, 3.6), "concrete_ribbon": (3.6, 3.5),
    "shop_a": (4.2, 4.5), "shop_b": (4.6, 4.5), "lobby": (4.0, 4.5),
}
"""Style -> (bay width, storey height) in metres; ground floors are one 4.5 m storey."""
ROOF_OF: dict[str, str] = {"brick_red": "roof_gravel", "brick_brown": "roof_gravel", "plaster_cream": "roof_gravel",
                           "plaster_ochre": "roof_gravel", "glass_blue": "roof_membrane", "glass_teal": "roof_membrane",
                           "concrete_ribbon": "roof_membrane"}


# ----- building blocks (integer-exact numpy) ----------------------------------------------------
def _rng(name: str, seed: int) -> np.random.Generator:
    return np.random.default_rng([seed & 0xFFFFFFFF, zlib.crc32(name.encode())])


def _noise(rng: np.random.Generator, h: int, w: int, cells: int, amplitude: float) -> np.ndarray:
    """Tileable value noise: a random ``cells`` x ``cells`` lattice, bilinear between lattice points
    (wrapping), scaled to +-amplitude. Elementwise float64 only, so bit-identical everywhere."""
    lattice = rng.uniform(-1.0, 1.0, size=(cells, cells))
    y = np.arange(h) * cells / h
    x = np.arange(w) * cells / w
    y0, x0 = np.floor(y).astype(int), np.floor(x).astype(int)
    fy, fx = (y - y0)[:, None], (x - x0)[None, :]
    y1, x1 = (y0 + 1) % cells, (x0 + 1) % cells
    top = lattice[y0][:, x0] * (1 - fx) + lattice[y0][:, x1] * fx
    bottom = lattice[y1][:, x0] * (1 - fx) + lattice[y1][:, x1] * fx
    return (top * (1 - fy) + bottom * fy) * amplitude


def _speckle(rng: np.random.Generator, h: int, w: int, amplitude: float) -> np.ndarray:
    return rng.uniform(-amplitude, amplitude, size=(h, w))


def _compose(base_rgb: tuple[float, float, float], shade: np.ndarray) -> Image:
    """A base colour (0..1) times (1 + shade), per pixel."""
    out = np.asarray(base_rgb, float)[None, None, :] * (1.0 + shade[:, :, None])
    return np.clip(np.round(out * 255.0), 0, 255).astype(np.uint8)


def _fill(img: Image, y0: int, y1: int, x0: int, x1: int, rgb: tuple[float, float, float]) -> None:
    img[max(0, y0):max(0, y1), max(0, x0):max(0, x1)] = np.round(np.asarray(rgb) * 255).astype(np.uint8)


def _tone(rgb: tuple[float, float, float], k: float) -> tuple[float, float, float]:
    return (min(1.0, rgb[0] * k), min(1.0, rgb[1] * k), min(1.0, rgb[2] * k))


# ----- ground-like textures ------------------------------------------------------------------------
def _asphalt(rng: np.random.Generator) -> Image:
    n = 128
    shade = _noise(rng, n, n, 4, 0.07) + _noise(rng, n, n, 16, 0.05) + _speckle(rng, n, n, 0.10)
    img = _compose((0.30, 0.30, 0.31), shade)
    for _ in range(3):  # darker patches and a tar seam
        y, x = (int(v) for v in rng.integers(0, n, 2))
        patch = img[y:y + int(rng.integers(6, 20)), x:x + int(rng.integers(6, 30))]
        patch[:] = (patch * 0.94).astype(np.uint8)
    seam_y = int(rng.integers(0, n))
    img[seam_y, :] = (img[seam_y, :] * 0.75).astype(np.uint8)
    return img


def _lot(rng: np.random.Generator) -> Image:
    """Concrete slabs 2 m square with joints (the ground between buildings)."""
    n = 192  # 6 m
    shade = _noise(rng, n, n, 6, 0.05) + _speckle(rng, n, n, 0.05)
    img = _compose((0.66, 0.64, 0.60), shade)
    slab = n // 3
    for k in range(3):
        for j in range(3):
            img[k * slab:(k + 1) * slab, j * slab:(j + 1) * slab] = np.clip(
                img[k * slab:(k + 1) * slab, j * slab:(j + 1) * slab].astype(int) + int(rng.integers(-10, 10)), 0, 255)
    img[::slab, :] = (img[::slab, :] * 0.84).astype(np.uint8)
    img[:, ::slab] = (img[:, ::slab] * 0.84).astype(np.uint8)
    return img


def _paving(rng: np.random.Generator) -> Image:
    """Rectangular pavers in a running bond, each its own shade (sidewalks)."""
    n = 128  # 2 m
    img = _compose((0.72, 0.70, 0.67), _speckle(rng, n, n, 0.05))
    ph, pw = 16, 32  # 0.25 x 0.5 m
    for r in range(n // ph):
        off = (r % 2) * pw // 2
        for c in range(-1, n // pw + 1):
            x0 = c * pw + off
            tone = float(rng.uniform(0.88, 1.08))
            block = img[r * ph:(r + 1) * ph, max(0, x0):max(0, min(n, x0 + pw))]
            block[:] = np.clip(block * tone, 0, 255).astype(np.uint8)
            if 0 <= x0 < n:
                img[r * ph:(r + 1) * ph, x0] = (img[r * ph:(r + 1) * ph, x0] * 0.7).astype(np.uint8)
        img[r * ph, :] = (img[r * ph, :] * 0.7).astype(np.uint8)
    return img


def _grass(rng: np.random.Generator) -> Image:
    n = 128
    shade = _noise(rng, n, n, 5, 0.18) + _noise(rng, n, n, 20, 0.10) + _speckle(rng, n, n, 0.16)
    return _compose((0.30, 0.50, 0.22), shade)


def _roof(rng: np.random.Generator, rgb: tuple[float, float, float], seams: bool) -> Image:
    """A whole roof, stretched over each building's roof (not tiled): gravel or membrane sheets,
    a light coping round the edge and a dark line inside it."""
    n = 128
    shade = _noise(rng, n, n, 4, 0.06) + _speckle(rng, n, n, 0.09)
    img = _compose(rgb, shade)
    if seams:  # membrane sheets
        img[:, ::16] = (img[:, ::16] * 0.82).astype(np.uint8)
    coping = np.round(np.array([0.80, 0.79, 0.76]) * 255).astype(np.uint8)
    img[:3], img[-3:], img[:, :3], img[:, -3:] = coping, coping, coping, coping
    img[3], img[-4], img[:, 3], img[:, -4] = (img[3] * 0.6).astype(np.uint8), (img[-4] * 0.6).astype(np.uint8), \
        (img[:, 3] * 0.6).astype(np.uint8), (img[:, -4] * 0.6).astype(np.uint8)
    return img


def _metal(rng: np.random.Generator) -> Image:
    n = 64
    img = _compose((0.70, 0.71, 0.72), _speckle(rng, n, n, 0.03))
    img[::6, :] = (img[::6, :] * 0.78).astype(np.uint8)  # louvres
    img[:, :2] = (img[:, :2] * 0.7).astype(np.uint8)
    return img


def _leaves(rng: np.random.Generator, rgb: tuple[float, float, float]) -> Image:
    n = 64
    shade = _noise(rng, n, n, 8, 0.25) + _speckle(rng, n, n, 0.22)
    return _compose(rgb, shade)


def _kerb(rng: np.random.Generator) -> Image:
    n = 32
    img = _compose((0.80, 0.79, 0.76), _speckle(rng, n, n, 0.04))
    img[:, ::16] = (img[:, ::16] * 0.75).astype(np.uint8)
    return img


# ----- façades -------------------------------------------------------------------------------
def _window(img: Image, y0: int, y1: int, x0: int, x1: int, rng: np.random.Generator, *, frame: tuple[float, float, float],
            glass: tuple[float, float, float], frame_px: int = 2, blinds: float = 0.3, mullion: bool = True) -> None:
    """A framed window: frame colour, glass with a sky reflection brighter at the top, sometimes
    a blind pulled part way down, a mullion and a transom."""
    _fill(img, y0, y1, x0, x1, frame)
    gy0, gy1, gx0, gx1 = y0 + frame_px, y1 - frame_px, x0 + frame_px, x1 - frame_px
    h = gy1 - gy0
    k = float(rng.uniform(0.8, 1.25))
    for r in range(h):  # reflection gradient, brighter at the top
        _fill(img, gy0 + r, gy0 + r + 1, gx0, gx1, _tone(glass, k * (1.35 - 0.6 * r / max(1, h))))
    if rng.random() < blinds:
        depth = int(h * rng.uniform(0.2, 0.7))
        _fill(img, gy0, gy0 + depth, gx0, gx1, _tone((0.86, 0.83, 0.76), float(rng.uniform(0.8, 1.0))))
    if mullion:
        mx = (gx0 + gx1) // 2
        _fill(img, gy0, gy1, mx, mx + 1, frame)
        ty = gy0 + h // 3
        _fill(img, ty, ty + 1, gx0, gx1, frame)


def _punched_facade(rng: np.random.Generator, wall: Image, *, bay_px: int, storey_px: int, window_w: float,
                    window_h: float, frame: tuple[float, float, float], glass: tuple[float, float, float],
                    sill: tuple[float, float, float] | None, cornice: tuple[float, float, float] | None) -> Image:
    """Windows punched into a wall texture, one per bay and storey, with sills and a string course."""
    img = wall
    ww, wh = round(bay_px * window_w), round(storey_px * window_h)
    for s in range(STOREYS_PER_TILE):
        top = s * storey_px
        if cornice is not None:
            _fill(img, top, top + 3, 0, img.shape[1], cornice)
        for b in range(BAYS_PER_TILE):
            x0 = b * bay_px + (bay_px - ww) // 2
            y0 = top + (storey_px - wh) // 2 + 2
            _window(img, y0, y0 + wh, x0, x0 + ww, rng, frame=frame, glass=glass)
            if sill is not None:
                _fill(img, y0 + wh, y0 + wh + 3, x0 - 2, x0 + ww + 2, sill)
    return img


def _brick(rng: np.random.Generator, rgb: tuple[float, float, float]) -> Image:
    bay_px, storey_px = 64, 64
    h, w = storey_px * STOREYS_PER_TILE, bay_px * BAYS_PER_TILE
    img = _compose(rgb, _noise(rng, h, w, 8, 0.06) + _speckle(rng, h, w, 0.05))
    for r in range(0, h, 3):  # courses of bricks: mortar every third row, brick tones staggered
        img[r] = np.clip(img[r].astype(int) + 45, 0, 255).astype(np.uint8)
        off = 3 * ((r // 3) % 2)
        for c in range(off, w, 6):
            tone = float(rng.uniform(0.85, 1.12))
            img[r + 1:r + 3, c:c + 6] = np.clip(img[r + 1:r + 3, c:c + 6] * tone, 0, 255).astype(np.uint8)
    return _punched_facade(rng, img, bay_px=bay_px, storey_px=storey_px, window_w=0.45, window_h=0.58,
                           frame=(0.92, 0.91, 0.88), glass=(0.20, 0.25, 0.30), sill=(0.85, 0.83, 0.78), cornice=None)


def _plaster(rng: np.random.Generator, rgb: tuple[float, float, float]) -> Image:
    bay_px, storey_px = 64, 64
    h, w = storey_px * STOREYS_PER_TILE, bay_px * BAYS_PER_TILE
    img = _compose(rgb, _noise(rng, h, w, 6, 0.04) + _speckle(rng, h, w, 0.03))
    out = _punched_facade(rng, img, bay_px=bay_px, storey_px=storey_px, window_w=0.42, window_h=0.55,
                          frame=(0.30, 0.27, 0.24), glass=(0.18, 0.22, 0.27), sill=(0.95, 0.94, 0.90),
                          cornice=_tone(rgb, 1.12))
    for s in range(STOREYS_PER_TILE):  # shutters beside some windows
        for b in range(BAYS_PER_TILE):
            if rng.random() < 0.35:
                ww, wh = round(bay_px * 0.42), round(storey_px * 0.55)
                x0 = b * bay_px + (bay_px - ww) // 2
                y0 = s * storey_px + (storey_px - wh) // 2 + 2
                colour = (0.25, 0.38, 0.30) if rng.random() < 0.5 else (0.45, 0.30, 0.22)
                _fill(out, y0, y0 + wh, x0 - 7, x0 - 1, colour)
                _fill(out, y0, y0 + wh, x0 + ww + 1, x0 + ww + 7, colour)
    return out


def _curtain_wall(rng: np.random.Generator, glass: tuple[float, float, float]) -> Image:
    """Glass curtain wall: two panels per bay, dark mullions, spandrel bands at the floor slabs,
    each panel its own reflection."""
    bay_px, storey_px = 48, 64
    h, w = storey_px * STOREYS_PER_TILE, bay_px * BAYS_PER_TILE
    img = np.zeros((h, w, 3), np.uint8)
    frame = (0.20, 0.22, 0.24)
    _fill(img, 0, h, 0, w, frame)
    panel = bay_px // 2
    for s in range(STOREYS_PER_TILE):
        top = s * storey_px
        _fill(img, top, top + 10, 0, w, _tone(glass, 0.55))  # spandrel
        for p in range(w // panel):
            k = float(rng.uniform(0.75, 1.3))
            x0, x1 = p * panel + 2, (p + 1) * panel - 1
            for r in range(top + 12, top + storey_px - 1):
                t = (r - top) / storey_px
                _fill(img, r, r + 1, x0, x1, _tone(glass, k * (1.4 - 0.7 * t)))
            if rng.random() < 0.15:  # a lit or blinded panel
                _fill(img, top + 12, top + 12 + int(rng.integers(8, 30)), x0, x1, (0.80, 0.80, 0.74))
    return img


def _ribbon(rng: np.random.Generator) -> Image:
    """Concrete office block: continuous ribbon windows between concrete bands."""
    bay_px, storey_px = 64, 64
    h, w = storey_px * STOREYS_PER_TILE, bay_px * BAYS_PER_TILE
    img = _compose((0.74, 0.73, 0.70), _noise(rng, h, w, 6, 0.05) + _speckle(rng, h, w, 0.04))
    for s in range(STOREYS_PER_TILE):
        y0 = s * storey_px + 24
        y1 = y0 + 30
        for x in range(0, w, bay_px // 2):
            _window(img, y0, y1, x, x + bay_px // 2, rng, frame=(0.30, 0.31, 0.33), glass=(0.16, 0.21, 0.26),
                    frame_px=1, blinds=0.25, mullion=False)
        _fill(img, y1, y1 + 2, 0, w, (0.58, 0.57, 0.55))
    return img


def _shops(rng: np.random.Generator, palette: tuple[tuple[float, float, float], ...]) -> Image:
    """Ground floor of three shops: sign band in the shop's colour, awning, display glass, door."""
    bay_px, h = 80, 96
    w = bay_px * SHOP_BAYS_PER_TILE
    img = _compose((0.55, 0.53, 0.50), _speckle(rng, h, w, 0.04))
    for b in range(SHOP_BAYS_PER_TILE):
        x0 = b * bay_px
        colour = palette[int(rng.integers(len(palette)))]
        _fill(img, 4, 20, x0 + 3, x0 + bay_px - 3, colour)  # sign band
        for k in range(int(rng.integers(3, 6))):  # lettering
            lx = x0 + 10 + k * 12
            _fill(img, 9, 15, lx, lx + 8, (0.97, 0.96, 0.92))
        if rng.random() < 0.6:  # awning, striped
            for k in range(0, bay_px - 6, 8):
                stripe = colour if (k // 8) % 2 == 0 else (0.95, 0.95, 0.92)
                _fill(img, 22, 30, x0 + 3 + k, x0 + 7 + k, _tone(stripe, 0.9))
        door = x0 + int(rng.integers(8, bay_px - 24))
        _window(img, 32, h - 6, x0 + 4, x0 + bay_px - 4, rng, frame=(0.15, 0.15, 0.16), glass=(0.22, 0.26, 0.30),
                frame_px=2, blinds=0.0, mullion=False)
        for _ in range(int(rng.integers(2, 5))):  # goods in the window
            gx = x0 + 8 + int(rng.integers(0, bay_px - 20))
            _fill(img, h - 24, h - 8, gx, gx + 8, palette[int(rng.integers(len(palette)))])
        _fill(img, 34, h - 6, door, door + 14, (0.10, 0.10, 0.11))
        _fill(img, h - 6, h, x0, x0 + bay_px, (0.40, 0.39, 0.37))
    return img


def _lobby(rng: np.random.Generator) -> Image:
    bay_px, h = 80, 96
    w = bay_px * SHOP_BAYS_PER_TILE
    img = np.zeros((h, w, 3), np.uint8)
    _fill(img, 0, h, 0, w, (0.18, 0.19, 0.21))
    for b in range(SHOP_BAYS_PER_TILE * 2):
        _window(img, 8, h - 4, b * bay_px // 2 + 2, (b + 1) * bay_px // 2 - 2, rng, frame=(0.18, 0.19, 0.21),
                glass=(0.25, 0.32, 0.38), frame_px=1, blinds=0.0, mullion=False)
    _fill(img, 0, 8, 0, w, (0.55, 0.56, 0.58))
    return img


_SHOP_COLOURS = ((0.70, 0.10, 0.10), (0.10, 0.35, 0.60), (0.12, 0.45, 0.22), (0.85, 0.55, 0.10),
                 (0.45, 0.15, 0.45), (0.15, 0.15, 0.15), (0.80, 0.30, 0.45))

GENERATORS: dict[str, Callable[[np.random.Generator], Image]] = {
    "asphalt": _asphalt, "lot": _lot, "paving": _paving, "grass": _grass, "kerb": _kerb,
    "roof_gravel": lambda r: _roof(r, (0.46, 0.44, 0.41), seams=False),
    "roof_membrane": lambda r: _roof(r, (0.34, 0.35, 0.38), seams=True),
    "metal": _metal,
    "leaves_a": lambda r: _leaves(r, (0.20, 0.42, 0.17)), "leaves_b": lambda r: _leaves(r, (0.28, 0.46, 0.16)),
    "brick_red": lambda r: _brick(r, (0.58, 0.26, 0.19)), "brick_brown": lambda r: _brick(r, (0.48, 0.33, 0.25)),
    "plaster_cream": lambda r: _plaster(r, (0.86, 0.81, 0.69)), "plaster_ochre": lambda r: _plaster(r, (0.80, 0.62, 0.42)),
    "glass_blue": lambda r: _curtain_wall(r, (0.28, 0.40, 0.55)), "glass_teal": lambda r: _curtain_wall(r, (0.26, 0.44, 0.46)),
    "concrete_ribbon": _ribbon,
    "shop_a": lambda r: _shops(r, _SHOP_COLOURS), "shop_b": lambda r: _shops(r, _SHOP_COLOURS[::-1]), "lobby": _lobby,
}
"""Texture name -> generator; :func:`texture` seeds each from (seed, name)."""


def texture(name: str, seed: int) -> Image:
    """The texture ``name`` for a town's texture seed; same inputs, same bytes."""
    if name not in GENERATORS:
        raise ValueError(f"unknown texture {name!r}; known: {', '.join(sorted(GENERATORS))}")
    img = GENERATORS[name](_rng(name, seed))
    return np.ascontiguousarray(img, dtype=np.uint8)


@functools.lru_cache(maxsize=256)
def texture_file(name: str, seed: int, cache_root: Path) -> Path:
    """Path of the texture's PNG under ``cache_root`` (named by the sha256 of its pixels and
    shape), written on first use; concurrent writers race harmlessly (write, then rename)."""
    img = texture(name, seed)
    digest = hashlib.sha256(np.asarray(img.shape, np.int64).tobytes() + img.tobytes()).hexdigest()
    path = cache_root / f"{digest[:32]}.png"
    if not path.exists():
        cache_root.mkdir(parents=True, exist_ok=True)
        ok, data = cv2.imencode(".png", cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
        if not ok:
            raise RuntimeError(f"could not encode texture {name}")
        tmp = path.with_suffix(f".{os.getpid()}.tmp")
        tmp.write_bytes(data.tobytes())
        os.replace(tmp, path)
    return path
