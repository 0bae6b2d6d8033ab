"""The look: tissue stages blended by the burn, blood over them -> base colour, normal and roughness maps (H, W).

A stage table (scene key look.stages) drives the tissue: the first stage is the base look; each later stage is mixed
in with weight opacity * smoothstep(from, to, field), where field is one of coagulation (1 - exp(-Omega)), char,
omega, temperature_c (all at the surface) or coagulation_depth_mm (how deep the burn goes, so a deep burn can look
different from a shallow one). Reordering or adding stages needs no code. Every stage has a colour texture and a
surface: a height (mm, its map's red times relief_mm plus offset_mm, so coagulated tissue can sit lower than healthy
tissue and char can stand up as a crust) and a roughness (its map's green, or a constant); both are blended with the
colour's weights.

Blood lies over the tissue as a layer of its thickness h (sims.look.film: the trail the look keeps on simulated time):
its reflectance per colour channel is the Kubelka-Munk layer over the tissue's reflectance R_g (linear light),

    R = (t (1 - R_g a) + R_g b) / (t (a - R_g) + b),  a = 1 + K/S, b = sqrt(a^2 - 1), t = tanh(b S h),

with absorption K = 2 mu_a (Beer-Lambert's coefficient for diffuse light) and scattering S = 3/4 mu_s' of whole
blood (haematocrit 45 %) at 650, 550 and 450 nm for red, green and blue (Bosschaart et al. 2014, Lasers Med Sci
29:453, appendix: mu_a oxygenated 0.16 / 23.9 / 31.8, deoxygenated 1.80 / 26.0 / 40.3, mu_s' 1.5 / 2.6 / 4.3 per mm;
the red channel's short end near 600 nm, which absorbs about ten times more, is left out). A thin layer shows the
tissue through it, a deep one tends to blood's own colour (a - b): 0.05 mm hides most green and blue, red passes
through millimetres. Clotted blood at rest loses its oxygen and darkens, so a pool that has settled is dark red and
fresh running blood bright. Fresh blood is FRESH_SATURATION oxygenated, clotted blood CLOT_SATURATION (darker). Where blood
has been (the film's stain) the tissue keeps a brown-red dried stain (STAIN_TRANSMITTANCE: chosen, no measurement
found). The blood's thickness is part of the surface height (a pool's edge is raised and rounded; a pool deeper than
POOL_LEVEL_MM hides the tissue's relief) and wet blood is glossy. The normal map is the slope of that height; the
browser lights it, so highlights move with the camera and nothing is baked into the colour.

Texels outside the UV charts take the maps of the nearest surface texel, so texture filtering in a viewer never
bleeds background into the mesh.
"""
import hashlib
import os

import numpy as np
import PIL
import taichi as ti
from PIL import Image

from sims.core import field_io
from sims.core.backend import cache_dir, prune_cache, read_cached_npz, row_span, save_cached_npz
from sims.look.display_tiles import BLOOD_COLUMNS, BLOOD_ROWS, BLOOD_SAMPLE, NORMAL, TISSUE, WRITE

FIELD_CODES = {"coagulation": 0, "char": 1, "omega": 2, "temperature_c": 3, "coagulation_depth_mm": 4}
BLOOD_MU_A_OXY = (0.16, 23.9, 31.8)     # 1/mm, red / green / blue = 650 / 550 / 450 nm (module docstring)
BLOOD_MU_A_DEOXY = (1.80, 26.0, 40.3)   # 1/mm
BLOOD_MU_S_REDUCED = (1.5, 2.6, 4.3)    # 1/mm
FRESH_SATURATION = 0.85                 # oxygen saturation of fresh surgical blood (arterial and venous mixed)
CLOT_SATURATION = 0.3                   # of clotted blood at rest
STAIN_TRANSMITTANCE = (0.72, 0.5, 0.45)  # what a dried stain lets through, per channel (brown-red)
STAIN_MM = 0.1                          # blood depth (mm) that leaves a full stain
BLOOD_ROUGHNESS = (0.1, 0.4)            # fresh, clotted
WET_MM = 0.01                           # blood depth at which the surface is wet (glossy) by 1 - 1/e
POOL_LEVEL_MM = 0.2                     # blood deeper than this has a level surface over the tissue's relief
NORMAL_LEVEL = 127.5                    # 8-bit normal maps: 0 maps to 127.5
COPY_ALL_SHARE = 0.25                   # compose copies whole maps off the device when more tiles than this changed
ENCODE_STEPS = 16384                    # linear light -> 8-bit sRGB by table: within a level of the exact encoding
TEXTURE_CACHE_BYTES = 256 << 20         # resampled stage images kept on disk (a 512² one: 0.8 MB)


