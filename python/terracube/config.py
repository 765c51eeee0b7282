"""Every stage's parameters in one YAML file: commented defaults, loading with clear errors.

A configuration is one section per registered parameter dataclass (``frame``, ``collapse``,
``elevation``, ``terrain``, ``fuzzy``, ``registration``, ``pcl_icp``, ``mapper``). Each section's
YAML is checked by a pydantic model made from its dataclass's fields, so the two cannot drift;
the dataclass then checks the values it refuses (``__post_init__``, and ``to_core``, which runs the
C++ core's own check of the ranges), so a bad file fails when it is read, not at the first scan.
``default_config()`` holds the defaults, :func:`dump_config` writes them as commented YAML (the
comments come from each dataclass's numpy-style ``Attributes`` docstring) and :func:`load_config`
merges a YAML file over the defaults: a file gives only the keys it changes.

A later stage registers its parameters with one line, e.g.::

    register_section("mapper", MapperParams, "Mapper: chaining classified maps into one.")

Example
-------
>>> config = load_config("robot.yaml")        # unknown sections or keys and wrong types: ConfigError
>>> config.collapse.edge
0.25
>>> config = config.replace("collapse", sigma=4)
>>> print(dump_config(config))
"""

from __future__ import annotations

import dataclasses
import difflib
import enum
import functools
import inspect
import math
import reprlib
import textwrap
import types
import typing
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import pydantic

__all__ = [
    "Config",
    "ConfigError",
    "FrameParams",
    "Section",
    "SECTIONS",
    "config_from_dict",
    "default_config",
    "dump_config",
    "load_config",
    "preset_names",
    "preset_path",
    "register_section",
]


class ConfigError(ValueError):
    """A configuration file that cannot be used; the message names the file, section and key."""


@dataclass
class FrameParams:
    """The sensor frame every stage works in: the sensor's range limits, leveling and a crop box.

    Points nearer than ``min_range`` or farther than ``max_range`` from the sensor (the origin of the
    scan's frame, before leveling) take no part: a sensor stores its no-returns as (0, 0, 0), which
    would otherwise become one "ground" cell at the sensor. The leveling transform
    R = Ry(pitch) Rx(roll) (``terracube.leveling_transform``) and the crop box
    are handed to collapsible cubes and to the elevation map alike, so the overhang mask, the DEM and
    the classes of one scan share one frame.

    Attributes
    ----------
    roll_deg : float
        Sensor roll [deg], for leveling (0).
    pitch_deg : float
        Sensor pitch [deg], for leveling (0).
    crop : ((xmin, ymin, zmin), (xmax, ymax, zmax)) or None
        Axis-aligned box [m] in the leveled frame; points outside take no part. None keeps every point.
    min_range : float
        Points nearer the sensor than this [m] take no part (0.1: drops the (0, 0, 0) no-returns).
    max_range : float or None
        Points farther from the sensor than this [m] take no part; None keeps them all.
    """

    roll_deg: float = 0.0
    pitch_deg: float = 0.0
    crop: Sequence[Sequence[float]] | None = None
    min_range: float = 0.1
    max_range: float | None = None

    def __post_init__(self) -> None:
        if not (math.isfinite(float(self.min_range)) and self.min_range >= 0):
            raise ValueError(f"min_range must be a distance >= 0 [m], got {self.min_range!r}")
        if self.max_range is not None and not (
            math.isfinite(float(self.max_range)) and self.max_range > self.min_range
        ):
            raise ValueError(
                f"max_range must be a distance [m] beyond min_range ({self.min_range:g} m) or null, "
                f"got {self.max_range!r}"
            )
        for name in ("roll_deg", "pitch_deg"):
            if not math.isfinite(float(getattr(self, name))):
                raise ValueError(f"{name} must be a finite angle [deg], got {getattr(self, name)!r}")
        if self.crop is not None:
            box = np.asarray(self.crop, dtype=np.float64)
            if box.shape != (2, 3) or not np.all(np.isfinite(box)):
                raise ValueError(
                    f"crop must be [[xmin, ymin, zmin], [xmax, ymax, zmax]] in metres, got {self.crop!r}"
                )
            if np.any(box[0] > box[1]):
                raise ValueError(
                    f"crop: the min corner {box[0].tolist()} exceeds the max corner {box[1].tolist()}"
                )

    def transform(self) -> np.ndarray:
        """The (4, 4) float64 leveling transform of ``roll_deg`` and ``pitch_deg``."""
        from .collapse import leveling_transform

        return leveling_transform(math.radians(self.roll_deg), math.radians(self.pitch_deg))

    def crop_box(self) -> tuple[tuple[float, ...], tuple[float, ...]] | None:
        """The crop box as ((xmin, ymin, zmin), (xmax, ymax, zmax)) [m] or None."""
        if self.crop is None:
            return None
        return tuple(float(v) for v in self.crop[0]), tuple(float(v) for v in self.crop[1])

    def in_range(self, points: np.ndarray) -> np.ndarray:
        """(N,) bool: the points whose distance from the sensor lies in [min_range, max_range]."""
        xyz = np.asarray(points)
        x, y, z = (xyz[:, axis].astype(np.float64) for axis in range(3))
        with np.errstate(over="ignore", invalid="ignore"):  # inf for 1e300, NaN for NaN: both dropped
            squared = x * x + y * y + z * z
        nearest = float(self.min_range)  # x * x: inf for 1e300, where ** 2 raises
        keep = squared >= nearest * nearest  # NaN compares False: dropped too
        if self.max_range is not None:
            farthest = float(self.max_range)
            keep &= squared <= farthest * farthest
        return keep


