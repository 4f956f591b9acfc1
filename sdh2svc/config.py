"""Configuration: ``config/default.toml`` validated into one immutable :class:`Settings` value.

Sources, later ones winning: the packaged defaults, a user TOML file (any subset of keys),
environment variables (``SDH2SVC_<SECTION>__<KEY>``, e.g. ``SDH2SVC_ROLLING__K=3``), and
``key.path=value`` overrides (the CLI's ``--set``). A bad value raises :class:`ConfigError`,
whose message names each offending key, its value and the allowed range.
"""

from __future__ import annotations

import itertools
import json
import math
import os
import re
import tomllib
import types
import typing
from collections.abc import Callable, Iterable, Mapping
from functools import lru_cache
from importlib import resources
from pathlib import Path
from typing import Annotated, Any

import annotated_types as at
from pydantic import (
    AfterValidator,
    BaseModel,
    Field,
    ValidationError,
    ValidationInfo,
    model_validator,
)
from pydantic_settings import BaseSettings, EnvSettingsSource, SettingsConfigDict, SettingsError

from sdh2svc.control.config import ControlConfig
from sdh2svc.control.params import RollingParams
from sdh2svc.control.safety import RunConfig, SafetyConfig, params_outside
from sdh2svc.hosts import is_host, origin_key
from sdh2svc.model.base import Finite
from sdh2svc.model.contact import TactileCalibration, saturated_force
from sdh2svc.model.hand import AxisMap, JointLimits, TactileConfig, matrix_pads
from sdh2svc.model.kinematics import Finger, FingerLimits, HandGeometry
from sdh2svc.model.observe import ModelContext
from sdh2svc.sim.simconfig import SimConfig


class LinksConfig(Finite):
    """The real hand's two serial lines (``--dsa``/``--sdh`` override them)."""

    dsa_url: str
    sdh_url: str
    binary: bool


class StorageConfig(Finite):
    """Where runs are recorded."""

    db_path: Annotated[str, Field(min_length=1)]
    busy_timeout_s: Annotated[float, Field(gt=0.0, le=600.0)] = 10.0


def _host_part(text: str) -> str:
    """What stands for the host in a URL-like entry: ``http://labpc:8000/x`` → ``labpc:8000``."""
    return text.split("://", 1)[-1].split("/", 1)[0]


def _host_entry(entry: str) -> str:
    """A ``service.allowed_hosts`` entry that can match a Host header (the guard compares the
    header's name and port, never a scheme or a path: such an entry matched nothing)."""
    text = entry.strip()
    if is_host(text):
        return entry
    bare = _host_part(text)
    like = repr(bare) if is_host(bare) else "'labpc' or 'labpc:8000'"
    raise ValueError(f"a host is name or name:port, without a scheme or a path: write {like}")


def _origin_entry(entry: str) -> str:
    """A ``service.allowed_origins`` entry that can match a browser's Origin header,
    ``scheme://host[:port]`` (without its scheme it matched nothing)."""
    text = entry.strip()
    if origin_key(text) is not None:
        return entry
    scheme, sep, _ = text.partition("://")
    host = _host_part(text)
    like = f"'{scheme if sep else 'http'}://{host}'" if is_host(host) else "'http://labpc:8000'"
    raise ValueError(f"an origin is scheme://host[:port], without a path: write {like}")


HostEntry = Annotated[str, AfterValidator(_host_entry)]
OriginEntry = Annotated[str, AfterValidator(_origin_entry)]


class ServiceConfig(Finite):
    """``sdh2svc serve``: where it listens, who may command it, how telemetry flows."""

    host: str
    port: Annotated[int, Field(ge=0, le=65535)]
    viser_port: Annotated[int, Field(ge=0, le=65535)]
    viewer: bool
    viewer_process: bool
    token: str
    telemetry_queue: Annotated[int, Field(ge=1, le=100_000)]
    send_timeout_s: Annotated[float, Field(gt=0.0, le=60.0)]
    send_buffer_kb: Annotated[int, Field(ge=16, le=65536)]
    tactile_max_hz: Annotated[float, Field(gt=0.0, le=30.0)]
    viewer_max_hz: Annotated[float, Field(gt=0.0, le=30.0)]
    monitor_rate_hz: Annotated[float, Field(ge=0.0, le=30.0)]
    pose_hz: Annotated[float, Field(gt=0.0, le=30.0)]
    status_hz: Annotated[float, Field(gt=0.0, le=30.0)]
    stop_timeout_s: Annotated[float, Field(gt=0.0, le=120.0)]
    allowed_hosts: tuple[HostEntry, ...] = ()
    allowed_origins: tuple[OriginEntry, ...] = ()
    max_body_kb: Annotated[int, Field(ge=1, le=1_048_576)] = 1024
    foxglove_port: Annotated[int, Field(ge=0, le=65535)] = 0  # the live Foxglove view; 0: off