class TextureError(ValueError):
    """A stage texture that cannot be read."""


def load_texture(path, size: int, tile: int = 1) -> np.ndarray:
    """Read an image as (size, size, 3) float32 in [0, 1], repeated `tile` times per side. The 8-bit image is kept in
    cache_dir()/textures, keyed by the file (path, bytes, modification time), size, tile and Pillow's version: the
    liver's nine 1024² stage PNGs took about 0.3 s to decode and resample for every scene build."""
    try:
        info = os.stat(path)
    except OSError as exc:
        raise TextureError(f"cannot read image: {exc.strerror or exc}") from None
    key = repr((os.path.realpath(path), info.st_size, info.st_mtime_ns, size, tile, PIL.__version__))
    cached = cache_dir() / "textures" / f"{hashlib.sha1(key.encode()).hexdigest()}.npz"
    stored = read_cached_npz(cached, "rgb")
    if stored is None:
        stored = (_read_texture(path, size, tile),)
        save_cached_npz(cached, rgb=stored[0])
        prune_cache(cached.parent, TEXTURE_CACHE_BYTES)
    return np.asarray(stored[0], np.float32) / 255.0


def _read_texture(path, size: int, tile: int) -> np.ndarray:
    """load_texture's image as (size, size, 3) uint8, read from the file."""
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
    return np.asarray(tiled, np.uint8)


def stage_surface(stage: dict, size: int) -> np.ndarray:
    """(size, size, 2) float32 height (mm) and roughness of a stage: from its surface map (red: height in units of
    relief_mm, green: roughness) when it has one, else its constant roughness at height 0; offset_mm added."""
    if stage.get("surface"):
        image = load_texture(stage["surface"], size, stage["tile"])
        height, roughness = image[..., 0] * stage["relief_mm"], image[..., 1]
    else:
        height, roughness = np.zeros((size, size), np.float32), np.full((size, size), stage["roughness"], np.float32)
    return np.stack([height + stage["offset_mm"], roughness], axis=-1).astype(np.float32)


@ti.func
def _smoothstep(lo, hi, value):
    x = ti.min(ti.max((value - lo) / (hi - lo), 0.0), 1.0)
    return x * x * (3.0 - 2.0 * x)


@ti.func
def _linear(srgb):
    """sRGB-encoded colour (0-1) -> linear light."""
    return ti.select(srgb <= 0.04045, srgb / 12.92, ((srgb + 0.055) / 1.055) ** 2.4)


def _encoded(linear: np.ndarray) -> np.ndarray:
    """Linear light -> sRGB-encoded colour (0-1)."""
    x = np.maximum(linear, 0.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1.0 / 2.4) - 0.055)


@ti.func
def blood_layer(ground, thickness_mm, saturation):
    """Kubelka-Munk reflectance (linear, per channel) of a blood layer thickness_mm deep over reflectance `ground`."""
    oxy, deoxy = ti.Vector(BLOOD_MU_A_OXY), ti.Vector(BLOOD_MU_A_DEOXY)
    mu_a = saturation * oxy + (1.0 - saturation) * deoxy
    s = 0.75 * ti.Vector(BLOOD_MU_S_REDUCED)
    a = 1.0 + 2.0 * mu_a / s
    b = ti.sqrt(a * a - 1.0)
    e = ti.exp(-2.0 * b * s * thickness_mm)
    t = (1.0 - e) / (1.0 + e)  # tanh(b s h) for h >= 0, with one exp per channel
    return (t * (1.0 - ground * a) + ground * b) / (t * (a - ground) + b)


