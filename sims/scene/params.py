"""Parameter specs (name, unit, default, range, help), shared by scene files, --set and sliders."""
from __future__ import annotations

import math
from dataclasses import dataclass

from sims.core.quoting import quote


@dataclass(frozen=True)
class ParamSpec:
    """One tunable number. `integer` params accept only whole numbers."""

    name: str
    unit: str
    default: float
    min: float
    max: float
    help: str
    integer: bool = False

    def check(self, value) -> str | None:
        """Return what is wrong with `value`, or None when it is acceptable."""
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            return f"expected a number ({self.unit}), got {type(value).__name__} {quote(value)}"
        if isinstance(value, float) and not math.isfinite(value):  # (math.isfinite overflows on a huge int)
            return f"must be finite, got {value}"
        if self.integer and int(value) != value:
            return f"must be a whole number, got {value}"
        if not self.min <= value <= self.max:
            return f"{quote(value)} is outside [{self.min:g}, {self.max:g}] {self.unit}"
        return None


def _table(*specs: ParamSpec) -> dict[str, ParamSpec]:
    return {spec.name: spec for spec in specs}


SIMULATION = _table(
    ParamSpec("texture_size", "texels", 512, 16, 2048, "simulation texels per side of the texture", integer=True),
    ParamSpec("time_step_s", "s", 0.01, 1e-4, 0.05, "simulation time step; heat substeps are added automatically"),
    ParamSpec("duration_s", "s", 10.0, 0.0, 3600.0, "length of a headless run"),
)

TISSUE = _table(
    ParamSpec("density_kg_m3", "kg/m^3", 1079.0, 500.0, 2000.0, "tissue density rho"),
    ParamSpec("specific_heat_j_kgk", "J/(kg K)", 3540.0, 1000.0, 5000.0, "tissue specific heat c"),
    ParamSpec("conductivity_w_mk", "W/(m K)", 0.52, 0.05, 5.0, "tissue thermal conductivity k"),
    ParamSpec("perfusion_1_s", "1/s", 3.6e-3, 0.0, 0.05, "blood perfusion rate w_b (Pennes)"),
    ParamSpec("blood_density_kg_m3", "kg/m^3", 1000.0, 900.0, 1200.0, "perfusing blood density rho_b"),
    ParamSpec("blood_specific_heat_j_kgk", "J/(kg K)", 3639.0, 3000.0, 4500.0, "perfusing blood specific heat c_b"),
    ParamSpec("body_temperature_c", "C", 37.0, 0.0, 45.0, "arterial blood temperature T_body"),
    ParamSpec("initial_temperature_c", "C", 37.0, 0.0, 60.0, "tissue temperature at t = 0"),
    ParamSpec("arrhenius_ln_a", "ln(1/s)", math.log(7.39e39), 10.0, 250.0, "natural log of the Arrhenius frequency factor A"),
    ParamSpec("activation_energy_j_mol", "J/mol", 2.577e5, 5.0e4, 8.0e5, "Arrhenius activation energy Ea"),
    ParamSpec("damage_threshold_c", "C", 43.0, 20.0, 100.0,
              "Arrhenius damage accumulates only above this temperature (the fitted A, Ea do not hold near body temperature)"),
    ParamSpec("char_temperature_c", "C", 180.0, 100.0, 400.0, "charring starts above this temperature"),
    ParamSpec("char_rate_1_s_c", "1/(s C)", 0.02, 0.0, 1.0, "char growth per second per degree above the charring temperature"),
)

CAUTERY = _table(
    ParamSpec("contact_conductance_w_m2k", "W/(m^2 K)", 5000.0, 100.0, 1.0e5, "tool-tissue contact conductance h"),
    ParamSpec("contact_distance_mm", "mm", 0.3, 0.0, 3.0, "gap over which contact heating fades to zero"),
    ParamSpec("layers", "layers", 8, 1, 32, "temperature layers under each texel, thin at the surface and growing with depth", integer=True),
    ParamSpec("depth_mm", "mm", 6.0, 0.5, 30.0, "depth of the deepest layer's bottom (held at body temperature or insulated: cautery.bottom)"),
    ParamSpec("surface_loss_w_m2k", "W/(m^2 K)", 10.0, 0.0, 100.0,
              "heat transfer to the air where no tool touches (radiation and natural convection: 9.7 measured by Scott et al. 1990)"),
    ParamSpec("air_temperature_c", "C", 22.0, 0.0, 40.0, "operating-room air temperature"),
    ParamSpec("heat_grid_divisor", "x", 2, 1, 8,
              "display texels per heat texel along a side: heat and its layers run on a texture_size / divisor grid, "
              "read on the display grid by bilinear taps", integer=True),
    ParamSpec("sleep_tolerance_c", "C", 0.05, 0.0, 2.0, "tiles whose every layer is this close to its rest temperature are not stepped"),
)