#: The sections a run's recording keeps (Settings.recorded).
RECORDED_SECTIONS = ("hand", "axes", "limits", "tactile", "calibration", "run", "safety")
_READ_SECTIONS = ("hand", "axes", "limits", "tactile", "calibration")  # a recording read back


class Settings(BaseSettings):
    """The whole configuration of sdh2svc; see ``config/default.toml`` for every key and unit."""

    model_config = SettingsConfigDict(
        env_prefix="SDH2SVC_", env_nested_delimiter="__", frozen=True, extra="forbid"
    )

    hand: HandGeometry
    axes: AxisMap
    limits: JointLimits
    tactile: TactileConfig
    calibration: TactileCalibration
    rolling: RollingParams
    run: RunConfig
    safety: SafetyConfig
    links: LinksConfig
    storage: StorageConfig
    service: ServiceConfig
    sim: SimConfig

    @model_validator(mode="after")
    def _consistent(self, info: ValidationInfo) -> Settings:
        """Checks across sections: a pre-shape inside the joint limits; rolling parameters the
        supervisor's limits allow; a force ceiling the pads can reach; distinct ports. Not for
        a recording read back (:meth:`as_recorded`): it is what was, and drives nothing."""
        if info.context and info.context.get("recorded"):
            return self
        problems = self.run.preshape_outside(self.limits)
        problems += params_outside(self.rolling, self.safety)
        full = saturated_force(self.tactile.distal, self.tactile.texel_pitch_mm,
                               self.calibration, self.hand.pad)  # fmt: skip
        if self.safety.force_ceiling_max >= full:
            problems.append(
                f"safety.force_ceiling_max = {self.safety.force_ceiling_max:g}: a saturated pad "
                f"reads F = {full:.3g} with this calibration (calibration.*), so the ceiling "
                f"could never trip (allowed: force_ceiling_max < {full:.3g})"
            )
        svc = self.service
        ports = {"port": svc.port, "viser_port": svc.viser_port, "foxglove_port": svc.foxglove_port}
        for a, b in itertools.combinations(ports, 2):
            if ports[a] and ports[a] == ports[b]:
                problems.append(f"service.{a} and service.{b} are both {ports[a]}: one port each")
        problems += self._dead_texels_outside()
        sim = self.sim.links
        if sim.dsa_tcp_port and sim.dsa_tcp_port == sim.sdh_tcp_port:
            problems.append(f"sim.links.dsa_tcp_port and sdh_tcp_port are both "
                            f"{sim.dsa_tcp_port}: one port each")  # fmt: skip
        if problems:
            raise ValueError("; ".join(problems))
        return self

    def _dead_texels_outside(self) -> list[str]:
        """sim.sensor.dead_texels outside its matrix's rows and columns (as wired here). A
        position of the layout without a cell (its mask's '.') reads 0 already: listed, as
        when a whole pad is listed dead, it changes nothing."""
        pads = matrix_pads(self.axes, self.tactile)
        return [
            f"sim.sensor.dead_texels [{m}, {r}, {c}]: matrix {m}, the {pads[m][0]}, has rows "
            f"0…{pads[m][1].rows - 1} and columns 0…{pads[m][1].cols - 1}"
            for m, r, c in self.sim.sensor.dead_texels
            if r >= pads[m][1].rows or c >= pads[m][1].cols
        ]

    def model_context(self) -> ModelContext:
        """The pure model's view of this configuration."""
        return ModelContext(
            geom=self.hand,
            distal=self.tactile.distal,
            pitch_mm=self.tactile.texel_pitch_mm,
            calib=self.calibration,
            limits1=self.finger_limits(Finger.ONE),
            limits2=self.finger_limits(Finger.TWO),
        )

    def control(self) -> ControlConfig:
        """The controller's section: all a run needs."""
        return ControlConfig(
            ctx=self.model_context(),
            axes=self.axes,
            limits=self.limits,
            run=self.run,
            safety=self.safety,
            rolling=self.rolling,
        )

    def recorded(self) -> dict[str, Any]:
        """The sections a run's recording keeps (the hand, its wiring and the run's model), as
        JSON: what its export needs, whatever the configuration is when it is exported."""
        return {k: getattr(self, k).model_dump(mode="json") for k in RECORDED_SECTIONS}

    def as_recorded(self, sections: Mapping[str, Any]) -> Settings:
        """This configuration with what reading a recording needs of its sections
        (:meth:`recorded`) in place of its own — its hand, wiring, pads and calibration, and the
        pre-shape of the joints the model leaves out — key by key: a key an older version did
        not record keeps this configuration's value. Its safety limits and speeds are not read
        (limits tightened since must not make an old run unreadable). :class:`ConfigError` if
        what is read is not valid here (e.g. a newer version's)."""
        picked = {k: v for k, v in sections.items() if k in _READ_SECTIONS}
        cal = sections.get("calibration")
        distance = cal.get("distance") if isinstance(cal, Mapping) else None
        if isinstance(distance, Mapping) and distance.get("kind") == "linear":
            # a measured table an older version kept beside the linear map, which ignores it
            # (refused in a configuration since; the context does not reach nested validators)
            picked["calibration"] = {**picked["calibration"], "distance": {"kind": "linear"}}
        run = sections.get("run")
        if isinstance(run, Mapping) and "preshape_deg" in run:
            picked["run"] = {"preshape_deg": run["preshape_deg"]}
        try:
            data = deep_merge(self.model_dump(), picked)
            return self.model_validate(data, context={"recorded": True})
        except ValidationError as e:
            raise ConfigError(format_errors(e, Settings), "recorded configuration") from None

    def finger_limits(self, finger: Finger) -> FingerLimits:
        """Joint limits of a coupled finger in radians (for IK and the safety clamp)."""
        prox, dist = self.axes.finger_axes(finger)
        lo, hi = self.limits.min_deg, self.limits.max_deg
        return FingerLimits(
            math.radians(lo[prox]),
            math.radians(hi[prox]),
            math.radians(lo[dist]),
            math.radians(hi[dist]),
        )


