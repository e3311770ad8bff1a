"""Configuration: frozen dataclasses, one per stage, loaded from YAML with unknown keys rejected.

Each stage package defines its own config dataclass (``reconstruction.config``,
``mapping.config``, ...). ``PipelineConfig`` groups them; ``load_config`` reads a YAML file whose
top-level keys are the stage names. Every field is commented with its unit and, where the
dissertation names it, its symbol.

Valid values: each config class declares, next to its fields, a class-level
``RANGES: ClassVar[dict[str, str]]`` that maps a field name to its valid range in interval
notation, optionally followed by ``; why``::

    RANGES: ClassVar[dict[str, str]] = {
        "gsd_m": "(0, 1]; a raster cell above 1 m is a unit mistake (cm typed as m?)",
        "min_share": "[0, 1]",
        "max_features": "[1, inf)",
        "lr_schedule": "{cosine, exponential}",  # a set: the allowed values
    }

A numeric field (int, float, an optional number or a tuple of numbers: the range applies to each
element) must have a range (a test checks every config class). ``from_dict`` and
``load_yaml_config`` check every value they are given, after type coercion, and raise one-line
``ConfigError``s naming the file, the dotted key, the value and the range. NaN and infinities are
never valid.

Fields that only make sense in one order (a severity band's low and high edge, a minimum and a
maximum) are declared in ``ORDER: ClassVar[tuple[tuple[str, str], ...]]``: each ``(a, b)``
requires ``a < b`` (a value set that inverts them would silently swap the classes or select
nothing). The check runs after the ranges, on the built object, so a YAML that sets only one of
the two is judged against the other's default; the error names both keys and values.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import difflib
import functools
import math
import re
import types
import typing
from pathlib import Path
from typing import Any, TypeVar

import yaml

from roadsurf.core.errors import ConfigError

T = TypeVar("T")

# unit shown in range messages, from the field name's suffix (the naming convention of the
# config fields: gsd_m, tile_px, route_heading_deg, ...); longest suffix first
_UNITS: tuple[tuple[str, str], ...] = (
    ("_mps2", " m/s²"),
    ("_mps", " m/s"),
    ("_kmh", " km/h"),
    ("_cm2", " cm²"),
    ("_m2", " m²"),
    ("_deg", " deg"),
    ("_px", " px"),
    ("_hz", " Hz"),
    ("_m", " m"),
    ("_s", " s"),
)
_NUMBER = r"[-+]?(?:inf|\d+(?:\.\d*)?(?:e[-+]?\d+)?|\.\d+(?:e[-+]?\d+)?)"
_INTERVAL = re.compile(rf"^([\[(])\s*({_NUMBER})\s*,\s*({_NUMBER})\s*([\])])$", re.IGNORECASE)


@dataclasses.dataclass(frozen=True)
class Range:
    """A valid range: an interval (``lo``/``hi``, None = unbounded) or a set of ``choices``."""

    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False
    choices: tuple[Any, ...] | None = None
    note: str = ""  # why the bounds are what they are (shown in the error)

    def contains(self, value: Any) -> bool:
        if self.choices is not None:
            return value in self.choices
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            return False
        if not math.isfinite(value):
            return False
        if self.lo is not None and (value <= self.lo if self.lo_open else value < self.lo):
            return False
        return self.hi is None or (value < self.hi if self.hi_open else value <= self.hi)

    def describe(self, unit: str = "") -> str:
        """'> 0 m', '>= 0 and <= 1', 'one of cosine, exponential'."""
        if self.choices is not None:
            return "one of " + ", ".join(str(c) for c in self.choices)
        parts = []
        if self.lo is not None:
            parts.append(f"{'>' if self.lo_open else '>='} {_num(self.lo)}")
        if self.hi is not None:
            parts.append(f"{'<' if self.hi_open else '<='} {_num(self.hi)}")
        return (" and ".join(parts) or "a finite number") + unit


def _num(x: float) -> str:
    return str(int(x)) if float(x).is_integer() and abs(x) < 1e15 else repr(float(x))


@functools.cache
def parse_range(spec: str) -> Range:
    """``"(0, 1]; why"`` -> Range(0, 1, lo_open=True, note="why"); ``"{a, 2}"`` -> choices."""
    body, _, note = spec.partition(";")
    body, note = body.strip(), note.strip()
    if body.startswith("{") and body.endswith("}"):
        items = tuple(_choice(s.strip()) for s in body[1:-1].split(",") if s.strip())
        if not items:
            raise ValueError(f"empty choice set in range {spec!r}")
        return Range(choices=items, note=note)
    m = _INTERVAL.match(body)
    if m is None:
        raise ValueError(
            f"range {spec!r} is neither an interval like '(0, 1]' nor a set '{{a, b}}'"
        )
    lo, hi = float(m.group(2)), float(m.group(3))
    if lo > hi:
        raise ValueError(f"range {spec!r}: lower bound above the upper bound")
    return Range(
        lo=None if lo == -math.inf else lo,
        hi=None if hi == math.inf else hi,
        lo_open=m.group(1) == "(",
        hi_open=m.group(4) == ")",
        note=note,
    )


def _choice(token: str) -> Any:
    for conv in (int, float):
        try:
            return conv(token)
        except ValueError:
            pass
    return token


def ranges_of(cls: type) -> dict[str, Range]:
    """The parsed ``RANGES`` of a config class (empty when it declares none)."""
    specs: dict[str, str] = getattr(cls, "RANGES", None) or {}
    return {name: parse_range(spec) for name, spec in specs.items()}


def unit_of(name: str) -> str:
    """The unit a field's name ends with (' m' for gsd_m), or ''."""
    return next((u for suffix, u in _UNITS if name.endswith(suffix)), "")