# Keys older scenes may hold that no longer mean anything: loading says so and goes on.
RETIRED = {
    "cautery.heated_layer_mm": "the tool's heat now enters the top of layers in depth (cautery.layers, cautery.depth_mm); "
                               "the key is ignored",
    "bleeding.display_fade_s": "the picture is not physics: it moved to look.blood_trail_s (on simulated time); the key is ignored",
}

INSTRUMENT = _table(
    ParamSpec("tip_temperature_c", "C", 250.0, 20.0, 400.0, "temperature of the energized instrument surface"),
    ParamSpec("roll_deg", "deg", 0.0, -360.0, 360.0, "rotation of the instrument about its axis"),
)

SHAPE = _table(
    ParamSpec("radius_mm", "mm", 1.5, 0.05, 20.0, "ball or capsule radius"),
    ParamSpec("length_mm", "mm", 10.0, 0.1, 200.0, "capsule segment or spatula blade length"),
    ParamSpec("width_mm", "mm", 3.0, 0.05, 50.0, "spatula blade width"),
    ParamSpec("thickness_mm", "mm", 0.5, 0.02, 10.0, "spatula blade thickness"),
    ParamSpec("sdf_resolution", "cells", 40, 8, 128, "mesh instrument distance-grid cells along the longest side", integer=True),
)

BLEEDING = _table(
    ParamSpec("particle_spacing_mm", "mm", 0.5, 0.1, 3.0, "rest spacing of blood particles; sets the volume each carries"),
    ParamSpec("interaction_radius_mm", "mm", 1.5, 0.2, 10.0, "SPH interaction radius h"),
    ParamSpec("film_thickness_mm", "mm", 0.3, 0.02, 2.0, "blood film thickness at rest density"),
    ParamSpec("rest_density", "x lattice", 1.0, 0.2, 50.0, "rest density, in units of the density of a hexagonal lattice at the particle spacing"),
    ParamSpec("stiffness_mm_s2", "mm/s^2", 2000.0, 0.0, 1.0e5, "pressure stiffness k (double density relaxation)"),
    ParamSpec("near_stiffness_mm_s2", "mm/s^2", 2000.0, 0.0, 1.0e5, "near-pressure stiffness k_near"),
    ParamSpec("viscosity_sigma_1_s", "1/s", 2.0, 0.0, 100.0, "linear viscosity impulse sigma"),
    ParamSpec("viscosity_beta_s_mm", "s/mm", 0.05, 0.0, 10.0, "quadratic viscosity impulse beta"),
    ParamSpec("blood_viscosity_mpa_s", "mPa s", 3.5, 0.0, 50.0, "dynamic viscosity; with the film thickness it sets the drag of the tissue on the film (Nusselt)"),
    ParamSpec("blood_density_kg_m3", "kg/m^3", 1050.0, 900.0, 1200.0, "blood density"),
    ParamSpec("inertia", "", 1.0, 0.0, 1.0, "traction factor I: velocity = I * displacement / dt"),
    ParamSpec("max_speed_mm_s", "mm/s", 200.0, 1.0, 1.0e5, "velocity clamp"),
    ParamSpec("pinning_density", "x rest", 0.0, 0.0, 1.0, "blood thinner than this (relative to rest density) is held by the tissue: a minimum amount before it moves"),
    ParamSpec("clotting_rate_1_s", "1/s", 0.1, 0.0, 10.0, "how fast blood at rest clots and stops"),
    ParamSpec("rest_speed_mm_s", "mm/s", 1.0, 0.0, 50.0, "blood slower than this counts as at rest for clotting"),
    ParamSpec("lifetime_s", "s", 600.0, 0.1, 36000.0, "particles older than this expire"),
    ParamSpec("substeps", "", 2, 1, 16, "fluid substeps per simulation step", integer=True),
    ParamSpec("capacity", "particles", 0, 0, 2_000_000, "particle pool size; 0 sizes it from the bleed rates, duration and lifetime", integer=True),
)

