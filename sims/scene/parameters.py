"""The numbers a scene offers to change (Scene.parameters): their table, their values, and a live change reaching the
model that reads it (sims.scene.models.SceneModel.set). A mixin of sims.scene.assembly.Scene."""
from dataclasses import dataclass

from sims.scene import params
from sims.scene.checked import Refused, checked_number

# Parameters a scene offers (see Scene.parameters): (key prefix in the config, spec table, names that need a rebuild);
# a prefix other than "" is a section of the model that reads it (sims.scene.models). duration_s is left out: it only
# ends headless runs.
_PARAMETER_GROUPS = (
    ("", {name: spec for name, spec in params.SIMULATION.items() if name != "duration_s"}, {"texture_size"}),
    ("tissue", params.TISSUE, set()),
    ("cautery", params.CAUTERY, {"layers", "depth_mm", "heat_grid_divisor"}),
    ("bleeding", None, None),  # the table and rebuild keys of the scene's bleeding method (sims.blood.methods)
    ("look", params.LOOK, set()),
)
SHAPE_PARAMETERS = {"ball": ("radius_mm",), "capsule": ("radius_mm", "length_mm"), "spatula": ("width_mm", "thickness_mm", "length_mm"),
                    "mesh": ("sdf_resolution",)}


@dataclass(frozen=True)
class SceneParameter:
    """One number a scene offers to change. live: the models read it every step (Scene.set_parameter applies it);
    otherwise the scene must be rebuilt with it (config_key as an override). config_key: the dotted key in the scene
    config (the --set syntax), None for a bleed point or tool added at run time."""

    spec: params.ParamSpec
    live: bool
    config_key: str | None


class SceneParameters:
    """Scene's parameter registry (it reads self.config, self.instruments, self.bleed_points and the scene's models)."""

    def parameters(self) -> dict[str, SceneParameter]:
        """Every number this scene offers to change, by key: `time_step_s`, `tissue.<name>`, `cautery.<name>`,
        `bleeding.<name>`, `instruments.<tool>.tip_temperature_c`, `instruments.<tool>.shape.<name>`,
        `instruments.<tool>.suction.<name>`, `bleed_points.<point>.<name>` (tools and points by name). The table is
        made again only when a tool or a bleed point comes or goes."""
        layout = (tuple(tool.name for tool in self.instruments), tuple(point.name for point in self.bleed_points))
        if self._parameters is None or self._parameters[0] != layout:
            self._parameters = (layout, self._parameter_table())
        return self._parameters[1]

    def _parameter_table(self) -> dict[str, SceneParameter]:
        table = {}
        for group, specs, rebuild in _PARAMETER_GROUPS:
            if group and self._reader(group) is None:
                continue
            if group == "bleeding":
                from sims.blood.methods import REBUILD_KEYS

                method = self.config["bleeding"]["method"]
                specs, rebuild = params.BLEEDING_METHODS[method], REBUILD_KEYS[method]
            for name, spec in specs.items():
                key = f"{group}.{name}" if group else name
                table[key] = SceneParameter(spec, name not in rebuild, key)
        in_file = {item["name"]: index for index, item in enumerate(self.config["instruments"])}
        for tool in self.instruments:
            index = in_file.get(tool.name)
            prefix = None if index is None else f"instruments.{index}"
            if tool.suction is None:
                table[f"instruments.{tool.name}.tip_temperature_c"] = SceneParameter(
                    params.INSTRUMENT["tip_temperature_c"], True, prefix and f"{prefix}.tip_temperature_c")
            else:
                for name, spec in params.SUCTION.items():
                    table[f"instruments.{tool.name}.suction.{name}"] = SceneParameter(spec, True, prefix and f"{prefix}.suction.{name}")
            if index is not None:
                for name in SHAPE_PARAMETERS[tool.shape["type"]]:
                    table[f"instruments.{tool.name}.shape.{name}"] = SceneParameter(params.SHAPE[name], False, f"{prefix}.shape.{name}")
        for point in self.bleed_points:
            index = self._file_index(point)
            for name, spec in params.BLEED_POINT.items():
                table[f"bleed_points.{point.name}.{name}"] = SceneParameter(spec, True, None if index is None else f"bleed_points.{index}.{name}")
        return table

    def parameter_value(self, key: str):
        """The current value of a parameter of `parameters()`."""
        group, _, rest = key.partition(".")
        if group == "instruments":
            tool_name, _, name = rest.partition(".")
            tool = self.instrument(tool_name)
            if name == "tip_temperature_c":
                return tool.base.tip_temperature_c
            part, _, name = name.partition(".")
            return (tool.shape if part == "shape" else tool.suction)[name]
        if group == "bleed_points":
            point_name, _, name = rest.partition(".")
            return self.bleed_point(point_name).item[name]
        return self.config[group][rest] if rest else self.config[group]

    def set_parameter(self, key: str, value) -> dict:
        """Set a live parameter of `parameters()` from the next step on. Returns {config key: value} of what changed in
        the scene config (to keep as overrides for a rebuild). A tool's tip temperature and a bleed point's rate hold
        from now on: keyframes that set them are dropped. Raises Refused for an unknown or rebuild-only key, a value
        that is not a finite number or outside the range."""
        parameter = self.parameters().get(key)
        if parameter is None:
            raise Refused(f"{key}: not a parameter of this scene")
        if not parameter.live:
            raise Refused(f"{key}: takes a rebuild of the scene")
        value = checked_number(parameter.spec, value)
        group, _, rest = key.partition(".")
        changed = {parameter.config_key: value}
        if group == "instruments":
            tool_name, _, name = rest.partition(".")
            tool = self.instrument(tool_name)
            if name == "tip_temperature_c":
                tool.base.tip_temperature_c = value
                changed.update(self._drop_keyframes(tool.path, "tip_temperature_c", parameter.config_key))
            else:
                tool.suction[name.partition(".")[2]] = value
        elif group == "bleed_points":
            point_name, _, name = rest.partition(".")
            point = self.bleed_point(point_name)
            point.item[name] = value
            if name == "rate_ml_s":
                changed.update(self._drop_keyframes(point.item["path"], "rate_ml_s", parameter.config_key))
        elif rest:
            self._reader(group).set(key, value)
        else:
            self.config[group] = value
        return {config_key: item for config_key, item in changed.items() if config_key is not None}

    @staticmethod
    def _drop_keyframes(path: list, name: str, config_key: str | None) -> dict:
        """Unset `name` in every keyframe of path (a slider's value holds from now on); {path config key: path}."""
        if not any(frame.get(name) is not None for frame in path):
            return {}
        for frame in path:
            frame[name] = None
        return {} if config_key is None else {config_key.rsplit(".", 1)[0] + ".path": [dict(frame) for frame in path]}
