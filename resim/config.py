"""Typed config dataclasses, validated on load.

Every component has one ``@dataclass`` config. This module turns plain dicts
(from YAML or JSON) into those dataclasses and back, and refuses anything it
does not understand *before* any work starts:

* an unknown key is an error naming the full dotted key (``sources.opendv.roott``);
* a value of the wrong type is an error naming the key, the expected type and the value;
* ``__post_init__`` of each dataclass may raise ``ConfigError`` for range checks.

Overrides from the command line use ``--set key.sub=value``; the value is parsed
as YAML, so ``--set train.lr=1e-4`` gives a float and ``--set x=[1,2]`` a list.

Only the standard library and PyYAML are used, so ``shards`` (which must import
without torch or ray) can depend on it.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import re
import types
import typing
from pathlib import Path
from typing import Any, Literal, Mapping, TypeVar, Union, get_args, get_origin, get_type_hints

import yaml

T = TypeVar("T")


class ConfigError(ValueError):
    """A config value is missing, unknown, of the wrong type or out of range."""


# Configs, run folders and datasets come from other people: YAML is parsed within limits. PyYAML's safe_load
# runs no code, but aliases let 478 bytes stand for a tree of billions of nodes ("billion laughs"): shared
# references while loaded, expanded by any copy or JSON dump of the config (ours deep-copies it). The limit is
# on the *expanded* size, which is what a copy costs, not on the number of aliases (9 levels of 9 are enough).
MAX_YAML_BYTES = 16 << 20
MAX_YAML_EXPANDED_NODES = 1_000_000


def _expanded_nodes(root: yaml.Node) -> int:
    """Nodes of ``root`` with every alias expanded (shared subtrees counted once per reference), computed
    without expanding and without recursion; yaml.YAMLError beyond the limit or for a recursive alias."""
    def kids(n):
        if isinstance(n, yaml.MappingNode):
            return [x for kv in n.value for x in kv]
        return list(n.value) if isinstance(n, yaml.SequenceNode) else []

    size: dict[int, int] = {}
    open_: set[int] = set()
    stack = [(root, False)]
    while stack:
        n, done = stack.pop()
        if done:
            open_.discard(id(n))
            size[id(n)] = 1 + sum(size[id(k)] for k in kids(n))
            if size[id(n)] > MAX_YAML_EXPANDED_NODES:
                raise yaml.YAMLError(f"aliases expand to more than {MAX_YAML_EXPANDED_NODES:,} nodes: refused, as a "
                                     "YAML bomb would be")
        elif id(n) not in size:
            if id(n) in open_:
                raise yaml.YAMLError("a recursive alias (a node containing itself): refused")
            open_.add(id(n))
            stack.append((n, True))
            stack.extend((k, False) for k in kids(n) if id(k) not in size)
    return size[id(root)]


class _LimitedSafeLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` refusing documents whose aliases expand beyond MAX_YAML_EXPANDED_NODES."""

    def compose_document(self):   # noqa: D401 - PyYAML hook
        node = super().compose_document()
        if node is not None:
            _expanded_nodes(node)
        return node


def safe_yaml(text: str) -> Any:
    """``yaml.safe_load`` within limits (characters, expanded nodes); yaml.YAMLError otherwise."""
    if len(text) > MAX_YAML_BYTES:
        raise yaml.YAMLError(f"{len(text):,} characters, more than the {MAX_YAML_BYTES:,} a config may have")
    return yaml.load(text, Loader=_LimitedSafeLoader)  # noqa: S506 - a SafeLoader subclass


def check_positive(name: str, value: float, allow_zero: bool = False) -> None:
    """ConfigError unless ``value`` is a finite number > 0 (>= 0 with ``allow_zero``)."""
    # Written as `not (value > 0)` and with isfinite: NaN compares False both ways, so `value <= 0` let
    # `.nan` through (and `.inf` then failed somewhere else with an unrelated message).
    ok = (value >= 0) if allow_zero else (value > 0)
    if not (ok and math.isfinite(value)):
        raise ConfigError(f"{name} must be a finite number {'>= 0' if allow_zero else '> 0'}, got {value}")


def _type_name(tp: Any) -> str:
    return getattr(tp, "__name__", None) or str(tp).replace("typing.", "")