# The height-field bleeding method (sims.blood.height_field); keys that mean the same as the particles' keep their names.
HEIGHT_FIELD = _table(
    ParamSpec("film_thickness_mm", "mm", 0.3, 0.02, 2.0, "reference depth of the display (the composer draws depth in units of it)"),
    ParamSpec("blood_viscosity_mpa_s", "mPa s", 3.5, 0.0, 50.0, "dynamic viscosity; sets the laminar film drag 3 nu / h^2"),
    ParamSpec("blood_density_kg_m3", "kg/m^3", 1050.0, 900.0, 1200.0, "blood density"),
    ParamSpec("pinning_depth_mm", "mm", 0.02, 0.0, 1.0, "blood shallower than this does not flow out of a texel: a front stops, rivulets form"),
    ParamSpec("clotting_rate_1_s", "1/s", 0.1, 0.0, 10.0, "how fast blood at rest clots and stops"),
    ParamSpec("rest_speed_mm_s", "mm/s", 1.0, 0.0, 50.0, "blood slower than this counts as at rest for clotting"),
    ParamSpec("lifetime_s", "s", 600.0, 0.1, 36000.0, "blood dries exponentially with this time constant"),
    ParamSpec("cfl", "", 0.6, 0.05, 0.65, "substeps are added so that the fastest wave crosses this fraction of the shortest pipe per "
              "substep (explicit gravity waves: grid-scale noise grows above about 0.73)"),
    ParamSpec("max_substeps", "", 64, 1, 512, "upper bound of the automatic substep count per step", integer=True),
    ParamSpec("grid_divisor", "x", 8, 1, 8, "blood runs on a grid this many times coarser than the display texture "
              "(the display reads it bilinearly); fewer texels and fewer substeps", integer=True),
)

# Bleeding methods (scene key bleeding.method) and their parameter tables; the first is what a scene that names no
# method gets: the height field, the bench's choice (it pools and thins out, within 2 % of Nusselt's film and the level
# pool, and costs what its wetted area costs; docs/model/blood.md "Choosing a method"). A scene written for the particles
# without naming them is refused at its first particle key, with the method named.
BLEEDING_METHODS = {"height_field": HEIGHT_FIELD, "particles": BLEEDING}

# The look (sims.look.compose, sims.look.film): what only the picture depends on.
LOOK = _table(
    ParamSpec("blood_trail_s", "s", 0.2, 0.0, 5.0, "the look keeps traces of moving blood for about this long (simulated time)"),
)

BLEED_POINT = _table(
    ParamSpec("rate_ml_s", "ml/s", 0.02, 0.0, 10.0, "bleeding rate before coagulation at the point"),
    ParamSpec("radius_mm", "mm", 0.5, 0.0, 10.0, "radius of the disk new blood appears in"),
)

SUCTION = _table(
    ParamSpec("radius_mm", "mm", 3.0, 0.1, 30.0, "suction reach from the instrument position"),
    ParamSpec("rate_ml_s", "ml/s", 1.0, 0.0, 100.0, "largest volume removed per second"),
)

# Tissue presets: physical values (docs/model/heat.md, "Tissue data and presets"). Liver: Arrhenius after the widely used
# liver values; skin: Henriques' A and Ea with IT'IS-database thermal properties.
TISSUE_PRESETS: dict[str, dict[str, float]] = {
    "liver": {name: spec.default for name, spec in TISSUE.items()},
    "skin": {
        **{name: spec.default for name, spec in TISSUE.items()},
        "density_kg_m3": 1109.0,
        "specific_heat_j_kgk": 3391.0,
        "conductivity_w_mk": 0.37,
        "perfusion_1_s": 1.8e-3,
        "arrhenius_ln_a": math.log(3.1e98),
        "activation_energy_j_mol": 6.28e5,
    },
}
