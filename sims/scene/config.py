"""Scene files: YAML -> validated, defaults-filled dict. Every error names the file and the dotted key.

`cautery.scheme` (optional, default explicit) picks the heat time stepping of the cautery model:
`explicit` (automatic substeps below the stability limit) or `implicit` (one backward-Euler step per
time step, conjugate gradient), e.g. `cautery: {scheme: implicit}` or `--set cautery.scheme=implicit`.
`cautery.bottom` (optional, default body): below the deepest heat layer the tissue is held at body temperature
(`body`) or insulated (`insulated`). `bleeding.method` (optional, default height_field) picks the bleeding method
(`particles` or `height_field`, sims.blood.methods); the other `bleeding` keys are that method's parameters.
Keys in sims.scene.params.RETIRED load with a note in config["notes"] and are ignored.
"""
from __future__ import annotations

import copy
import difflib
import math
import re
import stat
from pathlib import Path

import yaml

from sims.core.quoting import quote
from sims.scene import params
from sims.scene.models import MODELS  # the names a scene file may list under `models`

REPO_ROOT = Path(__file__).resolve().parents[2]
MAX_SCENE_BYTES = 1_000_000  # a scene file is a page of YAML; anything larger is refused before it is read
# YAML aliases repeat a node without repeating its text: 380 bytes can stand for a billion strings ("billion laughs").
# Counted as characters of scalars plus one per node, a scene without aliases comes to at most twice its bytes
# (`{a, b}`: each key adds a null); one whose aliases expand it further, or that nests deeper, is refused.
MAX_EXPANDED = 4 * MAX_SCENE_BYTES
MAX_DEPTH = 32  # nesting of YAML collections (a scene nests 6 deep; PyYAML's composer recurses, 1000 deep overflows)
KEY_CHARS = 120  # of a dotted key shown in a message (the longest a scene has is under 50)
NAME_PATTERN = re.compile(r"[A-Za-z0-9_\-]{1,64}")
STAGE_FIELDS = ("coagulation", "char", "omega", "temperature_c", "coagulation_depth_mm")
SHAPE_TYPES = ("ball", "capsule", "spatula", "mesh")
CAUTERY_SCHEMES = ("explicit", "implicit")  # = sims.heat.cautery.SCHEMES (not imported here: that imports Taichi)
CAUTERY_BOTTOMS = ("body", "insulated")  # = sims.heat.layers.BOTTOMS
# The liver's look (tools/make_static.py makes the textures; their colours are cited there): healthy capsule, the
# hyperaemic rim where damage has begun (Omega 0.001-0.03: tissue that stayed near 45-50 C), the pale crest at the
# coagulum's margin, the tan coagulum where it is 0.1-0.45 mm deep, browner where the burn is deeper, black-brown
# char. Coagulum and char sit lower than the capsule (shrinkage); char stands up as a cracked crust within that.
_HEALTHY_SURFACE = {"surface": "textures/liver_healthy_surface.png", "relief_mm": 0.015}
_COAGULATED_SURFACE = {"surface": "textures/liver_coagulated_surface.png", "relief_mm": 0.06, "offset_mm": -0.05}
DEFAULT_STAGES = [
    {"name": "healthy", "texture": "textures/liver_healthy.png", **_HEALTHY_SURFACE},
    {"name": "hyperaemic_rim", "texture": "textures/liver_hyperaemic.png", "field": "omega", "from": 0.001, "to": 0.03,
     "opacity": 0.75, **_HEALTHY_SURFACE},
    {"name": "pale_crest", "texture": "textures/liver_pale.png", "field": "coagulation", "from": 0.3, "to": 0.8,
     **_COAGULATED_SURFACE},
    {"name": "coagulated", "texture": "textures/liver_coagulated.png", "field": "coagulation_depth_mm", "from": 0.1,
     "to": 0.45, **_COAGULATED_SURFACE},
    {"name": "browned", "texture": "textures/liver_browned.png", "field": "coagulation_depth_mm", "from": 0.6, "to": 1.2,
     "opacity": 0.8, **_COAGULATED_SURFACE},
    {"name": "charred", "texture": "textures/liver_charred.png", "field": "char", "from": 0.05, "to": 0.8,
     "surface": "textures/liver_charred_surface.png", "relief_mm": 0.15, "offset_mm": -0.08},
]


