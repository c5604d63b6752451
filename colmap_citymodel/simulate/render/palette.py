"""Colours of the rendered city and each object's draw of them (per building: plaster or brick,
its colour, the roof's, the window frames' and the door's; per car its paint; per tree its
green), all from the render seed.

Colours are given in sRGB (0-255, as a photograph shows them) and used in linear light.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def linear(srgb) -> np.ndarray:
    """sRGB 0-255 -> linear reflectance 0-1 (the sRGB transfer curve)."""
    c = np.asarray(srgb, dtype=np.float64) / 255.0
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4).astype(np.float32)


PLASTER = linear([(236, 231, 220), (240, 228, 196), (236, 218, 165), (214, 178, 120),
                  (228, 196, 186), (204, 202, 196), (186, 196, 206), (216, 202, 178),
                  (206, 214, 190), (226, 214, 200)])
BRICK = linear([(152, 72, 52), (122, 56, 44), (184, 148, 102), (132, 86, 62), (160, 100, 70)])
MORTAR = linear((190, 185, 175))
ROOF_TILE = linear([(172, 82, 56), (126, 54, 42), (112, 76, 56), (64, 64, 70), (98, 98, 104),
                    (150, 70, 48)])
FLAT_ROOF = linear([(128, 126, 120), (86, 86, 88), (150, 146, 136)])
FRAME = linear([(240, 240, 236), (240, 240, 236), (66, 68, 72), (96, 64, 44)])
DOOR = linear([(102, 66, 42), (42, 72, 52), (112, 38, 32), (92, 92, 98), (226, 224, 218),
               (60, 48, 40)])
CAR = linear([(236, 236, 234), (182, 184, 188), (26, 26, 30), (32, 48, 92), (152, 28, 28),
              (102, 102, 108), (52, 92, 160), (70, 80, 62)])
FOLIAGE = linear([(66, 96, 44), (52, 82, 40), (84, 106, 50), (60, 86, 56)])
BARK = linear((92, 80, 68))
CONCRETE = linear((168, 166, 160))
METAL = linear([(62, 66, 64), (44, 60, 52), (120, 122, 124), (40, 40, 42)])
ASPHALT = linear((88, 88, 90))
PAVING = linear([(168, 162, 152), (150, 142, 136), (176, 170, 164)])
KERB = linear((150, 150, 148))
GRASS = linear([(88, 118, 52), (104, 124, 58), (76, 104, 48)])
MARKING = linear((232, 232, 226))
GLASS = linear((30, 38, 44))


@dataclass
class Styles:
    """Per object (row = object number + 1; row 0 the terrain): what it is painted with."""

    plaster: np.ndarray  # (M,3) wall colour (plaster, or the brick's when brick)
    brick: np.ndarray  # (M,) bool: brick walls
    roof: np.ndarray  # (M,3) tile colour
    flat_roof: np.ndarray  # (M,3)
    frame: np.ndarray  # (M,3) window frames
    door: np.ndarray  # (M,3)
    paint: np.ndarray  # (M,3) cars, street furniture, trees: their own colour
    offset: np.ndarray  # (M,2) texture coordinate offset (m): no two objects alike
    rand: np.ndarray  # (M,8) uniform [0, 1) draws for anything else

    @classmethod
    def draw(cls, num_objects: int, seed: int) -> Styles:
        rng = np.random.default_rng([seed, 3])
        m = num_objects + 1

        def pick(table, jitter=0.06):
            colours = table[rng.integers(len(table), size=m)]
            return (colours * rng.uniform(1 - jitter, 1 + jitter, (m, 3))).astype(np.float32)

        brick = rng.random(m) < 0.3
        plaster = pick(PLASTER)
        plaster[brick] = pick(BRICK, 0.1)[brick]
        paint = pick(CAR, 0.05)
        return cls(plaster, brick, pick(ROOF_TILE), pick(FLAT_ROOF), pick(FRAME, 0.02),
                   pick(DOOR), paint, rng.uniform(0, 500, (m, 2)).astype(np.float32),
                   rng.random((m, 8)).astype(np.float32))

    def row(self, obj: np.ndarray) -> np.ndarray:
        """Row of each object number (-1, the terrain, is row 0)."""
        return np.asarray(obj, dtype=np.int64) + 1
