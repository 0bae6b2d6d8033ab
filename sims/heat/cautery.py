"""Cautery: Pennes bioheat in layers under the surface (lateral conduction with the texel metric, implicit along
each column), the tool as a surface boundary condition, Arrhenius damage and charring in every layer.

Fields: per texel (H, W) in the image orientation of sims.surface.texels, and per layer (H * W, L) with layer 0 at the
surface (sims.heat.layers: L layers down to depth_mm, thin at the top; the outputs give them as (L, H, W)).

Heat: rho c dT/dt = k div grad T + w_b rho_b c_b (T_body - T) in every layer, with
- lateral conduction along each layer: a symmetric graph Laplacian on the 8-neighbour texel grid. The conductance
  tensor K = sqrt|g| g^-1 (grid units) is split into non-negative weights along the two grid axes and one diagonal
  (a - |b|, c - |b|, |b|), so every explicit update is a convex combination of neighbour values: heat is conserved
  exactly (symmetric weights) and the maximum principle holds; diffusion is isotropic in millimetres whatever the
  UV stretch. UV chart seams conduct (sims.surface.seams links, the same in every layer); open mesh borders are insulated.
  The layers share the surface metric (curvature over the few millimetres of depth is neglected).
- conduction between layers, perfusion and the surface exchange: backward Euler along each column, a tridiagonal
  M-matrix eliminated from the bottom up (sims.heat.layers), stable for any dt and thinnest layer.
- the surface: flux into the top layer H (T_ext - T_s) with H = h w(d) + h_air (1 - w(d)) and T_ext their weighted
  temperature (tool tip, air), w(d) falling from 1 at contact (signed distance d <= 0) to 0 at the contact distance.
  The face temperature T_s is eliminated through the top half layer (conductance 2k/dz_0 in series with H), as the
  bench's 3D reference does; T_s is the reported surface temperature and drives the surface damage and char.
- the bottom: held at body temperature at depth_mm, or insulated (cautery.bottom; sims.heat.layers says why).
Time stepping (SCHEMES; scene key `cautery.scheme`): per (sub)step the lateral part, then the column solve (Lie
splitting, first order; both parts are convex, so the step keeps the maximum principle).
  "explicit" (default): forward-Euler lateral substeps, added automatically below the stability limit (which
  depends on the texel size, not on the layers: depth is implicit), at most MAX_SUBSTEPS (SubstepLimit beyond).
  "implicit": one backward-Euler lateral step per layer and time step by Jacobi-preconditioned conjugate gradient
  (matrix-free; sums reduced in a fixed order, so results do not depend on the thread count), unconditionally
  stable; the diffused layer is clamped into its bounds at the step's start (a no-op after a converged solve).
Damage: Omega += exp(ln A - Ea / (R T_K)) dt at the mean of a (sub)step's start and end temperatures, in every layer
and at the surface (the rate from a table, RATE_STEP_C); coagulated fraction 1 - exp(-Omega). Char: char += rate (T - T_char) dt above the charring
temperature, capped at 1. The coagulation depth per texel is the depth down to which Omega >= 1 from the surface (log
Omega linear between the surface and the layer centres).
Cost follows activity (sims.surface.sleep_tiles): only awake tiles are stepped, each down to the deepest layer off its rest
temperature (the steady column under perfusion and air loss) plus a margin; a tile sleeps when every layer is
within sleep_tolerance_c of rest and below the damage threshold, and no energized tool is within reach.
"""
import math

import numpy as np
import taichi as ti

from sims.core import field_io
from sims.heat import layers
from sims.surface.seams import seam_links
from sims.surface.sleep_tiles import TILE, WAKE_HALO_TEXELS, TileSchedule, tile_spheres
from sims.surface.stencil import NEIGHBOURS, direction_coefficients, edge_weights

GAS_CONSTANT = 8.314462618  # J/(mol K)
KELVIN = 273.15
OMEGA_MAX = 1.0e6           # Omega is capped here: 1 - exp(-Omega) is 1 in float32 long before
LOG_OMEGA_FLOOR = -80.0     # log Omega where Omega is 0 (for the depth map)
STABILITY_MARGIN = 0.9      # explicit substep at this fraction of the convexity limit
# Explicit heat substeps a step may take. Past it the implicit scheme is the better choice: an explicit 512^2
# substep costs about 1 ms per layer here, so 256 make a 0.01 s step far slower than real time. The lab's scenes stay far
# below (1-3 at 512^2-1024^2); the slider extremes reach 138 at 1024^2 (k = 5 W/(m K), dt = 0.05 s), 551 at 2048^2.
MAX_SUBSTEPS = 256
CHARRED_LEVEL = 0.5         # char at or above this counts as charred area
SCHEMES = ("explicit", "implicit")  # heat time stepping (sims.scene.config.CAUTERY_SCHEMES lists the same)
CG_TOLERANCE = 1e-5         # implicit: relative residual |r| / |dt alpha L T| to stop at
CG_MAX_ITERATIONS = 500     # implicit: iteration cap (the step stays bounded when it is hit)
# slots of Cautery.sums, the CG scalars (sums reduced in the kernels: r.z, r.r, b.b, p.q)
RZ, RR, BB, PQ, RZ_OLD, ALPHA, LOW, HIGH = range(8)
CG_CHUNK = 64               # texels of a row one thread sums; rows per block in the second reduction stage
SPARE_LAYERS = 2            # layers solved below the deepest one off rest (heat moving down finds a solved layer)
TOOL_DEPTH = 3              # layers solved at least under a tool within reach
# Cautery settings under which a field uniform in depth stays uniform (insulated bottom, no loss to air): the layered
# model then spreads heat exactly as a surface-only model, which the analytic surface references need.
SURFACE_ONLY = {"bottom": "insulated", "surface_loss_w_m2k": 0.0}
MAX_FIELD_BYTES = 1_000_000_000  # bytes of layered fields (two temperature buffers, damage, char) a scene may allocate
# Arrhenius rates are tabulated every RATE_STEP_C from the damage threshold up to RATE_TOP_C (above every temperature the
# sliders allow: tip 400 C) and interpolated linearly: ln rate has slope Ea / (R T^2) <= 0.3 per C above 43 C for the
# presets, so the relative error is below (0.3 RATE_STEP_C)^2 / 8 = 1e-6, and a step costs a lookup, not an exp per
# texel and layer (which was 80 % of a burning step).
RATE_STEP_C = 0.01
RATE_TOP_C = 410.0
RATE_ENTRIES = int(round((RATE_TOP_C - 20.0) / RATE_STEP_C)) + 2  # the lowest damage threshold a slider allows is 20 C


