"""Display: blend the tissue stage textures by the damage fields into one RGB texture (H, W, 3) uint8.

A stage table (scene key look.stages) drives the blend: the first stage is the base look; each
later stage is mixed in with weight smoothstep(from, to, field), where field is one of
coagulation (1 - exp(-Omega)), char, omega or temperature_c. Reordering or adding stages needs
no code. Texels outside the UV charts take the colour of the nearest surface texel, so texture
filtering in a viewer never bleeds background into the mesh.
"""
import numpy as np
import taichi as ti
from PIL import Image

FIELD_CODES = {"coagulation": 0, "char": 1, "omega": 2, "temperature_c": 3}


class TextureError(ValueError):
    """A stage texture that cannot be read."""


def load_texture(path, size: int, tile: int = 1) -> np.ndarray:
    """Read an image as (size, size, 3) float32 in [0, 1], repeated `tile` times per side."""
    try:
        with Image.open(path) as image:
            cell = image.convert("RGB").resize((max(1, round(size / tile)),) * 2, Image.Resampling.LANCZOS)
    except Exception as exc:  # Pillow raises several types for unreadable files
        raise TextureError(f"cannot read image: {exc}") from None
    tiled = Image.new("RGB", (cell.width * tile,) * 2)
    for i in range(tile):
        for j in range(tile):
            tiled.paste(cell, (i * cell.width, j * cell.width))
    if tiled.size != (size, size):
        tiled = tiled.resize((size, size), Image.Resampling.LANCZOS)
    return np.asarray(tiled, np.float32) / 255.0


def fill_gutters(rgb: np.ndarray, fill_index: np.ndarray) -> np.ndarray:
    """Give texels outside the charts the colour of the nearest surface texel: (H, W, C) -> (H, W, C)."""
    return rgb.reshape(-1, rgb.shape[-1])[fill_index]


@ti.data_oriented
class Composer:
    """Stage textures in one field; compose() blends them from the cautery fields."""

    def __init__(self, stages: list, textures: list, fill_index: np.ndarray):
        count = len(stages)
        height, width = fill_index.shape
        self.textures = ti.Vector.field(3, ti.f32, (count, height, width))
        self.textures.from_numpy(np.stack(textures).astype(np.float32))
        self.codes = ti.field(ti.i32, count)
        self.ranges = ti.Vector.field(3, ti.f32, count)  # from, to, opacity
        codes = [FIELD_CODES[stage["field"]] if stage["field"] else -1 for stage in stages]
        self.codes.from_numpy(np.array(codes, np.int32))
        self.ranges.from_numpy(np.array([[stage["from"], stage["to"], stage["opacity"]] for stage in stages], np.float32))
        self.fill = ti.field(ti.i32, (height, width))
        self.fill.from_numpy(fill_index.astype(np.int32))
        self.rgb = ti.Vector.field(3, ti.u8, (height, width))
        self.count = count

    def compose(self, temperature, omega, char) -> np.ndarray:
        """(H, W, 3) uint8 from Taichi fields T (C), Omega, char."""
        self._blend(temperature, omega, char)
        return self.rgb.to_numpy()

    @ti.kernel
    def _blend(self, temperature: ti.template(), omega: ti.template(), char: ti.template()):
        width = self.fill.shape[1]
        for r, c in self.fill:
            source = self.fill[r, c]
            sr, sc = source // width, source % width
            color = self.textures[0, sr, sc]
            for s in range(1, self.count):
                code = self.codes[s]
                value = temperature[sr, sc]
                if code == 0:
                    value = 1.0 - ti.exp(-omega[sr, sc])
                elif code == 1:
                    value = char[sr, sc]
                elif code == 2:
                    value = omega[sr, sc]
                lo, hi = self.ranges[s][0], self.ranges[s][1]
                x = ti.min(ti.max((value - lo) / (hi - lo), 0.0), 1.0)
                weight = x * x * (3.0 - 2.0 * x) * self.ranges[s][2]
                color = color * (1.0 - weight) + self.textures[s, sr, sc] * weight
            self.rgb[r, c] = ti.cast(ti.min(ti.max(color * 255.0 + 0.5, 0.0), 255.0), ti.u8)