class ConfigError(Exception):
    """Bad input: `file: key: message`."""

    def __init__(self, file, key: str, message: str):
        super().__init__(f"{file}: {key}: {message}")
        self.file, self.key, self.message = str(file), key, message


class _Context:
    def __init__(self, file: Path):
        self.file = file
        self.notes: list[str] = []  # "key: message" for retired keys the file still holds

    def note(self, key: str, message: str):
        self.notes.append(f"{key}: {message}")

    def fail(self, key: str, message: str):
        key = key or "(top level)"
        raise ConfigError(self.file, key if len(key) <= KEY_CHARS else key[: KEY_CHARS - 3] + "...", message)

    def resolve(self, key: str, name: str) -> Path:
        """A relative path: the scene's folder, then the repo root, then static/. The first that exists must be a
        regular file (a FIFO or a device such as /dev/zero is refused unopened: reading it would never end)."""
        path = Path(name).expanduser()
        candidates = [path] if path.is_absolute() else [self.file.parent / path, REPO_ROOT / path, REPO_ROOT / "static" / path]
        for candidate in candidates:
            if candidate.exists() and not candidate.is_file():
                self.fail(key, f"not a regular file: {candidate}")
            if candidate.is_file():
                try:
                    with open(candidate, "rb") as handle:
                        handle.read(1)
                except OSError as exc:
                    self.fail(key, f"cannot read {candidate}: {exc.strerror}")
                return candidate.resolve()
        self.fail(key, f"file not found: {name} (looked in {', '.join(str(c.parent) for c in candidates)})")


def _join(key: str, part) -> str:
    return f"{key}.{part}" if key else str(part)


# --- schema nodes: each is validate(value, key, ctx) -> clean value -------------------------------

class Number:
    def __init__(self, spec: params.ParamSpec, default=True):
        self.spec, self.default = spec, spec.default if default is True else default

    def validate(self, value, key, ctx):
        problem = self.spec.check(value)
        if problem:
            ctx.fail(key, problem)
        return int(value) if self.spec.integer else float(value)


class Boolean:
    def __init__(self, default=False):
        self.default = default

    def validate(self, value, key, ctx):
        if not isinstance(value, bool):
            ctx.fail(key, f"expected true or false, got {quote(value)}")
        return value


class Text:
    def __init__(self, default=None, choices=None):
        self.default, self.choices = default, choices

    def validate(self, value, key, ctx):
        if not isinstance(value, str) or not value:
            ctx.fail(key, f"expected a non-empty string, got {quote(value)}")
        if self.choices and value not in self.choices:
            ctx.fail(key, f"unknown value {quote(value)}; expected one of: {', '.join(self.choices)}")
        return value


class Name(Text):
    """A name that parameter keys carry (`instruments.<name>.tip_temperature_c`): letters, digits, _ and - only."""

    def validate(self, value, key, ctx):
        value = super().validate(value, key, ctx)
        if not NAME_PATTERN.fullmatch(value):
            ctx.fail(key, f"{quote(value)}: a name takes letters, digits, _ and - only")
        return value


class FilePath(Text):
    def validate(self, value, key, ctx):
        return ctx.resolve(key, super().validate(value, key, ctx))


class Vector:
    def __init__(self, default, length=3, nonzero=False, bound=1.0e6):
        self.default, self.length, self.nonzero, self.bound = default, length, nonzero, bound

    def validate(self, value, key, ctx):
        if not isinstance(value, (list, tuple)) or len(value) != self.length:
            ctx.fail(key, f"expected a list of {self.length} numbers, got {quote(value)}")
        for item in value:
            if isinstance(item, bool) or not isinstance(item, (int, float)) or isinstance(item, float) and not math.isfinite(item):
                ctx.fail(key, f"expected finite numbers, got {quote(value)}")
            if abs(item) > self.bound:
                ctx.fail(key, f"{quote(item)} is outside [-{self.bound:g}, {self.bound:g}]")
        if self.nonzero and not any(value):
            ctx.fail(key, "must not be the zero vector")
        return [float(item) for item in value]


class Optional:
    """A mapping that is absent (None) unless the scene gives it; then validated by `node`."""

    def __init__(self, node):
        self.node, self.default = node, None

    def validate(self, value, key, ctx):
        return self.node.validate(value, key, ctx)


