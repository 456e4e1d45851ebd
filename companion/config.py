"""The application's configuration: one typed schema, loaded from TOML plus ``--set`` overrides.

Each TOML table is one section, and each section is an options dataclass (see
:mod:`autonomy.options`) that owns its defaults and validates itself. This module only finds
the values, checks that their names exist, and says where a bad one came from: every failure
is a :class:`ConfigError` reading ``<source>: <section>.<key>: <what is wrong>``, so an
operator can fix the file without reading a traceback.
"""

from __future__ import annotations

import dataclasses
import difflib
import json
import sys
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple, Sequence

if sys.version_info >= (3, 11):
    import tomllib
else:  # Python 3.10
    import tomli as tomllib

from autonomy.depth.network import NetworkOptions
from autonomy.depth.options import RescaleOptions
from autonomy.depth.stage import DepthStageOptions
from autonomy.depth.synthetic import SyntheticDepthOptions
from autonomy.navigation.mission import FlightOptions
from autonomy.options import OptionError, field_types, option, validate
from autonomy.planning.planner import PlannerOptions
from autonomy.vins.frontend import FrontendOptions
from autonomy.vins.options import VinsOptions
from autonomy.vins.preintegration import ImuNoise
from autonomy.vins.static_init import StaticInitOptions
from companion.flight.go import GoOptions
from companion.recording.options import RecorderOptions
from drivers.camera.options import CameraOptions
from drivers.camera.oak import OakOptions
from drivers.camera.realsense import RealSenseOptions
from drivers.camera.v4l2 import V4l2Options
from drivers.mavlink.autopilot import MavlinkOptions
from drivers.sim.options import CONFIG_SECTIONS as SIMULATOR_SECTIONS

LOG_LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR")


@dataclass(frozen=True)
class LogOptions:
    """How the application logs."""

    level: str = option("INFO", choices=LOG_LEVELS, doc="lowest severity written to stderr")

    def __post_init__(self) -> None:
        validate(self)


@dataclass(frozen=True)
class FlightConfig:
    """The flight application's own tables: one field per TOML table, each an options
    dataclass."""

    log: LogOptions = field(default_factory=LogOptions)
    rescale: RescaleOptions = field(default_factory=RescaleOptions)
    depth: DepthStageOptions = field(default_factory=DepthStageOptions)
    depth_network: NetworkOptions = field(default_factory=NetworkOptions)
    synthetic_depth: SyntheticDepthOptions = field(default_factory=SyntheticDepthOptions)
    camera: CameraOptions = field(default_factory=CameraOptions)
    v4l2: V4l2Options = field(default_factory=V4l2Options)
    realsense: RealSenseOptions = field(default_factory=RealSenseOptions)
    oak: OakOptions = field(default_factory=OakOptions)
    vins: VinsOptions = field(default_factory=VinsOptions)
    vins_frontend: FrontendOptions = field(default_factory=FrontendOptions)
    vins_init: StaticInitOptions = field(default_factory=StaticInitOptions)
    vins_imu: ImuNoise = field(default_factory=ImuNoise.icm42688p)
    planner: PlannerOptions = field(default_factory=PlannerOptions)
    flight: FlightOptions = field(default_factory=FlightOptions)
    go: GoOptions = field(default_factory=GoOptions)
    recorder: RecorderOptions = field(default_factory=RecorderOptions)
    mavlink: MavlinkOptions = field(default_factory=MavlinkOptions)

    def __post_init__(self) -> None:
        validate(self)


#: The whole configuration: the flight's tables (:class:`FlightConfig`) and, after them, the
#: tables the simulator declares for itself (:data:`drivers.sim.options.CONFIG_SECTIONS`:
#: ``[sim]``, ``[vehicle]``, ``[imu]``, ``[px4]``), each at its class's defaults.
Config = dataclasses.make_dataclass(
    "Config", [(name, kind, field(default_factory=kind))
               for name, kind in SIMULATOR_SECTIONS.items()],
    bases=(FlightConfig,), frozen=True)
Config.__module__ = __name__  # where pickle (eval's worker processes) finds it


class ConfigError(Exception):
    """A configuration that cannot be used, naming where the bad value came from.

    ``source`` is the file path or ``--set section.key=value``; ``key`` is the dotted key when
    the problem belongs to one (``rescale.kappa``), else None.
    """

    def __init__(self, source: str, message: str, key: str | None = None):
        self.source = source
        self.key = key
        self.message = message
        where = f"{source}: {key}" if key else source
        super().__init__(f"{where}: {message}")