@ti.data_oriented
class Composer:
    """Stage textures and surfaces in fields; compose() blends them from the cautery's fields and lays blood over them.
    After compose(): rgb (H, W, 3) u8, normal (H, W, 3) u8 (glTF tangent-space normal map: x along columns, y toward
    lower rows, z out), roughness (H, W) u8 (PBR roughness x 255)."""

    def __init__(self, stages: list, textures: list, surfaces: list, fill_index: np.ndarray, texel_mm: float):
        """textures: one (H, W, 3) float32 colour (sRGB, 0-1) per stage; surfaces: one (H, W, 2) float32 height (mm)
        and roughness per stage (stage_surface); texel_mm: typical texel size, for the slope of the height."""
        count = len(stages)
        height, width = fill_index.shape
        self.textures = ti.Vector.field(3, ti.f32, (count, height, width))
        self.surfaces = ti.Vector.field(2, ti.f32, (count, height, width))
        self.ranges = ti.Vector.field(3, ti.f32, count)  # from, to, opacity
        # the fields each stage reads, fixed when the kernels compile: each texel samples only the fields in use
        self.codes = tuple(FIELD_CODES[stage["field"]] if stage["field"] else -1 for stage in stages)
        self.reads = tuple(code in self.codes[1:] for code in range(len(FIELD_CODES)))
        self.reads_omega = self.reads[FIELD_CODES["coagulation"]] or self.reads[FIELD_CODES["omega"]]
        self.shows_temperature = self.reads[FIELD_CODES["temperature_c"]]  # else only damage and char change the look
        self.fill = ti.field(ti.i32, (height, width))
        self.color = ti.Vector.field(3, ti.f32, (height, width))    # tissue colour (sRGB, 0-1) at surface texels
        self.color_linear = ti.Vector.field(3, ti.f32, (height, width))  # the same in linear light
        self.encode = ti.field(ti.u8, ENCODE_STEPS)  # 8-bit sRGB of linear light (i / (ENCODE_STEPS - 1))
        self.tissue = ti.Vector.field(2, ti.f32, (height, width))   # tissue height (mm), roughness at surface texels
        self.relief = ti.field(ti.f32, (height, width))             # surface height with blood (mm), every texel
        self.blood_raw = ti.field(ti.f32, (height, width))          # blood depth at display texels (mm), as read
        self.blood_tmp = ti.field(ti.f32, (height, width))          # ... smoothed along rows
        self.blood = ti.field(ti.f32, (height, width))              # ... and along columns
        self.rgb = ti.Vector.field(3, ti.u8, (height, width))
        self.normal = ti.Vector.field(3, ti.u8, (height, width))
        self.roughness = ti.field(ti.u8, (height, width))
        self.shown = tuple(np.zeros((height, width) + tail, np.uint8) for tail in ((3,), (3,), ()))  # rgb, normal, roughness
        self.count = count
        self.texel_mm = float(texel_mm)
        self.span = row_span(width)  # texels a thread of a light pass takes along a row
        field_io.load([(self.textures, np.stack(textures)), (self.surfaces, np.stack(surfaces)),
                       (self.ranges, np.array([[stage["from"], stage["to"], stage["opacity"]] for stage in stages])),
                       (self.fill, fill_index), (self.color, textures[0]), (self.tissue, surfaces[0]),
                       (self.encode, np.rint(_encoded(np.linspace(0.0, 1.0, ENCODE_STEPS)) * 255.0))])
        self._linearize()

    def compose(self, tiles, heat=None, film=None) -> np.ndarray:
        """(H, W, 3) uint8 base colour from the models present (each may be None; heat: sims.heat.display.HeatDisplay,
        film: sims.look.film.BloodFilm); normal and roughness follow (maps()). Only the tiles that tiles
        (sims.look.display_tiles.DisplayTiles) flags are recomposed and copied out; the others keep theirs. The arrays
        returned are read-only and never change: a compose that changes something returns new ones."""
        kinds = tiles.kinds
        if kinds & TISSUE and heat is not None:
            self._tissue(heat, tiles)
        if film is not None:
            if kinds & BLOOD_SAMPLE:
                self._blood_depth(film, tiles, film.display_per_texel // 2)
            if kinds & WRITE:
                self._with_blood(film, tiles)
        elif kinds & WRITE:
            self._plain(tiles)
        if kinds & NORMAL:
            self._normals(tiles, self.texel_mm)
        written = tiles.written
        if len(written):
            self._copy_out(tiles, written)
        return self.shown[0]

    def maps(self) -> tuple[np.ndarray, np.ndarray]:
        """(normal (H, W, 3) uint8, roughness (H, W) uint8) of the last compose()."""
        return self.shown[1], self.shown[2]

    def _copy_out(self, tiles, written: np.ndarray) -> None:
        """Copy the written tiles' maps from the device into new copies of the shown arrays (one transfer each); when
        more than COPY_ALL_SHARE of the tiles were written, the whole maps (cheaper than packing that many tiles)."""
        if len(written) > COPY_ALL_SHARE * tiles.tiles:
            shown = (self.rgb.to_numpy(), self.normal.to_numpy(), self.roughness.to_numpy())
            for array in shown:
                array.flags.writeable = False
            self.shown = shown
            return
        t = tiles.tile
        packed = np.empty((len(written) * t * t, 8), np.uint8)  # rgb, normal, roughness and a spare byte per texel
        self._pack(tiles.tile, tiles.cols, written, packed)
        packed = packed.reshape(len(written), t, t, 8)
        out = (packed[..., 0:3], packed[..., 3:6], packed[..., 6])
        height, width = self.fill.shape
        rows, cols = written // tiles.cols, written % tiles.cols
        shown = []
        for old, packed in zip(self.shown, out):
            whole = (tiles.rows * t, tiles.cols * t) == (height, width)
            new = old.copy() if whole else np.pad(old, [(0, tiles.rows * t - height), (0, tiles.cols * t - width)] + [(0, 0)] * (old.ndim - 2))
            new.reshape(tiles.rows, t, tiles.cols, t, *old.shape[2:]).swapaxes(1, 2)[rows, cols] = packed
            if not whole:
                new = np.ascontiguousarray(new[:height, :width])
            new.flags.writeable = False
            shown.append(new)
        self.shown = tuple(shown)

    @ti.kernel
    def _pack(self, tile: ti.i32, cols: ti.i32, written: ti.types.ndarray(), out: ti.types.ndarray(dtype=ti.u8, ndim=2)):
        """out (N * tile * tile, 8): the texels of the N written tiles, tile by tile in rows, as rgb, normal,
        roughness bytes (one array and a flat loop: 1.4-1.7 times faster than three arrays over a 3D range)."""
        height, width = self.fill.shape
        per = tile * tile
        for q in range(written.shape[0] * per):
            k, e = q // per, q % per
            r, c = written[k] // cols * tile + e // tile, written[k] % cols * tile + e % tile
            if r < height and c < width:
                for d in ti.static(range(3)):
                    out[q, d] = self.rgb[r, c][d]
                    out[q, 3 + d] = self.normal[r, c][d]
                out[q, 6] = self.roughness[r, c]

    @ti.kernel
    def _tissue(self, heat: ti.template(), tiles: ti.template()):
        """Tissue colour and surface of the flagged tiles' surface texels, from the burn read there."""
        for r, c in self.color:  # a loop over texels: heavy texels (walking rows measured 1.1-1.3 times slower for them)
            if tiles.flagged(r, c, TISSUE) and self.fill[r, c] == r * self.fill.shape[1] + c:
                color, surface = self.textures[0, r, c], self.surfaces[0, r, c]
                omega, char, temperature, depth = 0.0, 0.0, 0.0, 0.0
                if ti.static(self.reads_omega):
                    omega = heat.omega(r, c)  # read through its log: the edge where the heat grid puts it
                if ti.static(self.reads[FIELD_CODES["char"]]):
                    char = heat.sample(heat.cautery.char, r, c)
                if ti.static(self.reads[FIELD_CODES["temperature_c"]]):
                    temperature = heat.sample(heat.cautery.surface_temperature, r, c)
                if ti.static(self.reads[FIELD_CODES["coagulation_depth_mm"]]):
                    depth = heat.sample(heat.cautery.coagulation_depth, r, c)
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
                    weight = _smoothstep(self.ranges[s][0], self.ranges[s][1], value) * self.ranges[s][2]
                    color = color * (1.0 - weight) + self.textures[s, r, c] * weight
                    surface = surface * (1.0 - weight) + self.surfaces[s, r, c] * weight
                self.color[r, c] = color
                self.color_linear[r, c] = _linear(color)
                self.tissue[r, c] = surface

    @ti.func
    def _source(self, r, c):
        width = self.fill.shape[1]
        source = self.fill[r, c]
        return source // width, source % width

    @ti.func
    def _write(self, r, c, color, height, roughness):
        self.rgb[r, c] = ti.cast(ti.min(ti.max(color * 255.0 + 0.5, 0.0), 255.0), ti.u8)
        self._write_surface(r, c, height, roughness)

    @ti.func
    def _write_surface(self, r, c, height, roughness):
        self.relief[r, c] = height
        self.roughness[r, c] = ti.cast(ti.min(ti.max(roughness * 255.0 + 0.5, 0.0), 255.0), ti.u8)

    @ti.kernel
    def _linearize(self):
        for r, c in self.color:
            self.color_linear[r, c] = _linear(self.color[r, c])

    @ti.kernel
    def _plain(self, tiles: ti.template()):
        height, width = self.fill.shape
        for r, q in ti.ndrange(height, width // self.span):
            for c in range(q * self.span, (q + 1) * self.span):
                if tiles.flagged(r, c, WRITE):
                    sr, sc = self._source(r, c)
                    self._write(r, c, self.color[sr, sc], self.tissue[sr, sc][0], self.tissue[sr, sc][1])

    @ti.kernel
    def _blood_depth(self, film: ti.template(), tiles: ti.template(), radius: ti.template()):
        """blood = the film's trail at each texel's fill source, smoothed by a tent of `radius` texels (half a texel of
        the film's grid): read bilinearly alone, a coarser film is linear within each of its cells, so its contours
        (the wet edge) are cell-shaped and its slope (the lighting) changes in facets; the tent makes it smooth. Each
        pass runs on the tiles whose input changed (sims.look.display_tiles)."""
        height, width = self.blood.shape
        for r, q in ti.ndrange(height, width // self.span):
            for c in range(q * self.span, (q + 1) * self.span):
                if tiles.flagged(r, c, BLOOD_SAMPLE):
                    sr, sc = self._source(r, c)
                    self.blood_raw[r, c] = film.sample(film.trail, sr, sc) if film.is_near(sr, sc) else 0.0
        for r, q in ti.ndrange(height, width // self.span):
            for c in range(q * self.span, (q + 1) * self.span):
                if tiles.flagged(r, c, BLOOD_ROWS):
                    total = 0.0
                    if film.is_near(r, c):
                        for k in ti.static(range(-radius, radius + 1)):  # unrolled: the radius is fixed per scene
                            total += self.blood_raw[r, ti.min(ti.max(c + k, 0), width - 1)] * (radius + 1 - abs(k))
                    self.blood_tmp[r, c] = total / ((radius + 1) * (radius + 1))
        for r, q in ti.ndrange(height, width // self.span):
            for c in range(q * self.span, (q + 1) * self.span):
                if tiles.flagged(r, c, BLOOD_COLUMNS):
                    total = 0.0
                    if film.is_near(r, c):
                        for k in ti.static(range(-radius, radius + 1)):
                            total += self.blood_tmp[ti.min(ti.max(r + k, 0), height - 1), c] * (radius + 1 - abs(k))
                    self.blood[r, c] = total / ((radius + 1) * (radius + 1))

    @ti.kernel
    def _with_blood(self, film: ti.template(), tiles: ti.template()):
        for r, c in self.rgb:  # a loop over texels: heavy texels (walking rows measured 1.1-1.3 times slower for them)
            if not tiles.flagged(r, c, WRITE):
                continue
            sr, sc = self._source(r, c)
            h = self.blood[r, c]
            stain_mm = film.sample(film.stain, sr, sc)
            tissue = self.tissue[sr, sc]
            if h <= 0.0 and stain_mm <= 0.0:  # never wet: the tissue as it is, without the cost of the layer
                self._write(r, c, self.color[sr, sc], tissue[0], tissue[1])
            else:
                stain = 1.0 - ti.exp(-stain_mm / STAIN_MM)
                linear = self.color_linear[sr, sc] * (1.0 - stain * (1.0 - ti.Vector(STAIN_TRANSMITTANCE)))
                if h > 0.0:  # under blood (a dry stain is the ground as it is: a layer of 0 mm changes nothing)
                    clot = film.clot_at(sr, sc)
                    linear = blood_layer(linear, h, FRESH_SATURATION + (CLOT_SATURATION - FRESH_SATURATION) * clot)
                    wet = 1.0 - ti.exp(-h / WET_MM)
                    blood_roughness = BLOOD_ROUGHNESS[0] + (BLOOD_ROUGHNESS[1] - BLOOD_ROUGHNESS[0]) * clot
                    level = _smoothstep(0.0, POOL_LEVEL_MM, h)
                    self._write_surface(r, c, tissue[0] * (1.0 - level) + h, tissue[1] * (1.0 - wet) + blood_roughness * wet)
                else:
                    self._write_surface(r, c, tissue[0], tissue[1])
                for k in ti.static(range(3)):
                    index = ti.cast(ti.min(ti.max(linear[k], 0.0), 1.0) * (ENCODE_STEPS - 1) + 0.5, ti.i32)
                    self.rgb[r, c][k] = self.encode[index]

    @ti.kernel
    def _normals(self, tiles: ti.template(), texel_mm: ti.f32):
        """Normal map from the slope of relief at each texel's fill source (central differences, one-sided at the
        texture's border), on the tiles flagged NORMAL."""
        height, width = self.relief.shape
        for r, q in ti.ndrange(height, width // self.span):
            for c in range(q * self.span, (q + 1) * self.span):
                if not tiles.flagged(r, c, NORMAL):
                    continue
                sr, sc = self._source(r, c)
                left, right = ti.max(sc - 1, 0), ti.min(sc + 1, width - 1)
                up, down = ti.max(sr - 1, 0), ti.min(sr + 1, height - 1)
                slope_x = (self.relief[sr, right] - self.relief[sr, left]) / (ti.max(right - left, 1) * texel_mm)
                slope_y = (self.relief[down, sc] - self.relief[up, sc]) / (ti.max(down - up, 1) * texel_mm)
                n = ti.Vector([-slope_x, slope_y, 1.0]).normalized()
                self.normal[r, c] = ti.cast(ti.min(ti.max(NORMAL_LEVEL + NORMAL_LEVEL * n + 0.5, 0.0), 255.0), ti.u8)