class _KeyedConfigError(ConfigError):
    """A ConfigError that remembers the dotted key (load_yaml_config adds the YAML line)."""

    def __init__(self, source: str, key: str, message: str) -> None:
        super().__init__(f"{source}: {key + ': ' if key else ''}{message}")
        self.source, self.key, self.detail = source, key, message


def from_dict(cls: type[T], data: dict[str, Any] | None, where: str = "config") -> T:
    """Build dataclass ``cls`` from ``data``, rejecting unknown keys, ill-typed values and values
    outside the declared ``RANGES``.

    Nested dataclass fields are built recursively. ``where`` names the file (or other source) in
    errors, which read ``<where>: <dotted.key>: <problem>``.
    """
    return _build(cls, data, where, "")


def _build(cls: type[T], data: Any, source: str, prefix: str, base: T | None = None) -> T:
    """``cls`` from a mapping; keys not given keep ``base``'s values (the enclosing config's
    default for this section, which may differ from the class's own), else the class's."""
    if data is None:
        return base if base is not None else cls()
    section = prefix.rstrip(".")
    if not isinstance(data, dict):
        raise _KeyedConfigError(
            source,
            section,
            f"expected a mapping of keys to values, got {type(data).__name__} {_short(data)}",
        )
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    for key in data:
        if not isinstance(key, str):
            raise _KeyedConfigError(
                source,
                section,
                f"key {_short(key)} is not a setting name (keys are names like "
                f"{sorted(fields)[0]!r}; `~` is YAML's null). Fix or remove it.",
            )
    unknown = sorted(set(data) - set(fields))
    if unknown:
        guesses = [
            f"'{k}' -> did you mean '{m[0]}'?"
            for k in unknown
            if (m := difflib.get_close_matches(k, list(fields), n=1))
        ]
        hint = (" " + " ".join(guesses)) if guesses else ""
        raise _KeyedConfigError(
            source,
            section,
            f"unknown key(s) {unknown}.{hint} Valid keys are: {sorted(fields)}. "
            "Fix the spelling or remove them.",
        )
    ranges = ranges_of(cls)
    kwargs: dict[str, Any] = {}
    for key, value in data.items():
        dotted = prefix + key
        if dataclasses.is_dataclass(hints[key]):  # a section: start from its default here
            coerced = _build(hints[key], value, source, dotted + ".", _default(fields[key]))
        else:
            coerced = _coerce(hints[key], value, source, dotted)
        rng = ranges.get(key)
        if rng is not None:
            _check(rng, coerced, value, source, dotted, fields[key])
        kwargs[key] = coerced
    obj = dataclasses.replace(base, **kwargs) if base is not None else cls(**kwargs)  # type: ignore[type-var]
    _check_order(obj, source, prefix, given=set(data))
    return obj


