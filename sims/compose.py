"""Display: tissue stages blended by the damage fields, blood over them -> one RGB texture (H, W, 3) uint8.

A stage table (scene key look.stages) drives the tissue: the first stage is the base look; each
later stage is mixed in with weight opacity * smoothstep(from, to, field), where field is one of
coagulation (1 - exp(-Omega)), char, omega, temperature_c (all at the surface) or coagulation_depth_mm
(how deep the burn goes, so a deep burn can look different from a shallow one). Reordering or adding stages needs no
code. Blood covers the tissue where its film is thick enough: coverage is a smoothstep of the
displayed film thickness between BLOOD_EDGE fractions of the rest film (a defined, anti-aliased
edge rather than the glow ring of a plain blur), and its colour darkens from fresh red at the rest
film to near black-red at BLOOD_DARK_FILMS films, and a thin film lets the tissue show through
(opacity 1 - exp(-BLOOD_ABSORPTION films)). The film thickness is also read as a height map:
its slope tilts a normal that catches a baked highlight, so puddles and rivulet edges look wet. Texels outside the UV charts take the colour of the
nearest surface texel, so texture filtering in a viewer never bleeds background into the mesh.
"""
import numpy as np
import taichi as ti
from PIL import Image

FIELD_CODES = {"coagulation": 0, "char": 1, "omega": 2, "temperature_c": 3, "coagulation_depth_mm": 4}
BLOOD_EDGE = (0.25, 0.6)              # film fractions where coverage goes from 0 to 1
BLOOD_DARK_FILMS = 4.0                # film multiples at which blood reaches its darkest colour
BLOOD_THIN_RGB = (0.45, 0.02, 0.03)   # fresh blood film over tissue
BLOOD_THICK_RGB = (0.16, 0.0, 0.01)  # pooled blood
BLOOD_GLOSS = 0.35                    # strength of the baked highlight on the blood surface
BLOOD_ABSORPTION = 3.0                # opacity of a film: 1 - exp(-absorption * films); thin blood shows tissue
GLOSS_REACH = 6                       # texels either side for the slope of the blood surface
LIGHT_DIR = (-0.55, -0.65, 0.52)       # grid-space light (x = columns, y = rows, z out of the surface)


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