class ConfigError(ValueError):
    """Invalid configuration: one line per problem, each naming the key, the value and the range."""

    def __init__(self, problems: list[str], source: str = "configuration") -> None:
        self.problems = problems
        if len(problems) == 1:  # one problem, one line
            super().__init__(f"invalid {source}: {problems[0]}")
        else:
            super().__init__(f"invalid {source}:\n  " + "\n  ".join(problems))


def default_config_path(name: str = "default.toml") -> Path:
    """A packaged config file (wheel), or the repository's ``config/<name>``."""
    packaged = resources.files("sdh2svc") / "_config" / name
    if packaged.is_file():
        return Path(str(packaged))
    return Path(__file__).resolve().parent.parent / "config" / name


def _read_toml(path: Path) -> dict[str, Any]:
    """A TOML file's table; anything unreadable is a :class:`ConfigError` naming the file."""
    try:
        with path.open("rb") as f:
            return tomllib.load(f)
    except FileNotFoundError:
        raise ConfigError([f"file not found: {path}"]) from None
    except IsADirectoryError:
        raise ConfigError([f"{path} is a directory, not a TOML file"]) from None
    except UnicodeDecodeError:
        raise ConfigError([f"{path}: not valid TOML: not UTF-8 text (a binary file?)"]) from None
    except tomllib.TOMLDecodeError as e:
        raise ConfigError([f"{path}: not valid TOML: {e}"]) from None
    except (OSError, ValueError) as e:  # permissions, a NUL in the name, …
        why = e.strerror if isinstance(e, OSError) and e.strerror else str(e)
        raise ConfigError([f"cannot read {path}: {why}"]) from None


def deep_merge(base: Mapping[str, Any], top: Mapping[str, Any]) -> dict[str, Any]:
    """``base`` with ``top``'s keys laid over it, tables merged key by key."""
    out = dict(base)
    for key, value in top.items():
        if isinstance(value, Mapping) and isinstance(out.get(key), Mapping):
            out[key] = deep_merge(out[key], value)
        else:
            out[key] = value
    return out