class ListOf:
    def __init__(self, item, default=(), max_len=64):
        self.item, self.default, self.max_len = item, list(default), max_len

    def validate(self, value, key, ctx):
        if not isinstance(value, list):
            ctx.fail(key, f"expected a list, got {type(value).__name__}")
        if len(value) > self.max_len:
            ctx.fail(key, f"at most {self.max_len} entries, got {len(value)}")
        return [self.item.validate(item, _join(key, index), ctx) for index, item in enumerate(value)]


class Record:
    """A mapping with known keys; `required` keys must be present, the others get defaults."""

    def __init__(self, fields: dict, required=(), check=None):
        self.fields, self.required, self.check = fields, set(required), check

    def validate(self, value, key, ctx):
        if value is None:
            value = {}
        if not isinstance(value, dict):
            ctx.fail(key, f"expected a mapping, got {type(value).__name__}")
        for name in list(value):
            if _join(key, name) in params.RETIRED:
                ctx.note(_join(key, name), params.RETIRED[_join(key, name)])
                value = {other: item for other, item in value.items() if other != name}
            elif name not in self.fields:
                close = difflib.get_close_matches(str(name), self.fields, n=1)
                hint = f" (did you mean {close[0]!r}?)" if close else f"; known keys: {', '.join(self.fields)}"
                ctx.fail(_join(key, name), f"unknown key{hint}")
        clean = {}
        for name, node in self.fields.items():
            if name in value and value[name] is not None:
                clean[name] = node.validate(value[name], _join(key, name), ctx)
            elif name in self.required:
                ctx.fail(_join(key, name), "missing required key")
            elif isinstance(node, (Record, ListOf)):  # nested defaults are filled and checked too
                clean[name] = node.validate(copy.deepcopy(getattr(node, "default", {})), _join(key, name), ctx)
            else:
                clean[name] = copy.deepcopy(node.default)
        if self.check:
            self.check(clean, key, ctx)
        return clean


class MethodRecord(Record):
    """A mapping whose keys depend on its `method` key, one of `methods` ({name: fields}; the first is the default)."""

    def __init__(self, methods: dict[str, dict]):
        self.methods, self.default_method = methods, next(iter(methods))
        super().__init__(methods[self.default_method])
        self.default = {}

    def validate(self, value, key, ctx):
        value = {} if value is None else value
        if not isinstance(value, dict):
            ctx.fail(key, f"expected a mapping, got {type(value).__name__}")
        method = Text(choices=tuple(self.methods)).validate(value.get("method") or self.default_method, _join(key, "method"), ctx)
        fields = self.methods[method]
        for name in value:
            other = next((other for other, keys in self.methods.items() if name in keys), None)
            if name != "method" and name not in fields and other is not None:
                named = "" if value.get("method") else f" (the default when none is named: add {_join(key, 'method')}: {other})"
                ctx.fail(_join(key, name), f"a key of the {other} method; this scene's {_join(key, 'method')} is {method}{named}")
        clean = Record(fields).validate({name: item for name, item in value.items() if name != "method"}, key, ctx)
        return {"method": method, **clean}


def _numbers(table: dict[str, params.ParamSpec], default=True) -> dict:
    return {name: Number(spec, default) for name, spec in table.items()}


# --- cross-field checks -----------------------------------------------------------------------

def _check_models(models, key, ctx):
    for index, model in enumerate(models):
        if model in models[:index]:
            ctx.fail(_join(key, index), f"{model} is listed twice (each model runs once)")


def _check_shape(shape, key, ctx):
    if shape["type"] == "mesh" and shape["file"] is None:
        ctx.fail(_join(key, "file"), "a mesh instrument needs a file")
    if shape["type"] != "mesh" and shape["file"] is not None:
        ctx.fail(_join(key, "file"), f"only a mesh instrument takes a file, this one is a {shape['type']}")


def _check_path(path, key, ctx):
    times = [frame["t_s"] for frame in path]
    for index in range(1, len(times)):
        if times[index] <= times[index - 1]:
            ctx.fail(_join(_join(key, index), "t_s"), f"keyframe times must increase, {times[index]} follows {times[index - 1]}")


def _check_instrument(instrument, key, ctx):
    _check_path(instrument["path"], _join(key, "path"), ctx)


def _check_bleed_point(point, key, ctx):
    _check_path(point["path"], _join(key, "path"), ctx)
    if point["stop_s"] is not None and point["stop_s"] < point["start_s"]:
        ctx.fail(_join(key, "stop_s"), f"must not be before start_s ({point['start_s']})")