def _default(f: dataclasses.Field[Any]) -> Any:
    """A dataclass field's default value (None when it has none)."""
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return None if f.default is dataclasses.MISSING else f.default


def _check_order(obj: Any, source: str, prefix: str, given: set[str] | None = None) -> None:
    """Raise ConfigError when a pair of ``ORDER`` is not strictly increasing. The error names
    the key the user set (of the two), else the first."""
    for a, b in getattr(type(obj), "ORDER", ()):
        va, vb = getattr(obj, a), getattr(obj, b)
        if va is None or vb is None or va < vb:
            continue
        key = b if given is not None and b in given and a not in given else a
        raise _KeyedConfigError(
            source,
            prefix + key,
            f"{a} = {_short(va)} must be below {b} = {_short(vb)} "
            "(they bound one interval); change one of them",
        )


def _check(rng: Range, value: Any, raw: Any, source: str, key: str, fld: dataclasses.Field) -> None:
    if value is None:  # an optional field left unset
        return
    items = value if isinstance(value, (tuple, list)) else (value,)
    if all(rng.contains(v) for v in items):
        return
    default = fld.default if fld.default is not dataclasses.MISSING else None
    why = f" ({rng.note})" if rng.note else ""
    eg = f"; e.g. {_short(default)}" if default is not None else ""
    name = key.rsplit(".", 1)[-1]
    each = "each value " if isinstance(value, (tuple, list)) else ""
    raise _KeyedConfigError(
        source,
        key,
        f"{_short(raw)} is out of range: {each}must be {rng.describe(unit_of(name))}{why}{eg}",
    )


def check_ranges(obj: Any, where: str = "config") -> None:
    """Raise ConfigError when any field of config ``obj`` (recursively) is outside its range."""
    _check_obj(obj, where, "")


def _check_obj(obj: Any, source: str, prefix: str) -> None:
    ranges = ranges_of(type(obj))
    for fld in dataclasses.fields(obj):
        value = getattr(obj, fld.name)
        if dataclasses.is_dataclass(value):
            _check_obj(value, source, f"{prefix}{fld.name}.")
        elif fld.name in ranges:
            _check(ranges[fld.name], value, value, source, prefix + fld.name, fld)
    _check_order(obj, source, prefix)