def parse_override(text: str) -> dict[str, Any]:
    """``rolling.k=3`` → ``{"rolling": {"k": 3}}``; the value is read as TOML, else as a string."""
    key, sep, raw = text.partition("=")
    key = key.strip()
    if not sep or not key or any(not part for part in key.split(".")):
        raise ConfigError([f"override {text!r} must look like section.key=value"])
    try:
        value = tomllib.loads(f"v = {raw.strip()}")["v"]
    except tomllib.TOMLDecodeError:
        value = raw.strip()
    out: dict[str, Any] = {}
    node = out
    *parents, leaf = key.split(".")
    for part in parents:
        node = node.setdefault(part, {})
    node[leaf] = value
    return out


def load_config(
    path: str | Path | None = None,
    overrides: Iterable[str] = (),
    *,
    use_env: bool = True,
    base: Mapping[str, Any] | None = None,
) -> Settings:
    """Load and validate the configuration: defaults ← ``path`` ← environment ← ``overrides``.
    ``base``, a configuration already made (``Settings.model_dump``), stands for the defaults:
    what a campaign's workers start from, wherever they run, whatever their environment."""
    if base is not None:
        data = dict(base)
    else:
        data = _read_toml(default_config_path())
        data["sim"] = _read_toml(default_config_path("sim.toml"))
    # each layer with what names the origin of a value in it (a file, a variable, a --set)
    layers: list[tuple[Callable[[tuple[int | str, ...]], str], Mapping[str, Any]]] = []
    if path is not None:
        layers.append((_named(str(path)), _read_toml(Path(path))))
    if use_env:
        layers.append((_env_name, read_environment()))
    for text in overrides:
        layers.append((_named(f"--set {text}"), parse_override(text)))
    for _, layer in layers:
        data = deep_merge(data, layer)
    try:
        # model_validate, not Settings(...): the layers above are already merged in order.
        return Settings.model_validate(data)
    except ValidationError as e:

        def origin(loc: tuple[int | str, ...]) -> str | None:
            """Where the value at ``loc`` came from: the topmost layer that sets it."""
            return next((name(loc) for name, layer in reversed(layers) if _sets(layer, loc)), None)

        raise ConfigError(format_errors(e, Settings, origin)) from None


def _named(name: str) -> Callable[[tuple[int | str, ...]], str]:
    """The origin of every value of a layer that is one file or one option."""
    return lambda loc: name


ENV_PREFIX = "SDH2SVC_"


def read_environment() -> dict[str, Any]:
    """The ``SDH2SVC_SECTION__KEY`` variables as a table. A variable whose section is not one
    of the configuration's, or whose value cannot be read, is a :class:`ConfigError` naming it
    (pydantic-settings drops the first without a word)."""
    sections = {name.upper() for name in Settings.model_fields}
    unknown = [
        name for name in os.environ
        if name.startswith(ENV_PREFIX)
        and name[len(ENV_PREFIX):].split("__")[0].upper() not in sections
        and name not in NOT_CONFIGURATION
    ]  # fmt: skip
    if unknown:
        raise ConfigError([
            f"{name}: no such configuration section (the sections are: "
            f"{', '.join(Settings.model_fields)}; a key is SDH2SVC_SECTION__KEY)"
            for name in sorted(unknown)
        ])  # fmt: skip
    try:
        return EnvSettingsSource(Settings)()
    except SettingsError as e:  # e.g. SDH2SVC_LIMITS__MIN_DEG=[1, 2 (not JSON)
        section = str(e).partition('field "')[2].partition('"')[0]
        names = sorted(n for n in os.environ if n.startswith(f"{ENV_PREFIX}{section.upper()}"))
        raise ConfigError([
            f"{name} = {clip(repr(os.environ[name]))}: cannot be read (a list or table is "
            "written in JSON, e.g. '[\"a\", \"b\"]')" for name in names
        ] or [f"environment ({ENV_PREFIX}…): {e}"]) from None  # fmt: skip


# Variables with the prefix that are not configuration (the CLI's own switches).
NOT_CONFIGURATION = frozenset({"SDH2SVC_DEBUG", "SDH2SVC_HYPOTHESIS", "SDH2SVC_SCREENSHOTS"})


def _env_name(loc: tuple[int | str, ...]) -> str:
    """The environment variable that sets the value at ``loc`` (its string parts; an index
    is inside the variable's JSON value)."""
    keys = [str(p) for p in loc if isinstance(p, str)]
    for n in range(len(keys), 0, -1):
        name = ENV_PREFIX + "__".join(keys[:n]).upper()
        if name in os.environ:
            return name
    return ENV_PREFIX + "__".join(keys).upper()