def _check_stages(stages, key, ctx):
    if not stages:
        ctx.fail(key, "needs at least one stage (the healthy look)")
    if stages[0]["field"] is not None:
        ctx.fail(_join(_join(key, 0), "field"), "the first stage is the base look and takes no field")
    for index, stage in enumerate(stages[1:], start=1):
        if stage["field"] is None:
            ctx.fail(_join(_join(key, index), "field"), f"missing required key (one of {', '.join(STAGE_FIELDS)})")
        if not stage["from"] < stage["to"]:
            ctx.fail(_join(_join(key, index), "to"), f"must be greater than from ({stage['from']})")


def _check_tissue(tissue, key, ctx):
    preset = params.TISSUE_PRESETS[tissue["preset"]]
    for name, value in preset.items():
        if tissue[name] is None:
            tissue[name] = value


_TIME = params.ParamSpec("t_s", "s", 0.0, 0.0, 1.0e5, "")
_FROM_TO = params.ParamSpec("threshold", "", 0.0, -1.0e4, 1.0e4, "")
_TILE = params.ParamSpec("tile", "repeats", 1, 1, 64, "", integer=True)
_OPACITY = params.ParamSpec("opacity", "", 1.0, 0.0, 1.0, "")
_RELIEF = params.ParamSpec("relief_mm", "mm", 0.0, 0.0, 2.0, "height of the surface map's full red")
_OFFSET = params.ParamSpec("offset_mm", "mm", 0.0, -1.0, 1.0, "the stage's surface level against the first stage's")
_ROUGHNESS = params.ParamSpec("roughness", "", 0.6, 0.0, 1.0, "PBR roughness where the stage has no surface map")

_KEYFRAME = Record(
    {
        "t_s": Number(_TIME),
        "position_mm": Vector(None),
        "direction": Vector(None, nonzero=True),
        "roll_deg": Number(params.INSTRUMENT["roll_deg"], default=None),
        "energized": Boolean(None),
        "tip_temperature_c": Number(params.INSTRUMENT["tip_temperature_c"], default=None),
    },
    required=("t_s",),
)

_INSTRUMENT = Record(
    {
        "name": Name(),
        "shape": Record(
            {"type": Text(choices=SHAPE_TYPES), **_numbers(params.SHAPE), "file": FilePath()},
            required=("type",),
            check=_check_shape,
        ),
        **_numbers(params.INSTRUMENT),
        "position_mm": Vector([0.0, 0.0, 0.0]),
        "direction": Vector([0.0, 0.0, -1.0], nonzero=True),
        "energized": Boolean(False),
        "path": ListOf(_KEYFRAME, max_len=10000),
        "suction": Optional(Record(_numbers(params.SUCTION))),
    },
    required=("name", "shape"),
    check=_check_instrument,
)

_STAGE = Record(
    {
        "name": Text(),
        "texture": FilePath(),
        "field": Text(choices=STAGE_FIELDS),
        "from": Number(_FROM_TO, default=0.0),
        "to": Number(_FROM_TO, default=1.0),
        "tile": Number(_TILE),
        "opacity": Number(_OPACITY),
        "surface": Optional(FilePath()),
        "relief_mm": Number(_RELIEF),
        "offset_mm": Number(_OFFSET),
        "roughness": Number(_ROUGHNESS),
    },
    required=("name", "texture"),
)

_BLEED_KEYFRAME = Record(
    {"t_s": Number(_TIME), "position_mm": Vector(None), "rate_ml_s": Number(params.BLEED_POINT["rate_ml_s"], default=None)},
    required=("t_s",),
)

_BLEED_POINT = Record(
    {
        "name": Name(),
        "position_mm": Vector(None),
        **_numbers(params.BLEED_POINT),
        "start_s": Number(_TIME, default=0.0),
        "stop_s": Number(_TIME, default=None),
        "path": ListOf(_BLEED_KEYFRAME, max_len=10000),
    },
    required=("name", "position_mm"),
    check=lambda point, key, ctx: _check_bleed_point(point, key, ctx),
)