class SubstepLimit(ValueError):
    """The explicit heat scheme would need more than MAX_SUBSTEPS substeps per step; the message says what to change."""


class LayerBudget(ValueError):
    """The layered fields would not fit MAX_FIELD_BYTES; the message says what to change."""


def _flat_columns(values: np.ndarray) -> np.ndarray:
    """(L, H, W) -> (H * W, L) float32, the layout of the layered fields."""
    return np.ascontiguousarray(values.reshape(values.shape[0], -1).T, dtype=np.float32)


def layered_bytes(texture_size: int, layer_count: int) -> int:
    """Bytes of the four layered float32 fields (two temperature buffers, damage, char) at this size."""
    return 16 * int(texture_size) ** 2 * int(layer_count)


def check_layer_budget(texture_size: int, layer_count: int) -> None:
    """LayerBudget when the layered fields would exceed MAX_FIELD_BYTES (e.g. 16 layers at 2048^2: 1.07 GB)."""
    needed = layered_bytes(texture_size, layer_count)
    if needed > MAX_FIELD_BYTES:
        raise LayerBudget(f"{layer_count} layers under {texture_size} x {texture_size} heat texels need {needed / 1e9:.2f} GB "
                          f"(at most {MAX_FIELD_BYTES / 1e9:.2f}); use fewer cautery.layers, a larger cautery.heat_grid_divisor "
                          "or a smaller texture_size")