@ti.data_oriented
class Composer:
    """Stage textures in one field; compose() blends them from the cautery's fields and adds blood."""

    def __init__(self, stages: list, textures: list, fill_index: np.ndarray, texel_mm: float):
        count = len(stages)
        height, width = fill_index.shape
        self.textures = ti.Vector.field(3, ti.f32, (count, height, width))
        self.textures.from_numpy(np.stack(textures).astype(np.float32))
        self.ranges = ti.Vector.field(3, ti.f32, count)  # from, to, opacity
        # the fields each stage reads, fixed when the kernels compile: each texel samples only the fields in use
        self.codes = tuple(FIELD_CODES[stage["field"]] if stage["field"] else -1 for stage in stages)
        self.reads = tuple(code in self.codes[1:] for code in range(len(FIELD_CODES)))
        self.reads_omega = self.reads[FIELD_CODES["coagulation"]] or self.reads[FIELD_CODES["omega"]]
        self.shows_temperature = self.reads[FIELD_CODES["temperature_c"]]  # else only damage and char change the look
        self.ranges.from_numpy(np.array([[stage["from"], stage["to"], stage["opacity"]] for stage in stages], np.float32))
        self.fill = ti.field(ti.i32, (height, width))
        self.fill.from_numpy(fill_index.astype(np.int32))
        self.color = ti.Vector.field(3, ti.f32, (height, width))  # tissue colour
        self.color.from_numpy(textures[0].astype(np.float32))
        self.rgb = ti.Vector.field(3, ti.u8, (height, width))
        self.count = count
        self.texel_mm = texel_mm  # typical texel size, for slopes of the blood height map

    def compose(self, tiles, heat=None, bleeding=None) -> np.ndarray:
        """(H, W, 3) uint8 from the models present (each may be None; heat: sims.heat_display.HeatDisplay). The
        tissue is recomposed only on the tiles that tiles (sims.display_tiles.DisplayTiles) flags, the others keep
        their colour; blood covers every tile."""
        if tiles.listed:
            if heat is not None:
                self._tissue(heat, tiles, bleeding is None)
            elif bleeding is None:
                self._plain(tiles)
        if bleeding is not None:
            self._with_blood(bleeding.thickness, bleeding.params["film_thickness_mm"], self.texel_mm)
        return self.rgb.to_numpy()

    @ti.kernel
    def _tissue(self, heat: ti.template(), tiles: ti.template(), shown: ti.template()):
        """Tissue colour (color, at surface texels) of the flagged tiles, and their rgb when shown (no blood pass
        follows): each texel shows the stages blended at its fill source, from the burn read there."""
        for r, c in self.rgb:
            if tiles.flagged(r, c):
                sr, sc = self._source(r, c)
                color = self.textures[0, sr, sc]
                omega, char, temperature, depth = 0.0, 0.0, 0.0, 0.0
                if ti.static(self.reads_omega):
                    omega = heat.sample(heat.cautery.omega, sr, sc)
                if ti.static(self.reads[FIELD_CODES["char"]]):
                    char = heat.sample(heat.cautery.char, sr, sc)
                if ti.static(self.reads[FIELD_CODES["temperature_c"]]):
                    temperature = heat.sample(heat.cautery.surface_temperature, sr, sc)
                if ti.static(self.reads[FIELD_CODES["coagulation_depth_mm"]]):
                    depth = heat.sample(heat.cautery.coagulation_depth, sr, sc)
                for s in ti.static(range(1, self.count)):
                    value = depth
                    if ti.static(self.codes[s] == FIELD_CODES["coagulation"]):
                        value = 1.0 - ti.exp(-omega)
                    elif ti.static(self.codes[s] == FIELD_CODES["char"]):
                        value = char
                    elif ti.static(self.codes[s] == FIELD_CODES["omega"]):
                        value = omega
                    elif ti.static(self.codes[s] == FIELD_CODES["temperature_c"]):
                        value = temperature
                    lo, hi = self.ranges[s][0], self.ranges[s][1]
                    x = ti.min(ti.max((value - lo) / (hi - lo), 0.0), 1.0)
                    weight = x * x * (3.0 - 2.0 * x) * self.ranges[s][2]
                    color = color * (1.0 - weight) + self.textures[s, sr, sc] * weight
                if sr == r and sc == c:
                    self.color[r, c] = color
                if ti.static(shown):
                    self._write(r, c, color)

    @ti.func
    def _write(self, r, c, color):
        self.rgb[r, c] = ti.cast(ti.min(ti.max(color * 255.0 + 0.5, 0.0), 255.0), ti.u8)

    @ti.func
    def _source(self, r, c):
        width = self.fill.shape[1]
        source = self.fill[r, c]
        return source // width, source % width

    @ti.kernel
    def _plain(self, tiles: ti.template()):
        for r, c in self.rgb:
            if tiles.flagged(r, c):
                sr, sc = self._source(r, c)
                self._write(r, c, self.color[sr, sc])

    @ti.kernel
    def _with_blood(self, thickness: ti.template(), film: ti.f32, texel_mm: ti.f32):
        thin, thick = ti.Vector(BLOOD_THIN_RGB), ti.Vector(BLOOD_THICK_RGB)
        light = ti.Vector(LIGHT_DIR).normalized()
        half = (light + ti.Vector([0.0, 0.0, 1.0])).normalized()
        height, width = self.rgb.shape[0], self.rgb.shape[1]
        for r, c in self.rgb:
            sr, sc = self._source(r, c)
            films = thickness[sr, sc] / film
            x = ti.min(ti.max((films - BLOOD_EDGE[0]) / (BLOOD_EDGE[1] - BLOOD_EDGE[0]), 0.0), 1.0)
            cover = x * x * (3.0 - 2.0 * x)
            depth = ti.min(ti.max((films - 1.0) / (BLOOD_DARK_FILMS - 1.0), 0.0), 1.0)
            blood = thin * (1.0 - depth) + thick * depth
            dx = thickness[sr, ti.min(sc + GLOSS_REACH, width - 1)] - thickness[sr, ti.max(sc - GLOSS_REACH, 0)]
            dy = thickness[ti.min(sr + GLOSS_REACH, height - 1), sc] - thickness[ti.max(sr - GLOSS_REACH, 0), sc]
            normal = ti.Vector([-dx, -dy, 2.0 * GLOSS_REACH * texel_mm]).normalized()
            gloss = BLOOD_GLOSS * ti.max(normal.dot(half), 0.0) ** 24
            alpha = cover * (1.0 - ti.exp(-BLOOD_ABSORPTION * films))
            self._write(r, c, self.color[sr, sc] * (1.0 - alpha) + blood * alpha + gloss * cover)
