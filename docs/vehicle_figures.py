"""The contact sheet of the rich look's body types, docs/images/vehicles_rich.png (run from the
repository root):

    .venv/bin/python docs/vehicle_figures.py

Every vehicle is rendered alone, far from the town, from the UGV camera height (side, 3/4 front,
3/4 rear, straight from behind), from above, and the flat look's box vehicle beside it where one
exists. The last rows show the checkable attributes one at a time (a two-tone roof, a roof rack
with its cargo box, a stripe), the roof white, the stripe in the colour that contrasts with the paint.
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np

from agos.world.sim.scene import STUDIO_OFFSET_M, Scene
from agos.world.towns.asset import open_town
from agos.world.towns.catalog import BODY_TYPES
from agos.world.towns.look.vehicles import RICH_BODY_TYPES, ROOF_COLOUR, VehicleAttributes, contrast_colour, vehicle_mesh

OUT = Path("docs/images")
TILE_PX = 256
PAINTS = {"sedan": "red", "hatchback": "blue", "suv": "green", "pickup": "orange", "van": "white",
          "box_truck": "yellow", "bus": "red"}
GROUND_RGB = np.array([196, 194, 188], np.uint8)


def label(img: np.ndarray, text: str) -> np.ndarray:
    out = img.copy()
    cv2.putText(out, text, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.42, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.putText(out, text, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.42, (255, 255, 255), 1, cv2.LINE_AA)
    return out


def shot(scene: Scene, uid: int, length_m: float, azimuth_deg: float, *, top: bool = False) -> np.ndarray:
    """The vehicle at the studio (yaw 0) seen from ``azimuth_deg`` (0: from the front) at 1.7 m,
    framed by its length, or from straight above; nothing behind it but a plain backdrop."""
    centre = np.asarray(STUDIO_OFFSET_M) + [0.0, 0.0, 0.9]
    dist = 1.45 * length_m + 3.0
    if top:
        eye = centre + [0.0, 0.0, 1.6 * length_m + 4.0]
        forward, up = np.array([0.0, 0.0, -1.0]), np.array([1.0, 0.0, 0.0])
    else:
        a = math.radians(azimuth_deg)
        eye = np.asarray(STUDIO_OFFSET_M) + [dist * math.cos(a), dist * math.sin(a), 1.7]
        forward, up = centre - eye, np.array([0.0, 0.0, 1.0])
    r = scene.render(eye, forward, up, fov_deg=40.0, width_px=TILE_PX, height_px=TILE_PX)
    rgb = r.rgb.copy()
    rgb[r.instance != uid] = GROUND_RGB
    return rgb


def sheet(rich: Scene, flat: Scene) -> np.ndarray:
    rows = []
    entries = [(name, VehicleAttributes(), name, PAINTS[name]) for name in RICH_BODY_TYPES]
    entries += [("sedan", VehicleAttributes(roof=ROOF_COLOUR), "sedan + two-tone roof", "blue"),
                ("suv", VehicleAttributes(rack=True), "suv + roof rack", "green"),
                ("hatchback", VehicleAttributes(stripe=contrast_colour("yellow")), "hatchback + stripe", "yellow")]
    for name, attrs, title, paint in entries:
        length = vehicle_mesh(name, attrs).length_m
        uid = rich.add_vehicle(name, paint, tuple(STUDIO_OFFSET_M), 0.0, attributes=attrs)
        tiles = [label(shot(rich, uid, length, 90.0), f"{title}: left side"),
                 label(shot(rich, uid, length, 40.0), "3/4 front"),
                 label(shot(rich, uid, length, 215.0), "3/4 rear"),
                 label(shot(rich, uid, length, 180.0), "rear"),
                 label(shot(rich, uid, length, 0.0, top=True), "top")]
        rich.remove(uid)
        if name in BODY_TYPES and attrs == VehicleAttributes():
            uid = flat.add_vehicle(name, paint, tuple(STUDIO_OFFSET_M), 0.0)
            tiles.append(label(shot(flat, uid, length, 40.0), "flat look, 3/4 front"))
            flat.remove(uid)
        else:
            tiles.append(label(np.full((TILE_PX, TILE_PX, 3), GROUND_RGB, np.uint8), "(no flat model)"))
        rows.append(np.concatenate(tiles, axis=1))
    return np.concatenate(rows, axis=0)


def main() -> None:
    layout = open_town("grid-s7").layout
    with Scene(layout, look="rich") as rich, Scene(layout, look="flat") as flat:
        img = sheet(rich, flat)
    OUT.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(OUT / "vehicles_rich.png"), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
    print(OUT / "vehicles_rich.png")


if __name__ == "__main__":
    main()