@ti.data_oriented
class Cautery:
    """Temperature, damage and char in layers under a TissueSurface, heated by InstrumentFields."""

    def __init__(self, surface, tissue: dict, cautery: dict, instruments, scheme: str = "explicit",
                 tolerance: float = CG_TOLERANCE, max_iterations: int = CG_MAX_ITERATIONS):
        """tissue, cautery: parameter dicts (sims.scene.params TISSUE, CAUTERY; `bottom` one of sims.heat.layers.BOTTOMS), read
        again every step (sliders). scheme: one of SCHEMES. tolerance, max_iterations: the implicit CG solve."""
        if scheme not in SCHEMES:
            raise ValueError(f"unknown heat scheme {scheme!r}; expected one of: {', '.join(SCHEMES)}")
        if not (tolerance > 0.0 and max_iterations >= 1):
            raise ValueError(f"need tolerance > 0 and max_iterations >= 1, got {tolerance}, {max_iterations}")
        self.surface, self.tissue, self.cautery, self.instruments = surface, tissue, cautery, instruments
        self.scheme, self.tolerance, self.max_iterations = scheme, float(tolerance), int(max_iterations)
        self.bottom = cautery.get("bottom", "body")
        self.layer_count = int(cautery["layers"])
        self.faces_mm = layers.layer_faces(self.layer_count, float(cautery["depth_mm"]))
        self.layer_depth_mm = layers.layer_centres(self.faces_mm)  # (L,) centre depths
        layers.column_coupling(self.faces_mm, self.bottom)  # checks the bottom condition
        shape = surface.mask.shape
        check_layer_budget(max(shape), self.layer_count)
        self.last_iterations = 0   # CG iterations (implicit, all layers) or substeps (explicit) of the last step
        self.last_residual = 0.0   # implicit: largest relative residual of the last step's layer solves
        deep = (shape[0] * shape[1], self.layer_count)  # (texel r * W + c, layer): a column is contiguous
        self.temperature = ti.field(ti.f32, (2,) + deep)  # C per layer, two buffers: this (sub)step's (current), the next
        self.current = 0
        self.omega_depth = ti.field(ti.f32, deep)
        self.char_depth = ti.field(ti.f32, deep)
        self.surface_temperature = ti.field(ti.f32, shape)  # C, the face at depth 0
        self.omega = ti.field(ti.f32, shape)                # at the surface
        self.char = ti.field(ti.f32, shape)                 # at the surface
        self.coagulation_depth = ti.field(ti.f32, shape)    # mm
        self.mask = ti.field(ti.i32, shape)
        self.inv_area = ti.field(ti.f32, shape)
        self.weights = ti.Vector.field(8, ti.f32, shape)
        self.position = ti.Vector.field(3, ti.f32, shape)
        count = self.layer_count
        self.centre_mm = ti.field(ti.f32, count)
        self.rest = ti.field(ti.f32, count)       # C, the undisturbed column
        self.up = ti.field(ti.f32, count)         # column factors (sims.heat.layers.elimination_tables)
        self.down = ti.field(ti.f32, count)
        self.pivot = ti.field(ti.f32, (count + 1, count))
        self.carry = ti.field(ti.f32, (count + 1, count))
        self.rates = ti.field(ti.f32, RATE_ENTRIES)  # dOmega/dt (1/s) at t_damage + i RATE_STEP_C
        self._rates_key = None
        coefficients = direction_coefficients(surface.metric, surface.mask)
        weights = edge_weights(coefficients, surface.mask)
        link_start, link_to, link_weight = seam_links(surface, coefficients, NEIGHBOURS)
        self.seam_links = len(link_to) // 2  # texel pairs linked across UV seams
        self.link_start = ti.field(ti.i32, len(link_start))
        self.link_to, self.link_weight = ti.field(ti.i32, max(len(link_to), 1)), ti.field(ti.f32, max(len(link_to), 1))
        area = surface.texel_area_mm2
        inv_area = np.where(surface.mask, 1.0 / np.where(surface.mask, area, 1.0), 0.0).astype(np.float32)
        link_sum = np.bincount(np.repeat(np.arange(len(link_start) - 1), np.diff(link_start)), weights=link_weight,
                               minlength=len(link_start) - 1).reshape(shape)
        self.max_exchange_1_mm2 = float(((weights.sum(axis=2) + link_sum) * inv_area).max())  # max over texels of sum(w)/A
        self.tiles = TileSchedule(surface.mask, link_start, link_to, count)
        centre, radius = tile_spheres(surface.position_mm, surface.mask)
        self.tile_centre = ti.Vector.field(3, ti.f32, self.tiles.tiles)
        self.tile_radius = ti.field(ti.f32, self.tiles.tiles)
        self.tile_near = ti.field(ti.i32, self.tiles.tiles)  # 1: an energized tool within reach this step
        field_io.load([(self.centre_mm, self.layer_depth_mm), (self.link_start, link_start), (self.mask, surface.mask),
                       (self.inv_area, inv_area), (self.weights, weights), (self.position, surface.position_mm),
                       (self.tile_centre, centre), (self.tile_radius, radius)]
                      + ([(self.link_to, link_to), (self.link_weight, link_weight)] if len(link_to) else []))
        if scheme == "implicit":  # CG work fields (one layer at a time): layer, increment d, residual r, z, p (2), q
            self.layer = ti.field(ti.f32, shape)
            self.delta, self.residual, self.precond = ti.field(ti.f32, shape), ti.field(ti.f32, shape), ti.field(ti.f32, shape)
            self.product, self.diag = ti.field(ti.f32, shape), ti.field(ti.f32, shape)
            self.direction = ti.field(ti.f32, (2,) + tuple(shape))
            self.sums = ti.field(ti.f32, 8)
            self.groups = -(-shape[1] // CG_CHUNK)  # threads per row in the reducing kernels
            self.blocks = -(-shape[0] // CG_CHUNK)
            self.partial = ti.field(ti.f32, (shape[0], self.groups, 3))  # per thread, then per row, per block of rows
            self.row_sum = ti.field(ti.f32, (shape[0], 3))
            self.block_sum = ti.field(ti.f32, (self.blocks, 3))
            self.interleaved = ti.lang.impl.current_cfg().arch not in (ti.x64, ti.arm64)  # GPU: adjacent threads, adjacent texels
        self._column_key = None  # parameters the column tables were made for
        self._tools_were_near = False  # tile_near may hold ones
        self.version = 0  # counts the steps and settings that changed the fields (metrics() reads them again)
        self._metrics = (-1, {})
        self._wake_everything()
        self.reset()

    # --- parameters ---------------------------------------------------------------------------
    @property
    def diffusivity_mm2_s(self) -> float:
        t = self.tissue
        return t["conductivity_w_mk"] / (t["density_kg_m3"] * t["specific_heat_j_kgk"]) * 1e6

    @property
    def perfusion_rate_1_s(self) -> float:
        t = self.tissue
        return t["perfusion_1_s"] * t["blood_density_kg_m3"] * t["blood_specific_heat_j_kgk"] / (t["density_kg_m3"] * t["specific_heat_j_kgk"])

    @property
    def top_layer_mm(self) -> float:
        return float(self.faces_mm[1])

    @property
    def half_layer_conductance_w_m2k(self) -> float:
        """2 k / dz_0: the conductance from the surface face to the top layer's centre."""
        return 2.0 * self.tissue["conductivity_w_mk"] / (self.top_layer_mm * 1e-3)

    def exchange_rate_1_s(self, conductance_w_m2k: float) -> float:
        """Rate (1/s) at which a surface exchange H relaxes the top layer: H in series with 2k/dz_0, over rho c dz_0."""
        if conductance_w_m2k <= 0:
            return 0.0
        half = self.half_layer_conductance_w_m2k
        series = conductance_w_m2k * half / (conductance_w_m2k + half)
        t = self.tissue
        return series / (t["density_kg_m3"] * t["specific_heat_j_kgk"] * self.top_layer_mm * 1e-3)

    @property
    def contact_rate_1_s(self) -> float:
        """Rate at which full contact (w = 1) relaxes the top layer toward the tip temperature (1/s)."""
        return self.exchange_rate_1_s(self.cautery["contact_conductance_w_m2k"])

    def substeps(self, dt_s: float) -> int:
        """Heat substeps a step of dt_s takes: explicit_substeps(dt_s), or 1 for the implicit scheme.
        Raises SubstepLimit when the explicit scheme would need more than MAX_SUBSTEPS."""
        if self.scheme == "implicit":
            return 1
        count = self.explicit_substeps(dt_s)
        if count > MAX_SUBSTEPS:
            texel_mm = 2.0 / math.sqrt(self.max_exchange_1_mm2)  # a square texel of side h exchanges 4 / h^2
            raise SubstepLimit(f"the explicit heat scheme needs {count:.3g} substeps per {dt_s:g} s step, over the cap of "
                               f"{MAX_SUBSTEPS} (smallest texels about {texel_mm:.2g} mm across); use cautery.scheme=implicit, "
                               "a smaller time_step_s or a smaller texture_size")
        return count

    def explicit_substeps(self, dt_s: float) -> int:
        """Explicit lateral substeps needed for a step of dt_s to stay a convex update."""
        limit = STABILITY_MARGIN / max(self.diffusivity_mm2_s * self.max_exchange_1_mm2, 1e-30)
        return max(1, math.ceil(dt_s / limit))

    def _prepare_rates(self) -> None:
        """The Arrhenius rate table for the current ln A, Ea and damage threshold."""
        t = self.tissue
        key = (t["arrhenius_ln_a"], t["activation_energy_j_mol"], t["damage_threshold_c"])
        if key != self._rates_key:
            self._rates_key = key
            celsius = key[2] + RATE_STEP_C * np.arange(RATE_ENTRIES, dtype=np.float64)
            exponent = np.minimum(key[0] - key[1] / (GAS_CONSTANT * (celsius + KELVIN)), 80.0)
            self.rates.from_numpy(np.exp(exponent).astype(np.float32))

    def _prepare_columns(self, sub_s: float) -> None:
        """Column factors and the rest profile for the current parameters and (sub)step; a change wakes every tile."""
        t, c = self.tissue, self.cautery
        key = (sub_s, self.diffusivity_mm2_s, self.perfusion_rate_1_s, t["body_temperature_c"], t["conductivity_w_mk"],
               t["density_kg_m3"], t["specific_heat_j_kgk"], c["surface_loss_w_m2k"], c["air_temperature_c"])
        if key == self._column_key:
            return
        self._column_key = key
        up, down, pivot, carry = layers.elimination_tables(self.faces_mm, self.bottom, sub_s, self.diffusivity_mm2_s,
                                                           self.perfusion_rate_1_s)
        field_io.load([(self.up, up), (self.down, down), (self.pivot, pivot), (self.carry, carry),
                       (self.rest, self.rest_profile_c())])
        self._wake_everything()

    def rest_profile_c(self) -> np.ndarray:
        """(L,) C: the steady column under perfusion, the bottom and the air loss, no tool."""
        t, c = self.tissue, self.cautery
        return layers.rest_profile(self.faces_mm, self.bottom, self.diffusivity_mm2_s, self.perfusion_rate_1_s,
                                   t["body_temperature_c"], self.exchange_rate_1_s(c["surface_loss_w_m2k"]), c["air_temperature_c"])

    # --- state --------------------------------------------------------------------------------
    def reset(self) -> None:
        """t = 0: every layer at its rest temperature shifted by initial - body temperature, no damage or char."""
        t = self.tissue
        start = self.rest_profile_c() + (t["initial_temperature_c"] - t["body_temperature_c"])
        self.set_temperature(np.broadcast_to(start[:, None, None], (self.layer_count,) + self.surface.mask.shape),
                             also=[(field, 0.0) for field in (self.omega_depth, self.char_depth, self.omega, self.char,
                                                              self.coagulation_depth)])

    def set_temperature(self, values: np.ndarray, also=()) -> None:
        """Set T in C: (H, W) for every layer alike, or (L, H, W) per layer (masked texels stay 0). Wakes every tile.
        also: more (field, value) pairs loaded in the same launch (sims.core.field_io.load)."""
        values = np.asarray(values, np.float32)
        if values.ndim == 2:
            values = np.broadcast_to(values, (self.layer_count,) + values.shape)
        mask = self.surface.mask
        self.current = 0
        columns = _flat_columns(np.where(mask[None], values, 0.0))
        pairs = [(self.temperature, np.stack([columns, columns])), (self.surface_temperature, np.where(mask, values[0], 0.0)),
                 *also]
        if self.scheme == "implicit":
            pairs.append((self.delta, 0.0))  # the implicit solve starts from the last increment; a new state from 0
        field_io.load(pairs)
        self._wake_everything()

    def _wake_everything(self) -> None:
        """The next step steps every tile at full depth, and every tile counts as changed for the look."""
        self._wake_all = True
        self.tiles.mark_all_changed()
        self.version += 1

    def take_changed_tiles(self, temperature: bool) -> np.ndarray:
        """(T,) bool over self.tiles: the tiles whose fields changed since the last call (one reader: the look); with
        temperature False only those whose damage, char or coagulation depth changed (a look that shows no temperature
        needs no other)."""
        return self.tiles.take_changed(temperature)

    def arrays(self) -> dict[str, np.ndarray]:
        """What temperature_c, damage_omega, char_level, coagulation_depth_mm, temperature_depth_c and
        damage_omega_depth return, under those names (char as "char"), read in one launch (field_io.read)."""
        surface_temperature, temperature, omega, char, depth, omega_depth = field_io.read(
            [self.surface_temperature, self.temperature, self.omega, self.char, self.coagulation_depth, self.omega_depth])
        return {"temperature_c": surface_temperature, "damage_omega": omega, "char": char, "coagulation_depth_mm": depth,
                "temperature_depth_c": self._layers(temperature[self.current]), "damage_omega_depth": self._layers(omega_depth)}

    def temperature_c(self) -> np.ndarray:
        """(H, W) C at the surface."""
        return self.surface_temperature.to_numpy()

    def temperature_depth_c(self) -> np.ndarray:
        """(L, H, W) C per layer."""
        return self._layers(self.temperature.to_numpy()[self.current])

    def damage_omega(self) -> np.ndarray:
        """(H, W) Omega at the surface."""
        return self.omega.to_numpy()

    def damage_omega_depth(self) -> np.ndarray:
        """(L, H, W) Omega per layer."""
        return self._layers(self.omega_depth.to_numpy())

    def columns_at(self, rows: np.ndarray, cols: np.ndarray) -> dict[str, np.ndarray]:
        """The burn at N texels (rows, cols: (N,) ints), read in one kernel rather than whole grids: temperature_c and
        omega (L, N) per layer; surface_temperature_c, surface_omega and coagulation_depth_mm (N,)."""
        layers = self.layer_count
        texels = np.ascontiguousarray(np.stack([rows, cols], axis=1), np.int32)
        out = np.zeros((len(texels), 2 * layers + 3), np.float32)
        if len(texels):
            self._gather(texels, out, self.current)
        return {"temperature_c": out[:, :layers].T.copy(), "omega": out[:, layers:2 * layers].T.copy(),
                "surface_temperature_c": out[:, 2 * layers], "surface_omega": out[:, 2 * layers + 1],
                "coagulation_depth_mm": out[:, 2 * layers + 2]}

    @ti.kernel
    def _gather(self, texels: ti.types.ndarray(), out: ti.types.ndarray(), buffer: ti.i32):
        """out[i] = layer temperatures, layer Omegas, surface temperature, surface Omega, coagulation depth at texel i."""
        layers = self.layer_count
        for i in range(texels.shape[0]):
            r, c = texels[i, 0], texels[i, 1]
            f = r * self.mask.shape[1] + c
            for layer in range(layers):
                out[i, layer] = self.temperature[buffer, f, layer]
                out[i, layers + layer] = self.omega_depth[f, layer]
            out[i, 2 * layers] = self.surface_temperature[r, c]
            out[i, 2 * layers + 1] = self.omega[r, c]
            out[i, 2 * layers + 2] = self.coagulation_depth[r, c]

    def _layers(self, values: np.ndarray) -> np.ndarray:
        """(L, H, W) float32 of a layered field's values (H * W, L)."""
        height, width = self.surface.mask.shape
        return np.ascontiguousarray(values.reshape(height, width, self.layer_count).transpose(2, 0, 1))

    def char_level(self) -> np.ndarray:
        """(H, W) char at the surface."""
        return self.char.to_numpy()

    def coagulation_depth_mm(self) -> np.ndarray:
        """(H, W) mm: the depth down to which Omega >= 1 from the surface (log Omega linear between the surface and the
        layer centres; 0 where the surface is not coagulated)."""
        return self.coagulation_depth.to_numpy()

    def awake_fraction(self) -> float:
        """Share of the surface tiles stepped in the last step."""
        return self.tiles.awake_fraction()

    # --- stepping -----------------------------------------------------------------------------
    def step(self, dt_s: float) -> None:
        """Advance dt_s seconds: wake the tiles that need it, surface exchange from the current instrument poses,
        then lateral substeps (explicit) or one lateral solve per layer (implicit), each followed by the column solve."""
        t, c = self.tissue, self.cautery
        count = self.substeps(dt_s)
        sub = dt_s / count
        self._prepare_columns(sub)
        self._prepare_rates()
        reach = c["contact_distance_mm"]
        wake_all = self._wake_all or self.scheme == "implicit"
        if not (wake_all or self.instruments.any_energized or self.tiles.awake):
            self.last_iterations = count
            return  # nothing was awake and nothing can wake a tile: an idle lab costs no kernel
        if self.instruments.any_energized or self._tools_were_near:
            self._want_near_tools(self.tiles.serial, reach, min(TOOL_DEPTH, self.layer_count))
            self._tools_were_near = self.instruments.any_energized
        awake = self.tiles.plan(math.ceil(max(count, WAKE_HALO_TEXELS) / TILE), SPARE_LAYERS, wake_all)
        self._wake_all = False
        if self.tiles.fell_asleep:  # their latest values into the other buffer too (they are not stepped now)
            asleep = self.tiles.fell_asleep
            self._copy_sleeping(self.tiles.serial_for(asleep), self.current, 1 - self.current, asleep)
        self.last_iterations = count
        if awake == 0:
            return
        self.version += 1
        body = t["body_temperature_c"]
        surface = (reach, c["contact_conductance_w_m2k"], c["surface_loss_w_m2k"], c["air_temperature_c"], c["sleep_tolerance_c"])
        column = (body, sub * self.perfusion_rate_1_s, self.half_layer_conductance_w_m2k,
                  t["density_kg_m3"] * t["specific_heat_j_kgk"] * self.top_layer_mm * 1e-3,
                  t["damage_threshold_c"], t["char_temperature_c"], t["char_rate_1_s_c"])
        if self.scheme == "implicit":
            self._implicit_lateral(sub)
            self._substep(self.current, 1 - self.current, awake, False, 1, sub, 0.0,
                          *surface, *column)
            self.current = 1 - self.current
        else:
            for index in range(count):
                self._substep(self.current, 1 - self.current, awake, True,
                              int(index == count - 1), sub, self.diffusivity_mm2_s, *surface, *column)
                self.current = 1 - self.current

    def _implicit_lateral(self, dt_s: float) -> None:
        """Backward Euler for the lateral conduction of every layer (Jacobi-preconditioned CG) into the next buffer."""
        coupling = dt_s * self.diffusivity_mm2_s  # mm^2
        total, worst = 0, 0.0
        for layer in range(self.layer_count):
            self._take_layer(self.current, layer)
            self._cg_start(self.layer, coupling)
            scale, residual = float(self.sums[BB]), float(self.sums[RR])
            iterations = 0
            if scale > 0.0:
                threshold = self.tolerance**2 * scale
                while residual > threshold and iterations < self.max_iterations:
                    old = iterations % 2
                    self._cg_direction(old, 1 - old, coupling)
                    self._cg_update(1 - old)
                    iterations += 1
                    residual = float(self.sums[RR])
                worst = max(worst, math.sqrt(residual / scale))
            else:  # a uniform layer: nothing diffuses
                self.delta.fill(0.0)
            total += iterations
            self._cg_finish(1 - self.current, layer)
        self.last_iterations, self.last_residual = total, worst

    @ti.kernel
    def _want_near_tools(self, serial: ti.template(), reach: ti.f32, depth: ti.i32):
        """Tiles within reach of an energized tool ask for `depth` layers and are marked in tile_near."""
        ti.loop_config(serialize=serial)
        for t in range(self.tiles.tiles):
            near = 0
            if self.tile_radius[t] >= 0.0:
                for k in range(self.instruments.count):
                    gap = (self.tile_centre[t] - self.instruments.position[k]).norm() - self.tile_radius[t]
                    if self.instruments.energized[k] and gap < self.instruments.extent[k] + reach:
                        near = 1
            self.tile_near[t] = near
            if near:
                self.tiles.wanted[t] = depth

    @ti.func
    def _surface_exchange(self, tile, r, c, reach, contact, air, air_c, body):
        """(H in W/(m^2 K), T_ext in C) at a texel: the energized tools within reach (w(d) of their signed distance)
        and the air where they do not touch."""
        touch, heat = 0.0, 0.0
        for k in range(self.instruments.count * self.tile_near[tile]):
            near = (self.position[r, c] - self.instruments.position[k]).norm() < self.instruments.extent[k] + reach
            if self.instruments.energized[k] and near:
                d = self.instruments.distance(k, self.position[r, c])
                w = 0.0
                if d <= 0.0:
                    w = 1.0
                elif d < reach:
                    w = 1.0 - d / reach
                touch += w
                heat += w * self.instruments.tip_temperature[k]
        open_air = air * ti.max(1.0 - touch, 0.0)
        total = contact * touch + open_air
        target = body
        if total > 0.0:
            target = (contact * heat + open_air * air_c) / total
        return total, target

    @ti.kernel
    def _copy_sleeping(self, serial: ti.template(), src: ti.i32, dst: ti.i32, count: ti.i32):
        ti.loop_config(serialize=serial)
        for i, j in ti.ndrange(count, TILE * TILE):
            tile, r, c, inside = self.tiles.texel_of(self.tiles.asleep[i], j)
            if inside:
                f = r * self.mask.shape[1] + c
                for layer in range(self.layer_count):
                    self.temperature[dst, f, layer] = self.temperature[src, f, layer]

    @ti.func
    def _damage_rate(self, mid, t_damage):
        """dOmega/dt (1/s) at temperature mid (C) above the damage threshold, from the rate table."""
        x = ti.min((mid - t_damage) / RATE_STEP_C, RATE_ENTRIES - 1.001)
        i = ti.cast(x, ti.i32)
        a = x - i
        return self.rates[i] * (1.0 - a) + self.rates[i + 1] * a

    @ti.func
    def _column(self, buffer, f):
        """(L,) temperatures of texel f's column in a buffer, unrolled so the column stays in registers."""
        column = ti.Vector.zero(ti.f32, ti.static(self.layer_count))
        for layer in ti.static(range(self.layer_count)):
            column[layer] = self.temperature[buffer, f, layer]
        return column

    @ti.kernel
    def _substep(self, src: ti.i32, dst: ti.i32, awake: ti.i32, explicit: ti.template(), scan: ti.i32,
                 dt: ti.f32, alpha: ti.f32, reach: ti.f32, contact: ti.f32, air: ti.f32, air_c: ti.f32, tolerance: ti.f32,
                 body: ti.f32, perfused: ti.f32, half: ti.f32, rho_c_dz0: ti.f32, t_damage: ti.f32,
                 t_char: ti.f32, char_rate: ti.f32):
        """One (sub)step of the awake tiles, src -> dst: the surface exchange (_surface_exchange), the lateral part
        (explicit: from src's neighbours; otherwise dst already holds it), then the column solve of the solved layers,
        damage and char per layer and at the surface face; the layers below are copied. The step's last substep
        (scan = 1) also scans each column (_scan_column). perfused = dt w (w the perfusion rate), half = 2k/dz_0,
        rho_c_dz0 in J/(m^2 K); reach, contact, air, air_c: contact distance (mm), conductances (W/(m^2 K)) and the
        air's temperature (C); tolerance: the sleep tolerance (C) the scan uses."""
        height, width, count = self.mask.shape[0], self.mask.shape[1], self.layer_count
        for i, j in ti.ndrange(awake, TILE * TILE):
            tile, r, c, inside = self.tiles.texel(i, j)
            if inside and self.mask[r, c]:
                n = self.tiles.depth[tile]
                f = r * width + c
                star = ti.Vector.zero(ti.f32, ti.static(self.layer_count))  # the column after the lateral part
                w = self.weights[r, c]
                scale = dt * alpha * self.inv_area[r, c]
                first, last = self.link_start[f], self.link_start[f + 1]
                around = ti.Vector.zero(ti.i32, 8)  # the neighbours' texel indices (clamped at the texture border)
                for k in ti.static(range(8)):
                    around[k] = ti.min(ti.max(r + NEIGHBOURS[k][0], 0), height - 1) * width + ti.min(ti.max(c + NEIGHBOURS[k][1], 0), width - 1)
                if ti.static(not explicit):
                    star = self._column(dst, f)
                else:  # every layer, solved or not: without a branch per layer the stencil vectorises along the column
                    t0 = self._column(src, f)
                    flux = ti.Vector.zero(ti.f32, ti.static(self.layer_count))
                    for k in ti.static(range(8)):
                        flux += w[k] * (self._column(src, around[k]) - t0)
                    for m in range(first, last):  # seam links (few texels have any)
                        flux += self.link_weight[m] * (self._column(src, self.link_to[m]) - t0)
                    star = t0 + scale * flux
                exchange, target = self._surface_exchange(tile, r, c, reach, contact, air, air_c, body)
                rate = 0.0
                if exchange > 0.0:
                    rate = exchange * half / (exchange + half) / rho_c_dz0
                held = body
                if n < count:
                    held = self.temperature[src, f, n]
                # increment form: M delta = b - M T*, the right side from differences (0 for a column at rest, so
                # rounding scales with the change, and a uniform column with nothing driving it stays exactly uniform)
                rhs = ti.Vector.zero(ti.f32, ti.static(self.layer_count))
                for layer in ti.static(range(self.layer_count)):
                    if layer < n:
                        value = star[layer]
                        above = value
                        if ti.static(layer > 0):
                            above = star[layer - 1]
                        below = held
                        if ti.static(layer < self.layer_count - 1):
                            if layer < n - 1:
                                below = star[layer + 1]
                        rhs[layer] = self.up[layer] * (above - value) + self.down[layer] * (below - value) + perfused * (body - value)
                rhs[0] += dt * rate * (target - star[0])
                for step in ti.static(range(1, self.layer_count)):  # upward: R_l = r_l + carry[n, l] R_{l+1}
                    layer = ti.static(self.layer_count - 1 - step)
                    if layer < n - 1:
                        rhs[layer] += self.carry[n, layer] * rhs[layer + 1]
                above, damaged = 0.0, 0
                for layer in ti.static(range(self.layer_count)):  # downward: delta_l = (R_l + up_l delta_{l-1}) / pivot[n, l]
                    if layer < n:
                        pivot = self.pivot[n, layer]
                        if layer == 0:
                            pivot += dt * rate
                        change = (rhs[layer] + self.up[layer] * above) / pivot
                        t1 = star[layer] + change
                        self.temperature[dst, f, layer] = t1
                        mid = 0.5 * (self.temperature[src, f, layer] + t1)
                        if mid > t_damage:
                            self.omega_depth[f, layer] = ti.min(self.omega_depth[f, layer] + self._damage_rate(mid, t_damage) * dt, OMEGA_MAX)
                            damaged = 1
                        if mid > t_char:
                            self.char_depth[f, layer] = ti.min(self.char_depth[f, layer] + char_rate * (mid - t_char) * dt, 1.0)
                            damaged = 1
                        above = change
                for layer in range(n, count):
                    self.temperature[dst, f, layer] = self.temperature[src, f, layer]
                s0 = self.surface_temperature[r, c]
                s1 = (exchange * target + half * self.temperature[dst, f, 0]) / (exchange + half)
                self.surface_temperature[r, c] = s1
                mid = 0.5 * (s0 + s1)
                if mid > t_damage:
                    self.omega[r, c] = ti.min(self.omega[r, c] + self._damage_rate(mid, t_damage) * dt, OMEGA_MAX)
                    damaged = 1
                if mid > t_char:
                    self.char[r, c] = ti.min(self.char[r, c] + char_rate * (mid - t_char) * dt, 1.0)
                    damaged = 1
                if damaged:
                    self.tiles.damaged[tile] = 1  # the same value from every writer
                if scan:
                    self._scan_column(dst, tile, r, c, f, n, tolerance, t_damage)

    @ti.func
    def _log_omega(self, omega):
        value = LOG_OMEGA_FLOOR
        if omega > 0.0:
            value = ti.log(omega)
        return value

    @ti.func
    def _scan_column(self, buffer, tile, r, c, f, n, tolerance, t_damage):
        """After a step, at one texel of tile: the deepest layer off rest or above the damage threshold (into
        tiles.hot), and the coagulation depth: from the surface down to where log Omega, linear between the surface and
        the layer centres, falls below 0."""
        for step in range(n):
            layer = n - 1 - step
            value = self.temperature[buffer, f, layer]
            if ti.abs(value - self.rest[layer]) > tolerance or value > t_damage:  # off rest, or taking damage
                ti.atomic_max(self.tiles.hot[tile], layer)
                break
        depth, z_prev = 0.0, 0.0
        omega_prev = self.omega[r, c]
        if omega_prev >= 1.0:
            for layer in range(self.layer_count):  # logarithms only at the crossing: most burnt texels have several layers coagulated
                z, omega = self.centre_mm[layer], self.omega_depth[f, layer]
                if omega < 1.0:
                    f_prev, value = self._log_omega(omega_prev), self._log_omega(omega)
                    depth = z_prev + (z - z_prev) * f_prev / (f_prev - value)
                    break
                depth, z_prev, omega_prev = z, z, omega
        self.coagulation_depth[r, c] = depth

    # --- implicit lateral step: (A + k L) d = -k L T per layer, k = dt alpha, by Jacobi-preconditioned CG ------
    # (M d)_i = (A_i + k sum_j w_ij) d_i - k sum_j w_ij d_j is symmetric positive definite (w_ij = w_ji >= 0,
    # A_i > 0). The reducing kernels loop over (row, group): each thread sums CG_CHUNK texels of its row
    # (_chunk_column) into `partial`; _reduce then adds those up per row, per block of rows and in
    # total, each in a fixed order: the sums (so every result) are the same whatever the thread count,
    # and float32 sums never have more than a few dozen terms.
    @ti.func
    def _chunk_column(self, group, j):
        """Column of the j-th texel of a thread's chunk: contiguous on a CPU, interleaved on a GPU (coalesced reads)."""
        column = group * CG_CHUNK + j
        if ti.static(self.interleaved):
            column = j * self.groups + group
        return column

    @ti.func
    def _reduce(self, first: ti.template(), count: ti.template()):
        """sums[first + s] = the sum of partial[:, :, s] for s < count, in a fixed order (three stages)."""
        for r in range(self.mask.shape[0]):
            for s in ti.static(range(count)):
                total = 0.0
                for g in range(self.groups):
                    total += self.partial[r, g, s]
                self.row_sum[r, s] = total
        for b in range(self.blocks):
            for s in ti.static(range(count)):
                total = 0.0
                for j in range(CG_CHUNK):
                    row = b * CG_CHUNK + j
                    if row < self.mask.shape[0]:
                        total += self.row_sum[row, s]
                self.block_sum[b, s] = total
        ti.loop_config(serialize=True)
        for _ in range(1):
            for s in ti.static(range(count)):
                total = 0.0
                for b in range(self.blocks):
                    total += self.block_sum[b, s]
                self.sums[first + s] = total

    @ti.kernel
    def _cg_start(self, temperature: ti.template(), coupling: ti.f32):
        """Right-hand side b = -k L T, residual of the warm start d (last step's), z = r / diag; bounds of T."""
        for k in ti.static(range(8)):
            self.sums[k] = 0.0  # RZ_OLD = 0: the first direction is p = z
        self.sums[LOW] = 3.0e38
        self.sums[HIGH] = -3.0e38
        height, width, groups = self.mask.shape[0], self.mask.shape[1], ti.static(self.groups)
        for r, g in ti.ndrange(height, groups):
            rz, rr, bb, low, high = 0.0, 0.0, 0.0, 3.0e38, -3.0e38
            for j in range(CG_CHUNK):
                c = self._chunk_column(g, j)
                if c < width and self.mask[r, c]:
                    t0 = temperature[r, c]
                    w = self.weights[r, c]
                    flux, total, spread = 0.0, 0.0, 0.0
                    for k in ti.static(range(8)):
                        rn = ti.min(ti.max(r + NEIGHBOURS[k][0], 0), height - 1)
                        cn = ti.min(ti.max(c + NEIGHBOURS[k][1], 0), width - 1)
                        flux += w[k] * (temperature[rn, cn] - t0)
                        total += w[k]
                        spread += w[k] * self.delta[rn, cn]
                    for m in range(self.link_start[r * width + c], self.link_start[r * width + c + 1]):
                        jr, jc, wl = self.link_to[m] // width, self.link_to[m] % width, self.link_weight[m]
                        flux += wl * (temperature[jr, jc] - t0)
                        total += wl
                        spread += wl * self.delta[jr, jc]
                    rhs = coupling * flux
                    diag = 1.0 / self.inv_area[r, c] + coupling * total
                    res = rhs - (diag * self.delta[r, c] - coupling * spread)
                    z = res / diag
                    self.diag[r, c] = diag
                    self.residual[r, c] = res
                    self.precond[r, c] = z
                    rz += res * z
                    rr += res * res
                    bb += rhs * rhs
                    low = ti.min(low, t0)
                    high = ti.max(high, t0)
            self.partial[r, g, 0] = rz
            self.partial[r, g, 1] = rr
            self.partial[r, g, 2] = bb
            ti.atomic_min(self.sums[LOW], low)  # min and max are exact: any order gives the same
            ti.atomic_max(self.sums[HIGH], high)
        self._reduce(RZ, 3)  # RZ, RR, BB

    @ti.kernel
    def _cg_direction(self, old: ti.i32, new: ti.i32, coupling: ti.f32):
        """p = z + beta p_old (computed for the texel and its neighbours), q = M p, sum p.q."""
        height, width, groups = self.mask.shape[0], self.mask.shape[1], ti.static(self.groups)
        for r, g in ti.ndrange(height, groups):
            beta = self.sums[RZ] / self.sums[RZ_OLD] if self.sums[RZ_OLD] > 0.0 else 0.0
            pq = 0.0
            for j in range(CG_CHUNK):
                c = self._chunk_column(g, j)
                if c < width and self.mask[r, c]:
                    p = self.precond[r, c] + beta * self.direction[old, r, c]
                    w = self.weights[r, c]
                    spread = 0.0
                    for k in ti.static(range(8)):
                        rn = ti.min(ti.max(r + NEIGHBOURS[k][0], 0), height - 1)
                        cn = ti.min(ti.max(c + NEIGHBOURS[k][1], 0), width - 1)
                        spread += w[k] * (self.precond[rn, cn] + beta * self.direction[old, rn, cn])
                    for m in range(self.link_start[r * width + c], self.link_start[r * width + c + 1]):
                        jr, jc = self.link_to[m] // width, self.link_to[m] % width
                        spread += self.link_weight[m] * (self.precond[jr, jc] + beta * self.direction[old, jr, jc])
                    q = self.diag[r, c] * p - coupling * spread
                    self.direction[new, r, c] = p
                    self.product[r, c] = q
                    pq += p * q
            self.partial[r, g, 0] = pq
        self._reduce(PQ, 1)

    @ti.kernel
    def _cg_update(self, new: ti.i32):
        """d += a p, r -= a q with a = r.z / p.q; z = r / diag; sums r.z and r.r."""
        pq = self.sums[PQ]
        self.sums[ALPHA] = self.sums[RZ] / pq if pq > 0.0 else 0.0
        self.sums[RZ_OLD] = self.sums[RZ]
        width, groups = self.mask.shape[1], ti.static(self.groups)
        for r, g in ti.ndrange(self.mask.shape[0], groups):
            a = self.sums[ALPHA]
            rz, rr = 0.0, 0.0
            for j in range(CG_CHUNK):
                c = self._chunk_column(g, j)
                if c < width and self.mask[r, c]:
                    self.delta[r, c] += a * self.direction[new, r, c]
                    res = self.residual[r, c] - a * self.product[r, c]
                    z = res / self.diag[r, c]
                    self.residual[r, c] = res
                    self.precond[r, c] = z
                    rz += res * z
                    rr += res * res
            self.partial[r, g, 0] = rz
            self.partial[r, g, 1] = rr
        self._reduce(RZ, 2)  # RZ, RR

    @ti.kernel
    def _take_layer(self, buffer: ti.i32, layer: ti.i32):
        for r, c in self.layer:
            self.layer[r, c] = self.temperature[buffer, r * self.mask.shape[1] + c, layer]

    @ti.kernel
    def _cg_finish(self, buffer: ti.i32, layer: ti.i32):
        """The layer plus d, clamped into the layer's bounds at the step's start (maximum principle), into temperature buffer `buffer`."""
        for r, c in self.layer:
            if self.mask[r, c]:
                t1 = self.layer[r, c] + self.delta[r, c]
                if t1 < self.sums[LOW]:  # comparisons, not min/max: a NaN stays NaN (and is reported)
                    t1 = self.sums[LOW]
                if t1 > self.sums[HIGH]:
                    t1 = self.sums[HIGH]
                self.temperature[buffer, r * self.mask.shape[1] + c, layer] = t1

    # --- outputs ------------------------------------------------------------------------------
    def metrics(self) -> dict:
        """metrics.json `cautery`; the fields are read again only when a step changed them (version)."""
        if self._metrics[0] != self.version:
            mask, area = self.surface.mask, self.surface.texel_area_mm2.astype(np.float64)
            depth = self.coagulation_depth_mm().astype(np.float64)
            self._metrics = (self.version, {
                "max_temperature_c": float(self.temperature_c()[mask].max()),
                "coagulated_area_mm2": float(area[self.damage_omega() >= 1.0].sum()),
                "charred_area_mm2": float(area[self.char_level() >= CHARRED_LEVEL].sum()),
                "coagulation_depth_mm": float(depth[mask].max()),
                "coagulated_volume_mm3": float((area * depth)[mask].sum()),
            })
        return {**self._metrics[1], "layers": self.layer_count, "top_layer_mm": self.top_layer_mm,
                "awake_tiles": self.awake_fraction()}