SCENE = Record(
    {
        "name": Text(),
        "mesh": FilePath(),
        **_numbers(params.SIMULATION),
        "models": ListOf(Text(choices=MODELS), default=["cautery"]),
        "gravity_mm_s2": Vector([0.0, 0.0, -9810.0]),
        "tissue": Record({"preset": Text("liver", choices=tuple(params.TISSUE_PRESETS)), **_numbers(params.TISSUE, default=None)}, check=_check_tissue),
        "cautery": Record({**_numbers(params.CAUTERY), "scheme": Text("explicit", choices=CAUTERY_SCHEMES),
                           "bottom": Text("body", choices=CAUTERY_BOTTOMS)}),
        "bleeding": MethodRecord({method: _numbers(table) for method, table in params.BLEEDING_METHODS.items()}),
        "look": Record({"stages": ListOf(_STAGE, default=DEFAULT_STAGES, max_len=8), **_numbers(params.LOOK)}, check=lambda look, key, ctx: _check_stages(look["stages"], _join(key, "stages"), ctx)),
        "instruments": ListOf(_INSTRUMENT, max_len=8),
        "bleed_points": ListOf(_BLEED_POINT),
    },
    required=("name", "mesh"),
    check=lambda scene, key, ctx: _check_models(scene["models"], _join(key, "models"), ctx),
)


# --- reading YAML from outside ---------------------------------------------------------------

class _Refused(yaml.MarkedYAMLError):
    """YAML that parses but is refused: nested too deep, aliases that expand too far, a value Python cannot hold."""


class _SceneLoader(yaml.SafeLoader):
    """yaml.SafeLoader bounded for untrusted text (MAX_DEPTH, MAX_EXPANDED) that reads `1e-3` as a number, as YAML 1.2
    does (YAML 1.1 reads an exponent without a dot, or without a sign, as text)."""

    depth = 0  # collections being composed

    def compose_node(self, parent, index):
        if self.depth >= MAX_DEPTH:
            raise _Refused(problem=f"nested more than {MAX_DEPTH} levels deep", problem_mark=self.peek_event().start_mark)
        self.depth += 1
        try:
            return super().compose_node(parent, index)
        finally:
            self.depth -= 1

    def compose_document(self):
        node = super().compose_document()
        if _expanded_size(node, {}, set()) > MAX_EXPANDED:
            raise _Refused(problem=f"its aliases expand it to more than {MAX_EXPANDED} characters")
        return node

    def construct_object(self, node, deep=False):
        try:
            return super().construct_object(node, deep)
        except (ValueError, OverflowError) as exc:  # an integer of over 4300 digits, a 13th month
            raise _Refused(problem=f"cannot read this value ({str(exc).partition(':')[0]})", problem_mark=node.start_mark) from None


_SceneLoader.add_implicit_resolver("tag:yaml.org,2002:float", re.compile(r"^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9_]+)[eE][-+]?[0-9]+$"),
                                   list("-+0123456789."))


def _expanded_size(node, sizes: dict, open_nodes: set) -> int:
    """Characters of the scalars under `node` plus one per node, every alias expanded (an aliased node is one object
    shared by every alias: memoised in `sizes` by id). Raises _Refused on an alias inside the node it names."""
    if id(node) in sizes:
        return sizes[id(node)]
    if isinstance(node, yaml.ScalarNode):
        size = 1 + len(node.value)
    else:
        if id(node) in open_nodes:
            raise _Refused(problem="an alias refers to a node that holds it", problem_mark=node.start_mark)
        open_nodes.add(id(node))
        children = node.value if isinstance(node, yaml.SequenceNode) else [item for pair in node.value for item in pair]
        size = 1 + sum(_expanded_size(child, sizes, open_nodes) for child in children)
        open_nodes.discard(id(node))
    sizes[id(node)] = size
    return size


def _load_yaml(text: str):
    """The value of YAML `text` from outside. Raises ValueError: ("line N" or "(yaml)", one-line message)."""
    try:
        return yaml.load(text, Loader=_SceneLoader)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        where = f"line {mark.line + 1}" if mark is not None else "(yaml)"
        raise ValueError(where, problem if isinstance(exc, _Refused) else f"YAML syntax error: {problem}") from None


# --- entry points ---------------------------------------------------------------------------

def parse_override(text: str) -> tuple[list[str], object]:
    """`dotted.key=value` -> (path parts, YAML-parsed value). Raises ValueError on bad syntax."""
    key, sep, raw = text.partition("=")
    if not sep or not key.strip():
        raise ValueError(f"--set expects dotted.key=value, got {quote(text)}")
    try:
        value = _load_yaml(raw) if raw.strip() else None
    except ValueError as exc:
        raise ValueError(f"--set {quote(key.strip())}: value: {exc.args[1]}") from None
    return key.strip().split("."), value