# ------------------------------------------------------------------------------------------ sections


@dataclass(frozen=True)
class Section:
    """One section of the configuration: its YAML name, parameter dataclass and description.

    ``excluded`` fields are not read from or written to YAML (they keep the dataclass default), with
    ``excluded_reason`` telling a user who sets one where the value belongs instead.
    """

    name: str
    params_type: type
    description: str
    excluded: tuple[str, ...] = ()
    excluded_reason: str = ""

    def fields(self) -> list[dataclasses.Field]:
        return [f for f in dataclasses.fields(self.params_type) if f.name not in self.excluded]


#: The registered sections, in YAML order.
SECTIONS: dict[str, Section] = {}


def register_section(
    name: str,
    params_type: type,
    description: str,
    *,
    excluded: Sequence[str] = (),
    excluded_reason: str = "",
) -> Section:
    """Add a section ``name`` holding the dataclass ``params_type`` (whose fields all have defaults).

    Field types understood in YAML: bool, int, float, str, enums (by lower-case name), ``X | None``,
    sequences and mappings of these (enum keys by lower-case name). Field docs for the YAML comments
    come from the dataclass's ``Attributes`` docstring section.
    """
    if not dataclasses.is_dataclass(params_type):
        raise TypeError(f"section {name!r}: {params_type!r} is not a dataclass")
    if name in SECTIONS:
        raise ValueError(f"section {name!r} is already registered")
    params_type()  # every field needs a default
    section = Section(name, params_type, description, tuple(excluded), excluded_reason)
    SECTIONS[name] = section
    return section


def _register_defaults() -> None:
    from .collapse import CollapseParams
    from .elevation import ElevationParams, TerrainParams
    from .fuzzy import FuzzyParams
    from .mapping import MapperParams
    from .registration import PclIcpParams, RegistrationParams

    frame_reason = "set the leveling and crop box in the 'frame' section (roll_deg, pitch_deg, crop)"
    register_section(
        "frame",
        FrameParams,
        "The sensor frame of every stage: range limits, leveling (roll, pitch) and a crop box.",
    )
    register_section(
        "collapse",
        CollapseParams,
        "Collapsible cubes overhang removal ([CBC] Algorithm 1).",
        excluded=("transform", "crop"),
        excluded_reason=frame_reason,
    )
    register_section(
        "elevation",
        ElevationParams,
        "Elevation map: cell size, optional fixed extent (origin and size together).",
        excluded=("transform", "crop"),
        excluded_reason=frame_reason,
    )
    register_section("terrain", TerrainParams, "Terrain classes of the map cells ([TC] Table 1).")
    register_section(
        "fuzzy",
        FuzzyParams,
        "Fuzzy elevation map: Takagi-Sugeno surface identified by ANFIS hybrid learning.",
    )
    register_section(
        "registration",
        RegistrationParams,
        "Class-weighted ICP between classified maps ([TC] eq. (4) weights, [TC] Table 2).",
    )
    register_section("pcl_icp", PclIcpParams, "PCL's point-to-point ICP baseline (register --method pcl).")
    register_section(
        "mapper",
        MapperParams,
        "Mapper (terracube map): local maps every ~3 m chained by weighted ICP, loops closed with Ceres.",
        excluded=("terrain", "registration"),
        excluded_reason="the mapper takes them from the 'terrain' and 'registration' sections",
    )