def _sets(layer: Mapping[str, Any], loc: tuple[int | str, ...]) -> bool:
    """Whether ``layer`` supplies the value at ``loc`` (or a list or value that holds it)."""
    node: Any = layer
    for part in loc:
        if not isinstance(node, Mapping):
            return True  # inside a value this layer gave whole
        if part not in node:
            return False
        node = node[part]
    return True


@lru_cache(maxsize=1)
def default_config() -> Settings:
    """The packaged defaults alone (no file, no environment): the thesis's values."""
    return load_config(use_env=False)


# --- readable validation errors -------------------------------------------------------------


CLIP_CHARS = 80  # of a value (or a key) quoted back in an error message


def clip(text: str, n: int = CLIP_CHARS) -> str:
    """``text``, or its first ``n`` characters and "…": an error never echoes a long value back."""
    return text if len(text) <= n else text[:n] + "…"


def shown(value: Any) -> str:
    """A value as an error quotes it, clipped: true, false and null as JSON and TOML write them
    (what the user wrote), anything else as Python's repr ('text', 1.5)."""
    return clip(json.dumps(value) if value is None or isinstance(value, bool) else repr(value))


def error_message(e: Any, limit: int | None = 4 * CLIP_CHARS) -> str:
    """A pydantic error's message, with any long value it quotes (its input, its context) clipped
    (e.g. a discriminator's tag: "Input tag '…' found using 'kind' does not match …"), and the
    whole clipped to ``limit`` characters (None: not)."""
    msg = str(e["msg"])
    for v in (e.get("input"), *(e.get("ctx") or {}).values()):
        if isinstance(v, str) and len(v) > CLIP_CHARS:
            msg = msg.replace(v, clip(v))
    return msg if limit is None else clip(msg, limit)


def error_key(loc: Iterable[int | str]) -> str:
    """A pydantic error's location as ``a.b.0.c``, each part clipped (a key may be user input)."""
    return ".".join(clip(str(p)) for p in loc) or "(top level)"


def format_errors(
    err: ValidationError,
    model: Any,
    origin: Callable[[tuple[int | str, ...]], str | None] | None = None,
    maxima: Mapping[str, float] | None = None,
) -> list[str]:
    """One line per error, e.g. ``rolling.k = 0.5: Input should be greater than 1 (allowed: …)``.

    ``model`` is a model class, or an annotated union of them with a ``kind`` discriminator (the
    error's location then starts with the kind). Long values are clipped (:func:`clip`).
    ``origin`` names where a location's value came from (a file, a variable, an option), if known:
    ``rolling.k = 0.5 (lab.toml): …``. ``maxima``: tighter upper bounds than the model's, by
    top-level key (the safety limits' on the rolling parameters), quoted instead of the model's.
    """
    lines: list[str] = []
    errors = err.errors()
    locs = [tuple(e["loc"]) for e in errors]
    for e, loc in zip(errors, locs, strict=True):
        if e["type"] == "too_short" and any(len(x) > len(loc) and x[: len(loc)] == loc
                                            for x in locs):  # fmt: skip
            continue  # a list short only because its bad items were dropped: they say why
        key = error_key(loc)
        value = e.get("input")
        quoted = "" if isinstance(value, Mapping) else f" = {shown(value)}"
        if not loc:  # a check across fields (a model validator): its message says it all
            parts = error_message(e, None).removeprefix("Value error, ").split("; ")
            lines.extend(clip(_sourced(part, origin), 4 * CLIP_CHARS) for part in parts)
            continue
        source = origin(loc) if origin is not None else None
        if source:
            quoted += f" ({clip(source, 4 * CLIP_CHARS)})"
        top = (maxima or {}).get(str(loc[0])) if len(loc) == 1 else None
        allowed = _allowed_range(model, loc, top)
        msg = error_message(e).removeprefix("Value error, ")
        if top is not None and e["type"] in ("less_than", "less_than_equal"):
            msg = f"Input should be less than or equal to {top:g}"
        if e["type"] == "extra_forbidden":
            msg = REMOVED_KEYS.get(key) or unknown_key(model_keys(model, loc[:-1]))
            if len(loc) == 1 and (near := _sections_with(model, str(loc[0]))):
                msg += f"; did you mean {' or '.join(near)}?"  # a key given without its section
        elif e["type"] in ("tuple_type", "list_type") and isinstance(value, str):
            # a list given as text (--set, an environment variable): "tuple" says nothing there
            msg = f"a list is needed, written in JSON, e.g. {key}={json.dumps([value])}"
        lines.append(f"{key}{quoted}: {msg}" + (f" (allowed: {allowed})" if allowed else ""))
    return lines