def _short(value: Any, limit: int = 60) -> str:
    """One-line, bounded repr of a config value for an error message."""
    text = repr(value)
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        text = str(value)
    text = " ".join(text.split())
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _coerce(tp: Any, value: Any, source: str, key: str) -> Any:
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if dataclasses.is_dataclass(tp):
        return _build(tp, value, source, key + ".")  # type: ignore[arg-type]
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        for a in args:
            if a is type(None):
                continue
            try:
                return _coerce(a, value, source, key)
            except ConfigError:
                pass
        raise _KeyedConfigError(source, key, f"value {_short(value)} does not match {tp}")
    if origin is typing.Literal:
        if isinstance(value, (dict, list)) or value not in args:
            raise _KeyedConfigError(source, key, f"{_short(value)} is not one of {list(args)}")
        return value
    if origin in (tuple, list):
        if not isinstance(value, (list, tuple)):
            raise _KeyedConfigError(source, key, f"expected a list, got {_short(value)}")
        if origin is tuple and args and args[-1] is not Ellipsis:
            if len(args) != len(value):
                raise _KeyedConfigError(
                    source, key, f"expected {len(args)} values, got {len(value)}"
                )
            return tuple(_coerce(a, v, source, key) for a, v in zip(args, value, strict=True))
        inner = args[0] if args else Any
        seq = [_coerce(inner, v, source, key) for v in value]
        return tuple(seq) if origin is tuple else seq
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise _KeyedConfigError(source, key, f"expected a number, got {_short(value)}")
        try:
            return float(value)
        except OverflowError:
            raise _KeyedConfigError(source, key, f"{_short(value)} is too large") from None
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise _KeyedConfigError(source, key, f"expected an integer, got {_short(value)}")
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise _KeyedConfigError(source, key, f"expected true or false, got {_short(value)}")
        return value
    if tp is str:
        if isinstance(value, (dt.date, dt.datetime)):
            # YAML reads an unquoted ISO 8601 time as a timestamp: the text it was
            return value.isoformat()
        if not isinstance(value, str):
            raise _KeyedConfigError(source, key, f"expected a string, got {_short(value)}")
        return value
    return value


def to_dict(obj: Any) -> dict[str, Any]:
    """Plain-dict view of a config dataclass (for report.json and provenance)."""
    return dataclasses.asdict(obj)


def read_yaml_mapping(path: str | Path) -> Any:
    """The YAML document of config file ``path``; one-line ConfigError (with the line where
    YAML knows it) for a missing file, non-UTF-8 bytes or invalid YAML."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: config file not found")
    raw = path.read_bytes()
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as e:
        line = raw[: e.start].count(b"\n") + 1
        raise ConfigError(
            f"{path} line {line}: byte 0x{raw[e.start]:02x} at offset {e.start} is not UTF-8. "
            "Save the file as UTF-8."
        ) from None
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None) or getattr(e, "context_mark", None)
        at = f" line {mark.line + 1}" if mark is not None else ""
        problem = getattr(e, "problem", None) or getattr(e, "context", None) or type(e).__name__
        raise ConfigError(
            f"{path}{at}: not valid YAML ({' '.join(str(problem).split())}). Fix the syntax."
        ) from None
    except (ValueError, OverflowError, RecursionError) as e:  # e.g. a date like 2024-13-45
        raise ConfigError(
            f"{path}: not valid YAML ({' '.join(str(e).split())[:120]}). Fix the value."
        ) from None


def load_yaml_config(cls: type[T], path: str | Path) -> T:
    """Load dataclass ``cls`` from a YAML file, naming the file (and the line of the offending
    key where it can be found) in every error."""
    path = Path(path)
    data = read_yaml_mapping(path)
    try:
        return from_dict(cls, data or {}, str(path))
    except _KeyedConfigError as e:
        line = _line_of(path, e.key)
        if line is None:
            raise
        raise ConfigError(
            f"{path} line {line}: {e.key + ': ' if e.key else ''}{e.detail}"
        ) from None


def _line_of(path: Path, dotted: str) -> int | None:
    """1-based line of the dotted key in YAML file ``path`` (None when not found)."""
    if not dotted:
        return None
    try:
        node = yaml.compose(path.read_text(encoding="utf-8"), Loader=yaml.SafeLoader)
    except Exception:  # noqa: BLE001 - a best-effort hint; the error is raised anyway
        return None
    line = None
    for part in dotted.split("."):
        if not isinstance(node, yaml.MappingNode):
            return line
        match = [
            (k, v) for k, v in node.value if isinstance(k, yaml.ScalarNode) and k.value == part
        ]
        if not match:
            return line
        line = match[-1][0].start_mark.line + 1
        node = match[-1][1]
    return line