# ------------------------------------------------------------------------------------------ the config


class Config:
    """One parameter object per section, reachable as ``config.collapse`` or ``config["collapse"]``.

    Equal configurations compare equal; :meth:`replace` gives a copy with some fields changed.
    """

    def __init__(self, sections: Mapping[str, Any] | None = None):
        values = {name: section.params_type() for name, section in SECTIONS.items()}
        for name, params in (sections or {}).items():
            if name not in SECTIONS:
                raise KeyError(f"unknown section {name!r} (known: {', '.join(SECTIONS)})")
            if not isinstance(params, SECTIONS[name].params_type):
                raise TypeError(f"section {name!r} needs a {SECTIONS[name].params_type.__name__}")
            values[name] = params
        object.__setattr__(self, "_sections", values)

    def __reduce__(self):  # pickles (for batch workers) through the constructor
        return (Config, (dict(self._sections),))

    def __getattr__(self, name: str) -> Any:
        sections = object.__getattribute__(self, "_sections")
        if name in sections:
            return sections[name]
        raise AttributeError(f"no configuration section {name!r} (known: {', '.join(sections)})")

    def __getitem__(self, name: str) -> Any:
        return self._sections[name]

    def __iter__(self) -> Iterator[str]:
        return iter(self._sections)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Config):
            return NotImplemented
        return list(self) == list(other) and all(_values(self[n]) == _values(other[n]) for n in self)

    def __setattr__(self, name: str, value: Any) -> None:
        raise AttributeError("Config is immutable: use config.replace(section, field=value)")

    def replace(self, section: str, **changes: Any) -> Config:
        """A copy with the given fields of ``section`` changed; ``None`` values are ignored."""
        if section not in self._sections:
            raise KeyError(f"unknown section {section!r} (known: {', '.join(self._sections)})")
        changes = {k: v for k, v in changes.items() if v is not None}
        sections = dict(self._sections)
        sections[section] = dataclasses.replace(self._sections[section], **changes)
        return Config(sections)

    def to_dict(self) -> dict[str, dict[str, Any]]:
        """Plain YAML-ready values (lists, numbers, strings, None) of every section and field."""
        return {
            name: {f.name: _plain(getattr(self[name], f.name)) for f in SECTIONS[name].fields()}
            for name in self._sections
        }

    def __repr__(self) -> str:
        return "Config(" + ", ".join(f"{name}={self[name]!r}" for name in self._sections) + ")"


def _values(params: Any) -> dict[str, Any]:
    """Every field of a parameter dataclass, arrays as lists, for comparisons."""
    return {f.name: _plain(getattr(params, f.name)) for f in dataclasses.fields(params)}


def default_config() -> Config:
    """Every registered section at its dataclass defaults."""
    return Config()


# ------------------------------------------------------------------------------------------ YAML out