def _convert(value: Any, tp: Any, key: str) -> Any:
    """Check/convert ``value`` to type ``tp``; ``key`` is the dotted path for errors."""
    origin = get_origin(tp)
    if tp is Any:
        return value
    if origin in (Union, types.UnionType):
        args = get_args(tp)
        if value is None:
            if type(None) in args:
                return None
            raise ConfigError(f"{key}: null is not allowed (expected {_type_name(tp)})")
        errors = []
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _convert(value, arg, key)
            except ConfigError as e:  # try the next member of the union
                errors.append(str(e))
        raise ConfigError(f"{key}: {value!r} matches none of {_type_name(tp)} ({'; '.join(errors)})")
    if origin is Literal:
        allowed = get_args(tp)
        if isinstance(value, bool) and {"on", "off"} <= set(allowed):   # YAML 1.1 reads `on` / `off` as booleans
            value = "on" if value else "off"
        if value not in allowed:
            raise ConfigError(f"{key}: {value!r} is not one of {list(allowed)}")
        return value
    if dataclasses.is_dataclass(tp):
        if isinstance(value, tp):
            return value
        if not isinstance(value, Mapping):
            raise ConfigError(f"{key}: expected a mapping for {tp.__name__}, got {type(value).__name__}")
        return from_dict(tp, value, prefix=key)
    if origin in (list, tuple) or tp in (list, tuple):
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{key}: expected a list, got {value!r}")
        args = get_args(tp)
        if origin is tuple and args and not (len(args) == 2 and args[1] is Ellipsis):
            if len(args) != len(value):
                raise ConfigError(f"{key}: expected {len(args)} items, got {len(value)}")
            return tuple(_convert(v, a, f"{key}[{i}]") for i, (v, a) in enumerate(zip(value, args)))
        item_tp = args[0] if args else Any
        items = [_convert(v, item_tp, f"{key}[{i}]") for i, v in enumerate(value)]
        return tuple(items) if (origin is tuple or tp is tuple) else items
    if origin is dict or tp is dict:
        if not isinstance(value, Mapping):
            raise ConfigError(f"{key}: expected a mapping, got {value!r}")
        args = get_args(tp)
        vt = args[1] if args else Any
        return {str(k): _convert(v, vt, f"{key}.{k}") for k, v in value.items()}
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{key}: expected true/false, got {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            if isinstance(value, float) and value.is_integer():
                return int(value)
            raise ConfigError(f"{key}: expected an integer, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{key}: expected a number, got {value!r}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{key}: expected a string, got {value!r}")
        return value
    if tp is Path:
        if not isinstance(value, (str, Path)):
            raise ConfigError(f"{key}: expected a path, got {value!r}")
        return Path(value)
    raise TypeError(f"config type {tp!r} at {key} is not supported by resim.config")  # our bug


def _over_field_default(f: dataclasses.Field, tp: Any, value: Any) -> Any:
    """A partial mapping for a nested config goes over the *field's* default, not its class's: a task that
    defaults ``optim`` to ``OptimConfig(lr=2e-3, schedule="cosine")`` keeps its schedule under ``--set optim.lr=...``
    (with the class's defaults it would quietly become constant)."""
    if not (isinstance(value, Mapping) and dataclasses.is_dataclass(tp)
            and f.default_factory is not dataclasses.MISSING):  # type: ignore[misc]
        return value
    default = f.default_factory()  # type: ignore[misc]
    if not isinstance(default, tp):
        return value
    merged = to_dict(default)
    _deep_update(merged, value)
    return merged


def from_dict(cls: type[T], data: Mapping[str, Any], prefix: str = "") -> T:
    """Build dataclass ``cls`` from ``data``, validating keys and types recursively."""
    if not dataclasses.is_dataclass(cls):
        raise TypeError(f"{cls!r} is not a dataclass")
    hints = get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(set(data) - set(fields), key=str)   # YAML keys may be bools (`on:`, `yes:`) or ints
    if unknown:
        where = f"{prefix}." if prefix else ""
        raise ConfigError(
            f"unknown config key {where}{unknown[0]} (known keys of {cls.__name__}: {', '.join(sorted(fields))})"
        )
    kwargs = {}
    for name, value in data.items():
        key = f"{prefix}.{name}" if prefix else name
        kwargs[name] = _convert(_over_field_default(fields[name], hints[name], value), hints[name], key)
    missing = [
        n for n, f in fields.items()
        if n not in kwargs and f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING  # type: ignore[misc]
    ]
    if missing:
        where = f"{prefix}." if prefix else ""
        raise ConfigError(f"missing required config key {where}{missing[0]}")
    try:
        return cls(**kwargs)
    except ConfigError as e:
        raise ConfigError(f"{prefix + ': ' if prefix else ''}{e}") from None


def to_dict(cfg: Any) -> Any:
    """Dataclass (nested) → plain JSON/YAML-able dict (Paths as strings, tuples as lists)."""
    if dataclasses.is_dataclass(cfg) and not isinstance(cfg, type):
        return {f.name: to_dict(getattr(cfg, f.name)) for f in dataclasses.fields(cfg)}
    if isinstance(cfg, (list, tuple)):
        return [to_dict(v) for v in cfg]
    if isinstance(cfg, dict):
        return {str(k): to_dict(v) for k, v in cfg.items()}
    if isinstance(cfg, Path):
        return str(cfg)
    return cfg


def config_hash(cfg: Any) -> str:
    """A short stable hash of a resolved config (sha256 of canonical JSON, 16 hex chars)."""
    blob = json.dumps(to_dict(cfg), sort_keys=True, separators=(",", ":")).encode()
    return hashlib.sha256(blob).hexdigest()[:16]


def set_by_path(data: dict, dotted: str, value: Any) -> None:
    """Set ``data['a']['b'] = value`` for ``dotted == 'a.b'``, creating mappings as needed."""
    parts = dotted.split(".")
    cur = data
    for p in parts[:-1]:
        nxt = cur.get(p)
        if nxt is None:
            nxt = cur[p] = {}
        if not isinstance(nxt, dict):
            raise ConfigError(f"--set {dotted}: {p} is not a mapping")
        cur = nxt
    cur[parts[-1]] = value


def apply_overrides(data: dict, overrides: typing.Iterable[str]) -> dict:
    """Apply ``key.sub=value`` overrides (values parsed as YAML) to a raw config dict."""
    for item in overrides or ():
        if "=" not in item:
            raise ConfigError(f"--set {item!r}: expected key=value")
        k, v = item.split("=", 1)
        set_by_path(data, k.strip(), _parse_value(v))
    return data


_FLOAT_RE = re.compile(r"^[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)$")


def _parse_value(v: str) -> Any:
    """YAML-parse an override value; YAML 1.1 reads ``1e-4`` (no dot) as a string, so read it as a float."""
    if not v.strip():
        return ""
    try:
        out = safe_yaml(v)
    except yaml.YAMLError as e:
        raise ConfigError(f"--set value {v!r} is not valid YAML: {str(e).splitlines()[0]}") from None
    if isinstance(out, str) and _FLOAT_RE.match(out.strip()):
        return float(out)
    return out


def read_mapping(path: str | Path) -> dict:
    """A YAML config file's top-level mapping; :class:`ConfigError` naming the file when it is missing, not a
    regular file, not YAML or not a mapping."""
    p = Path(path)
    if not p.is_file():   # is_file() is a stat: it never blocks on a FIFO, as opening one would
        what = "is not a regular file" if p.exists() else "does not exist"
        raise ConfigError(f"config file {p} {what}")
    try:
        loaded = safe_yaml(p.read_text()) or {}
    except yaml.YAMLError as e:   # names the file, with the line and column YAML gives
        raise ConfigError(f"config file {p}: invalid YAML: {e}".replace('"<unicode string>"', str(p))) from None
    if not isinstance(loaded, dict):
        raise ConfigError(f"config file {p}: top level must be a mapping")
    return loaded


def load(cls: type[T], path: str | Path | None = None, overrides: typing.Iterable[str] = (),
         base: Mapping[str, Any] | None = None) -> T:
    """Load ``cls`` from a YAML file (optional) + a base dict (e.g. a preset) + overrides."""
    data: dict = json.loads(json.dumps(to_dict(dict(base or {}))))  # deep copy
    if path is not None:
        _deep_update(data, read_mapping(path))
    apply_overrides(data, overrides)
    return from_dict(cls, data)


def _deep_update(dst: dict, src: Mapping) -> None:
    for k, v in src.items():
        if isinstance(v, Mapping) and isinstance(dst.get(k), dict):
            _deep_update(dst[k], v)
        else:
            dst[k] = v


def save(cfg: Any, path: str | Path) -> Path:
    """Write the resolved config as YAML (atomically) next to an output."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = p.with_name(p.name + ".tmp")
    tmp.write_text(yaml.safe_dump(to_dict(cfg), sort_keys=False))
    tmp.replace(p)
    return p