class Override(NamedTuple):
    """One ``--set section.key=value``, with the text it came from for error messages."""

    section: str
    key: str
    value: Any
    source: str


def parse_override(text: str) -> Override:
    """Split ``section.key=value`` and read the value as TOML.

    A value that is not valid TOML is kept as a bare string, so that
    ``rescale.method=monotone_spline`` works without shell-escaped quotes. An argument that is
    not UTF-8 (Python keeps its undecodable bytes as surrogates) is refused: the config is
    UTF-8 text, as a file and in a recording.
    """
    source = f"--set {text}"
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        shown = text.encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")
        raise ConfigError(f"--set {shown}", "not UTF-8 text") from None
    name, equals, raw = text.partition("=")
    section, dot, key = name.strip().partition(".")
    if not (equals and dot and section and key) or "." in key:
        raise ConfigError(source, f"expected SECTION.KEY=VALUE, got {text!r}")
    return Override(section, key, _parse_toml_value(raw.strip()), source)


def _parse_toml_value(raw: str) -> Any:
    try:
        document = tomllib.loads(f"value = {raw}")
    except (tomllib.TOMLDecodeError, RecursionError):  # tomllib recurses into nested arrays
        return raw
    # A newline in the value could smuggle in more keys; such a value is not one TOML value.
    return document["value"] if len(document) == 1 else raw


#: section -> key -> (value, source it came from); a section's keys are in the order last set.
_Settings = dict[str, dict[str, tuple[Any, str]]]


#: The simulator commands' own defaults (``sim fly``, ``sim record``, ``eval rescale``,
#: ``eval nav``; issue 23): the realistic profile's vehicle, with the application configured
#: as the Orin presets configure a real one. ``config/sim-realistic.toml`` holds the same
#: settings with the reasons (tests/test_config.py keeps the two equal). They lie under the
#: config file and the ``--set`` overrides; ``--config config/sim.toml``, every key at its
#: default, flies the ideal profile.
SIMULATOR_DEFAULTS = (
    "sim.profile=realistic",
    "depth.scale_field_nodes=4",
    "vins.estimate_time_offset=true",
    "vins.estimate_gyro_alignment=true",
    "vins.gyro_alignment_rates=all",
    "vins.gyro_noise_scale=10",
    "vins.rest_accel_scale_share=0.71",
    "vins_frontend.anchor_age=2",
    "vins_frontend.anchor_warp=homography",
    "sim_latency.vins_s=0.024",
    "planner.near_tail_share=0.9",
    "planner.far_tail_share=0.9",
    "planner.height_swing=0.08",
)


def load_config(path: str | Path | None, overrides: Sequence[str] = (),
                defaults: Sequence[str] = ()) -> Config:
    """The configuration from a TOML file (None: all defaults) with overrides applied on top.

    Later sources win: ``defaults`` (``SECTION.KEY=VALUE`` settings, such as
    :data:`SIMULATOR_DEFAULTS`) over the options' own defaults, the file over them, each
    override over the file and the overrides before it. Raises :class:`ConfigError` for
    anything wrong.
    """
    document = None if path is None else (_read_toml(Path(path)), str(path))
    return _load(document, overrides, defaults)


def config_from_toml(text: str, source: str, overrides: Sequence[str] = ()) -> Config:
    """As :func:`load_config`, from TOML ``text`` (a recording's config) named ``source`` in
    errors."""
    return _load((_parse_toml(text, source), source), overrides)


def _load(document: tuple[dict[str, Any], str] | None, overrides: Sequence[str],
          defaults: Sequence[str] = ()) -> Config:
    settings: _Settings = {}
    for text in defaults:
        default = parse_override(text)
        _set(settings, f"the command's default {text}", default.section, default.key,
             default.value)
    if document is not None:
        _add_document(settings, *document)
    for text in overrides:
        override = parse_override(text)
        _set(settings, override.source, override.section, override.key, override.value)
    config = Config(**{section.name: _build_section(section, settings.get(section.name, {}))
                       for section in dataclasses.fields(Config)})
    _check_across_tables(config, settings)
    return config


def _check_across_tables(config: Config, settings: _Settings) -> None:
    """The rules that join two tables; ConfigError naming the source of the non-default key
    (``clamp`` is never the default)."""
    if config.rescale.extrapolation == "clamp" and config.planner.near_tail_share > 0.0:
        raise ConfigError(
            settings["rescale"]["extrapolation"][1], "a clamped tail reads every pixel nearer "
            "than the nearest landmark at that landmark's depth, which the planner's near tail "
            "would fly on: set planner.near_tail_share = 0 with it", "rescale.extrapolation")