def _plain(value: Any) -> Any:
    """A value as YAML-native data: enums by lower-case name, tuples and arrays as lists."""
    if isinstance(value, enum.Enum):
        return value.name.lower()
    if isinstance(value, np.ndarray | np.generic):
        return value.tolist()
    if isinstance(value, Mapping):
        return {_plain(k): _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    return value


def _field_docs(params_type: type) -> dict[str, str]:
    """Field descriptions from the ``Attributes`` section of a numpy-style class docstring."""
    lines = (inspect.getdoc(params_type) or "").splitlines()
    if "Attributes" not in (line.strip() for line in lines):
        return {}
    start = [line.strip() for line in lines].index("Attributes") + 2
    docs: dict[str, str] = {}
    names: list[str] = []
    for line in lines[start:]:
        if line and not line.startswith(" "):
            if set(line.strip()) <= {"-"}:  # an underline: the next docstring section began
                break
            names = [n.strip() for n in line.split(" : ")[0].split(",")]
            docs.update(dict.fromkeys(names, ""))
        elif line.strip():
            for name in names:
                docs[name] = (docs[name] + " " + line.strip()).strip()
    return docs


def _yaml_lines(key: str, value: Any) -> list[str]:
    import yaml

    if isinstance(value, Mapping) and value:
        return yaml.safe_dump({key: value}, default_flow_style=False, sort_keys=False).splitlines()
    text = yaml.safe_dump({key: value}, default_flow_style=True, sort_keys=False, width=1000).strip()
    return [text[1:-1]]  # flow style wraps the whole mapping in braces


def dump_config(config: Config | None = None) -> str:
    """The configuration (defaults when None) as YAML with a comment on every section and key.

    ``load_config`` of the text gives back an equal :class:`Config`.
    """
    values = (config or default_config()).to_dict()
    out = [
        "# terracube configuration: every stage's parameters, here at their defaults.",
        "# Use it with `terracube <stage> --config FILE`; options given on the command line win.",
        "# A file needs only the keys it changes: the others keep their defaults.",
    ]
    for name, section in SECTIONS.items():
        out.append("")
        out += textwrap.wrap(
            f"{name}: {section.description}", 100, initial_indent="# ", subsequent_indent="#   "
        )
        if section.excluded:
            out.append(f"#   ({', '.join(section.excluded)}: {section.excluded_reason})")
        out.append(f"{name}:")
        docs = _field_docs(section.params_type)
        previous = None
        for f in section.fields():
            doc = docs.get(f.name)
            if doc and doc != previous:  # a doc shared by several fields is written once, above the first
                out += textwrap.wrap(doc, 98, initial_indent="  # ", subsequent_indent="  # ")
            previous = doc
            out += ["  " + line for line in _yaml_lines(f.name, values[name][f.name])]
    return "\n".join(out) + "\n"


# ------------------------------------------------------------------------------------------ YAML in
#
# Each section's YAML is validated by a pydantic model built from its dataclass's type hints. YAML
# is stricter than pydantic's lax mode in three places: true/false is no number, a number no
# string and 1 no boolean; and enums are written by lower-case name.


def _not_bool(value: Any) -> Any:
    if isinstance(value, bool):
        raise ValueError("a boolean is not a number")
    return value


def _whole_number(value: Any) -> Any:
    if isinstance(value, bool | str):
        raise ValueError("not a whole number")
    return value


def _enum_by_name(enum_type: type[enum.Enum]):
    def parse(value: Any) -> Any:
        if isinstance(value, str) and value.upper() in enum_type.__members__:
            return enum_type[value.upper()]
        if isinstance(value, bool) or not isinstance(value, int):
            raise ValueError("not a member name")
        return value

    return parse


def _is_sequence(origin: Any) -> bool:
    return isinstance(origin, type) and issubclass(origin, Sequence) and not issubclass(origin, str)


def _validation_type(hint: Any) -> Any:
    """The pydantic type that reads the YAML of a dataclass field typed ``hint``."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if hint is bool:
        return pydantic.StrictBool
    if hint is int:
        return Annotated[int, pydantic.BeforeValidator(_whole_number)]
    if hint is float:  # lax: YAML 1.1 reads 1e-4 (no dot) as a string
        return Annotated[float, pydantic.BeforeValidator(_not_bool)]
    if hint is str:
        return pydantic.StrictStr
    if isinstance(hint, type) and issubclass(hint, enum.Enum):
        return Annotated[hint, pydantic.BeforeValidator(_enum_by_name(hint))]
    if origin in (typing.Union, types.UnionType):
        return typing.Union[tuple(_validation_type(a) for a in args)]  # noqa: UP007
    if isinstance(origin, type) and issubclass(origin, Mapping):
        key, value = args if len(args) == 2 else (Any, Any)
        return dict[_validation_type(key), _validation_type(value)]
    if origin is tuple and args and args[-1] is not Ellipsis:
        return tuple[tuple(_validation_type(a) for a in args)]
    if _is_sequence(origin) or hint in (list, tuple, np.ndarray):
        return list[_validation_type(args[0])] if args else list[Any]
    if hint is type(None) or hint is Any:
        return hint
    return pydantic.SkipValidation[hint]  # e.g. a nested dataclass: the dataclass checks it


@functools.cache
def _section_model(section: Section) -> type[pydantic.BaseModel]:
    """The pydantic model of one section's YAML: its dataclass's fields, each optional."""
    hints = typing.get_type_hints(section.params_type)
    fields = {f.name: (_validation_type(hints[f.name]), None) for f in section.fields()}
    config = pydantic.ConfigDict(extra="forbid", arbitrary_types_allowed=True)
    return pydantic.create_model(f"{section.params_type.__name__}Yaml", __config__=config, **fields)


def _type_name(hint: Any) -> str:
    """What a field typed ``hint`` takes, in words: "a list of whole numbers or null"."""
    if hint is type(None):
        return "null"
    if isinstance(hint, type) and issubclass(hint, enum.Enum):
        return "one of " + ", ".join(m.name.lower() for m in hint)
    names = {bool: "true or false", int: "a whole number", float: "a number", str: "a string"}
    if hint in names:
        return names[hint]
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        return " or ".join(_type_name(a) for a in args)
    if isinstance(origin, type) and issubclass(origin, Mapping):
        return f"a mapping of {_type_name(args[0])} to {_plural(args[1])}" if len(args) == 2 else "a mapping"
    if origin is tuple and len(set(args)) == 1 and args[0] is not Ellipsis:  # tuple[float, float, float]
        return f"a list of {len(args)} {_plural(args[0])}"
    return "a list" + (f" of {_plural(args[0])}" if args else "")


def _plural(hint: Any) -> str:
    names = {int: "whole numbers", float: "numbers", str: "strings", bool: "true/false values"}
    if hint in names:
        return names[hint]
    if _is_sequence(typing.get_origin(hint)):
        args = typing.get_args(hint)
        return "lists" + (f" of {_plural(args[0])}" if args else "")
    return "values"


# A bounded repr for values quoted in error messages: a YAML alias bomb of a few hundred bytes is
# a value whose full repr has billions of characters.
_SHORT_REPR = reprlib.Repr()
_SHORT_REPR.maxlevel, _SHORT_REPR.maxlist, _SHORT_REPR.maxdict = 2, 4, 4
_SHORT_REPR.maxstring = _SHORT_REPR.maxother = 60


def _short(value: Any, limit: int = 120) -> str:
    text = _SHORT_REPR.repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _unknown(kind: str, name: Any, known: Sequence[str]) -> str:
    close = difflib.get_close_matches(str(name), list(known), n=1)
    hint = f"; did you mean {close[0]!r}?" if close else ""
    return f"unknown {kind} {_short(name)}{hint} (known: {', '.join(known)})"


def _section_changes(section: Section, values: Mapping[str, Any], source: str) -> dict[str, Any]:
    """The validated fields a file's section sets; ConfigError naming the first bad key."""
    try:
        return _section_model(section).model_validate(values).model_dump(exclude_unset=True)
    except pydantic.ValidationError as error:
        key = error.errors()[0]["loc"][0]
    name = section.name
    if key in section.excluded:
        raise ConfigError(f"{source}: key {key!r} is not read in section {name!r}: {section.excluded_reason}")
    known = [f.name for f in section.fields()]
    if key not in known:
        raise ConfigError(f"{source}: {_unknown(f'key in section {name!r}', key, known)}")
    value = values[key]
    hint = typing.get_type_hints(section.params_type)[key]
    raise ConfigError(
        f"{source}: {name}.{key} must be {_type_name(hint)}, got {_short(value)} ({type(value).__name__})"
    )


#: Deepest nesting of mappings and lists a configuration file may have (a real one has 4).
MAX_YAML_DEPTH = 64


@functools.cache
def _yaml_loader() -> type:
    """yaml.SafeLoader that refuses duplicate keys (naming the key and both lines) and nesting deeper
    than :data:`MAX_YAML_DEPTH` (PyYAML's composer would recurse until RecursionError)."""
    import yaml
    from yaml.composer import ComposerError
    from yaml.constructor import ConstructorError

    class StrictLoader(yaml.SafeLoader):
        depth = 0

        def compose_node(self, parent, index):
            self.depth += 1
            try:
                if self.depth > MAX_YAML_DEPTH:
                    mark = self.peek_event().start_mark
                    raise ComposerError(None, None, f"nested deeper than {MAX_YAML_DEPTH} levels", mark)
                return super().compose_node(parent, index)
            finally:
                self.depth -= 1

        def construct_mapping(self, node, deep=False):
            seen: dict[tuple[str, str], Any] = {}
            for key_node, _ in node.value:
                if isinstance(key_node, yaml.ScalarNode) and key_node.tag != "tag:yaml.org,2002:merge":
                    key = (key_node.tag, key_node.value)
                    if key in seen:
                        raise ConstructorError(
                            None,
                            None,
                            f"duplicate key {_short(key_node.value)} (first at line {seen[key].line + 1})",
                            key_node.start_mark,
                        )
                    seen[key] = key_node.start_mark
            return super().construct_mapping(node, deep=deep)

    return StrictLoader


def _read_yaml(path: Path) -> Any:
    import yaml

    if not path.is_file():
        raise ConfigError(f"{path}: no such configuration file")
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as error:
        raise ConfigError(f"{path}: cannot read the configuration file: {error}") from error
    try:
        return yaml.load(text, Loader=_yaml_loader())  # noqa: S506 - a SafeLoader subclass
    except RecursionError:
        raise ConfigError(f"{path}: not valid YAML: nested too deeply") from None
    except yaml.YAMLError as error:
        where = getattr(error, "problem_mark", None)
        line = f" at line {where.line + 1}, column {where.column + 1}" if where is not None else ""
        problem = getattr(error, "problem", None) or str(error)
        raise ConfigError(f"{path}: not valid YAML{line}: {problem}") from error


def config_from_dict(data: Any, source: str = "<dict>", base: Config | None = None) -> Config:
    """Merge a nested mapping ``{section: {key: value}}`` over ``base`` (the defaults when None).

    ``source`` names the origin of ``data`` in error messages (the file path for :func:`load_config`).
    """
    config = base or default_config()
    if data is None:
        return config
    if not isinstance(data, Mapping):
        raise ConfigError(
            f"{source}: expected a mapping of sections (e.g. 'collapse:'), got {type(data).__name__}"
        )
    sections = {name: config[name] for name in config}
    for name, values in data.items():
        if name not in SECTIONS:
            raise ConfigError(f"{source}: {_unknown('section', name, list(SECTIONS))}")
        if values is None:
            continue
        if not isinstance(values, Mapping):
            raise ConfigError(
                f"{source}: section {name!r} must be a mapping of keys, "
                f"got {type(values).__name__} {_short(values)}"
            )
        changes = _section_changes(SECTIONS[name], values, source)
        try:  # the dataclass checks what types cannot: ranges, names, origin without size ...
            params = dataclasses.replace(sections[name], **changes)
            check = getattr(params, "to_core", None)
            if check is not None:
                check()
        except (ValueError, TypeError, KeyError) as error:
            raise ConfigError(f"{source}: section {name!r}: {error}") from error
        except RuntimeError:  # e.g. the PCL baseline absent from this build: checked when used
            pass
        sections[name] = params
    return Config(sections)


def preset_names() -> list[str]:
    """The names of the bundled sensor presets (``terracube/presets/NAME.yaml``), sorted."""
    return sorted(p.stem for p in _PRESET_DIR.glob("*.yaml"))


#: Other names of the presets: the sensor or the kind of data alone.
PRESET_ALIASES = {"kitti": "kitti_hdl64", "hdl64": "kitti_hdl64", "tls": "tls_plot", "als": "airborne_las"}


def preset_path(name: str) -> Path:
    """The YAML file of the bundled sensor preset ``name`` (or one of :data:`PRESET_ALIASES`);
    ConfigError naming the known ones."""
    name = PRESET_ALIASES.get(name, name)
    path = _PRESET_DIR / f"{name}.yaml"
    if not (name and name.replace("_", "").isalnum() and path.is_file()):
        raise ConfigError(f"--preset: {_unknown('preset', name, preset_names())}")
    return path


def load_config(path: str | Path | None, *, preset: str | None = None) -> Config:
    """The defaults with the sensor preset ``preset`` (:func:`preset_names`) and then the YAML file
    ``path`` merged over them (just the defaults when both are None).

    Raises :class:`ConfigError` (a ValueError) naming the file for a missing file, invalid YAML, an
    unknown section or key, a value of the wrong type or one the parameters refuse, and naming the
    known presets for an unknown one.
    """
    config = default_config()
    if preset is not None:
        source = preset_path(preset)
        config = config_from_dict(_read_yaml(source), f"preset {preset} ({source})", config)
    if path is None:
        return config
    path = Path(path)
    return config_from_dict(_read_yaml(path), str(path), config)


#: Where the bundled sensor presets live (package data).
_PRESET_DIR = Path(__file__).parent / "presets"


_register_defaults()