_LEADING_KEY = re.compile(r"([A-Za-z_]\w*(?:\.[A-Za-z_]\w*)+) = ([^:()]*):")


def _sourced(line: str, origin: Callable[[tuple[int | str, ...]], str | None] | None) -> str:
    """A check across fields' line that begins ``section.key = value:``, with where that
    value came from after it, as a field's own error has it."""
    m = _LEADING_KEY.match(line)
    if m is None or origin is None or not (source := origin(tuple(m[1].split(".")))):
        return line
    return f"{m[1]} = {m[2]} ({clip(source, 4 * CLIP_CHARS)}):{line[m.end() :]}"


# Keys an earlier version had: a file that still sets one is told why, not only that it is unknown
REMOVED_KEYS = {
    "run.watch_rate_hz": "a key no longer read (every tactile frame carries all six pads at "
    "the run's rate): drop it from the configuration",
}


def unknown_key(keys: Iterable[str] | None) -> str:
    """The message for a key a model does not have, naming the keys it has (if known)."""
    if keys is None:
        return "unknown key"
    return f"unknown key (the keys there are: {', '.join(keys) or 'none'})"


def _sections_with(model: Any, name: str) -> list[str]:
    """``section.name`` for every section of ``model`` that has a key ``name``."""
    return [f"{top}.{name}" for top in model_keys(model) or ()
            if name in (model_keys(model, (top,)) or ())]  # fmt: skip


def model_keys(model: Any, loc: tuple[int | str, ...] = ()) -> list[str] | None:
    """The keys of the model that ``loc`` leads to down ``model`` (None: not a model there)."""
    tp: Any = model
    for part in loc:
        tp, _ = _descend(tp, part)
        if tp is None:
            return None
    tp, _ = _unwrap(tp)
    return list(tp.model_fields) if isinstance(tp, type) and issubclass(tp, BaseModel) else None


def _allowed_range(model: Any, loc: tuple[int | str, ...], top: float | None = None) -> str:
    tp: Any = model
    metadata: list[Any] = []
    for part in loc:
        tp, metadata = _descend(tp, part)
        if tp is None:
            return ""
    name = str(next((p for p in reversed(loc) if isinstance(p, str)), "value"))
    lo = hi = ""
    for m in metadata:
        if isinstance(m, at.Gt):
            lo = f"{m.gt} < "
        elif isinstance(m, at.Ge):
            lo = f"{m.ge} ≤ "
        elif isinstance(m, at.Lt):
            hi = f" < {m.lt}"
        elif isinstance(m, at.Le):
            hi = f" ≤ {m.le}"
    if top is not None:  # a tighter limit than the field's own
        hi = f" ≤ {top:g}"
    return f"{lo}{name}{hi}" if lo or hi else ""


def _descend(tp: Any, part: int | str) -> tuple[Any, list[Any]]:
    """Type and constraint metadata one step down ``tp`` along a validation-error location."""
    tp, _ = _unwrap(tp)
    if isinstance(tp, type) and issubclass(tp, BaseModel):
        field = tp.model_fields.get(str(part))
        if field is None:
            return None, []
        inner, meta = _unwrap(field.annotation)
        return inner, list(field.metadata) + meta
    if typing.get_origin(tp) in (typing.Union, types.UnionType) and isinstance(part, str):
        for member in typing.get_args(tp):  # a discriminated union: the member of that kind
            kind = getattr(member, "model_fields", {}).get("kind")
            if kind is not None and kind.default == part:
                return member, []
        return None, []
    if typing.get_origin(tp) in (tuple, list) and isinstance(part, int):
        args = typing.get_args(tp)
        elem = args[0] if len(args) == 2 and args[1] is Ellipsis else args[min(part, len(args) - 1)]
        return _unwrap(elem)
    return None, []


def _unwrap(tp: Any) -> tuple[Any, list[Any]]:
    meta: list[Any] = []
    while True:
        if typing.get_origin(tp) is Annotated:
            tp, *extra = typing.get_args(tp)
            for m in extra:
                meta.extend(getattr(m, "metadata", [m]))
            continue
        if typing.get_origin(tp) in (typing.Union, types.UnionType):
            args = [a for a in typing.get_args(tp) if a is not type(None)]
            if len(args) == 1:
                tp = args[0]
                continue
        return tp, meta