def _read_toml(path: Path) -> dict[str, Any]:
    source = str(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise ConfigError(source, "no such file") from None
    except OSError as error:
        raise ConfigError(source, f"cannot read: {error.strerror or error}") from None
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as error:
        problem = f"not UTF-8 text ({error.reason} at byte {error.start})"
        raise ConfigError(source, problem) from None
    return _parse_toml(text, source)


def _parse_toml(text: str, source: str) -> dict[str, Any]:
    """The TOML document ``text``; ConfigError naming ``source`` when it is not one."""
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as error:
        raise ConfigError(source, f"invalid TOML: {error}") from None
    except RecursionError:  # tomllib recurses into nested arrays and inline tables
        raise ConfigError(source, "invalid TOML: arrays or tables nested too deeply") from None


def _add_document(settings: _Settings, document: dict[str, Any], source: str) -> None:
    for section, table in document.items():
        _check_known(source, section)
        if not isinstance(table, dict):
            raise ConfigError(source, f"must be a table [{section}], got {table!r}", section)
        for key, value in table.items():
            _set(settings, source, section, key, value)


def _set(settings: _Settings, source: str, section: str, key: str, value: Any) -> None:
    _check_known(source, section, key)
    keys = settings.setdefault(section, {})
    keys.pop(key, None)  # re-insert so the last key set is the last in order
    keys[key] = (value, source)


def _check_known(source: str, section: str, key: str | None = None) -> None:
    """Reject a section or key that the schema lacks, suggesting the closest known name."""
    sections = field_types(Config)
    _reject_unknown(source, "section", section, list(sections), section)
    if key is not None:
        keys = [f.name for f in dataclasses.fields(sections[section])]
        _reject_unknown(source, "key", key, keys, f"{section}.{key}")


def _reject_unknown(source: str, what: str, name: str, known: list[str], where: str) -> None:
    if name in known:
        return
    close = difflib.get_close_matches(name, known, n=1)
    hint = f"did you mean {close[0]!r}?" if close else f"known: {', '.join(known)}"
    raise ConfigError(source, f"unknown {what}; {hint}", where)


def _build_section(section: dataclasses.Field, values: dict[str, tuple[Any, str]]) -> Any:
    """The section's default (the ``Config`` field's, which may differ from its class's, as
    ``[vins_imu]``'s does) with ``values`` set."""
    default = section.default_factory()
    types = field_types(type(default))
    try:
        return dataclasses.replace(default, **{key: _coerce(value, types[key])
                                               for key, (value, _) in values.items()})
    except OptionError as error:
        raise ConfigError(_culprit(values, error.key), error.message,
                          f"{section.name}.{error.key}") from None


def _coerce(value: Any, kind: Any) -> Any:
    """TOML's ``3`` where a float is expected becomes ``3.0``; a bool is never a number; a
    TOML list where a ``tuple[...]`` is expected becomes a tuple of its items, coerced alike."""
    if kind is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if typing.get_origin(kind) is tuple and isinstance(value, list):
        item_kind = typing.get_args(kind)[0]
        return tuple(_coerce(item, item_kind) for item in value)
    return value


def _culprit(values: dict[str, tuple[Any, str]], key: str) -> str:
    """The source to blame for a bad key: the one that set it, else (for a cross-field error
    such as ``min_depth >= max_depth`` where only the other key was given) the source that
    set a key of this section last."""
    if key in values:
        return values[key][1]
    return list(values.values())[-1][1]


def dump_toml(config: Config) -> str:
    """The configuration as TOML with every key of every section, readable by
    :func:`load_config` into an equal ``Config``."""
    tables = []
    for section in dataclasses.fields(config):
        options = getattr(config, section.name)
        lines = [f"[{section.name}]"]
        lines += [f"{f.name} = {_toml_value(getattr(options, f.name))}"
                  for f in dataclasses.fields(options)]
        tables.append("\n".join(lines) + "\n")
    return "\n".join(tables)


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)  # shortest exact form; also TOML's spelling of inf and nan
    if isinstance(value, str):
        # A JSON string is a TOML basic string, except that TOML also forbids a raw DEL.
        return json.dumps(value, ensure_ascii=False).replace("\x7f", "\\u007f")
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(item) for item in value) + "]"
    raise TypeError(f"no TOML form for {value!r}")