def apply_override(raw: dict, parts: list[str], value, ctx: _Context) -> None:
    """Set raw[parts...] = value in the unvalidated scene; list items are addressed by index."""
    node = raw
    for depth, part in enumerate(parts):
        key = ".".join(parts[: depth + 1])
        last = depth == len(parts) - 1
        if isinstance(node, list):
            if not part.isdigit() or int(part) >= len(node):
                ctx.fail(key, f"--set: no list item {quote(part)} (the list has {len(node)} items)")
            index = int(part)
            if last:
                node[index] = value
            else:
                node = node[index]
        elif isinstance(node, dict):
            if last:
                node[part] = value
                continue
            if node.get(part) is None:
                if parts[depth + 1].isdigit():  # not a mapping with a key "0": say what is missing
                    ctx.fail(key, f"--set: the scene has no {key}, so no item {quote(parts[depth + 1])} to set")
                node[part] = {}
            node = node[part]
        else:
            ctx.fail(".".join(parts[:depth]), f"--set: cannot set {quote(part)} inside a {type(node).__name__}")


def _read_scene_text(path: Path, ctx: _Context) -> str:
    """The file's text: a regular file (not a FIFO or a device) of at most MAX_SCENE_BYTES, UTF-8."""
    try:
        info = path.stat()
        if not stat.S_ISREG(info.st_mode):
            ctx.fail("(file)", "not a regular file")
        if info.st_size > MAX_SCENE_BYTES:
            ctx.fail("(file)", f"{info.st_size} bytes; a scene file is at most {MAX_SCENE_BYTES} bytes")
        with open(path, "rb") as handle:
            data = handle.read(MAX_SCENE_BYTES + 1)
    except FileNotFoundError:
        ctx.fail("(file)", "scene file not found")
    except OSError as exc:
        ctx.fail("(file)", f"cannot read scene file: {exc.strerror or exc}")
    if len(data) > MAX_SCENE_BYTES:
        ctx.fail("(file)", f"more than {MAX_SCENE_BYTES} bytes; a scene file is at most that")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        ctx.fail("(file)", f"cannot read scene file: not UTF-8 text ({exc.reason} at byte {exc.start})")


def _plain(value):
    """An override value as YAML would have read it, in fresh containers (the scene may change its config; the
    caller's overrides stay as they were): NumPy scalars and arrays as Python numbers and lists, tuples as lists,
    paths as text."""
    if hasattr(value, "tolist") and not isinstance(value, (str, bytes)):  # NumPy, without importing it here
        value = value.tolist()
    if isinstance(value, dict):
        return {str(key): _plain(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(item) for item in value]
    if isinstance(value, Path):
        return str(value)
    return value


def _override_items(overrides, ctx: _Context):
    """(path parts, value) of each override: a mapping {dotted key: value} as it is, `dotted.key=value` texts (--set)
    read as YAML."""
    if isinstance(overrides, dict):
        for key, value in overrides.items():
            if not isinstance(key, str) or not key.strip():
                ctx.fail("--set", f"an override key must be a dotted scene key, got {quote(key)}")
            yield key.strip().split("."), _plain(value)
        return
    for text_override in overrides:
        try:
            yield parse_override(text_override)
        except ValueError as exc:
            ctx.fail(text_override.partition("=")[0] or "--set", str(exc))


def load_scene_config(path, overrides: dict | list[str] = ()) -> dict:
    """Read, override and validate a scene file. Raises ConfigError naming file and key.

    overrides: {dotted key: value} (a script, the lab's session: values as YAML reads them, list items by index:
    {"instruments.0.tip_temperature_c": 300}), or `dotted.key=value` texts as `--set` takes them."""
    path = Path(path)
    ctx = _Context(path)
    text = _read_scene_text(path, ctx)
    try:
        raw = _load_yaml(text)
    except ValueError as exc:
        ctx.fail(*exc.args)
    if not isinstance(raw, dict):
        ctx.fail("(top level)", f"a scene must be a YAML mapping, got {type(raw).__name__}")
    for parts, value in _override_items(overrides, ctx):
        apply_override(raw, parts, value, ctx)
    config = SCENE.validate(raw, "", ctx)
    config["scene_file"] = path.resolve()
    config["notes"] = ctx.notes
    return config
