"""Typed, frozen configs: one way to build one from a dict, to override its fields, and to check its modes.

Every static config in the project (the methods', the teacher reward's, the level sampler's, the
student's ``PPOConfig``) is a frozen dataclass. A field whose values are a closed set of names is
annotated ``Literal[...]`` and checked by :func:`check_modes` in the class's ``__post_init__``; a
field whose default is itself a config (PLR's ``sampler``, the teacher's ``reward``) is *nested*.

* :func:`from_dict` rebuilds a config from its JSON form (``dataclasses.asdict`` as ``config.json``
  and checkpoints hold it): nested dicts become their dataclasses, lists become tuples, and fields
  missing from the dict keep their defaults. That form is strict JSON: :func:`finite_json` names
  a non-finite float (e.g. an unbounded ``PPOConfig.log_std_max``) ``"inf"``, and :func:`from_dict`
  reads the name back.
* :func:`check_number` checks a numeric field against a bound, with the one-line message every
  config uses.
* :func:`with_overrides` replaces fields by name; a dict given for a nested field is merged into it.
  Unknown fields and values of the wrong kind are a ``ValueError`` of one line that names the field
  and what it takes.
"""
from __future__ import annotations

import dataclasses
import functools
import json
import math
import typing
from typing import Literal


def is_config(value) -> bool:
    """Whether ``value`` is a dataclass instance (a config, possibly nested in another)."""
    return dataclasses.is_dataclass(value) and not isinstance(value, type)


@functools.cache
def _modes(cls) -> dict[str, tuple]:
    """Field -> allowed values, for the fields of ``cls`` annotated ``Literal[...]``."""
    hints = typing.get_type_hints(cls)
    return {f.name: typing.get_args(hints[f.name]) for f in dataclasses.fields(cls)
            if typing.get_origin(hints.get(f.name)) is Literal}


def check_modes(obj) -> None:
    """ValueError naming ``<Class>.<field>`` and the allowed values for a Literal field holding another value."""
    for name, allowed in _modes(type(obj)).items():
        value = getattr(obj, name)
        if value not in allowed:
            raise ValueError(f"{type(obj).__name__}.{name} must be one of {', '.join(map(repr, allowed))}, got {value!r}")


def modes(cls, name: str) -> tuple:
    """The allowed values of ``cls``'s Literal field ``name``."""
    return _modes(cls)[name]


def check_number(obj, field: str, *, above: float | None = None, at_least: float | None = None,
                 finite: bool = True) -> None:
    """``obj.field`` must be a number (``finite``: and finite) ``> above`` or ``>= at_least``; else a
    ``ValueError`` of one line naming the class, the field and the rule, e.g. ``SHEDXConfig.syn_sigma
    must be a finite number >= 0, got -1``."""
    v = getattr(obj, field)
    ok = isinstance(v, (int, float)) and (not finite or math.isfinite(v))
    ok = ok and (above is None or v > above) and (at_least is None or v >= at_least)
    if not ok:
        rule = f"> {above:g}" if above is not None else f">= {at_least:g}"
        raise ValueError(f"{type(obj).__name__}.{field} must be a {'finite ' if finite else ''}number {rule}, got {v!r}")


def _field_names(cls) -> list[str]:
    return [f.name for f in dataclasses.fields(cls)]


def _unknown(cls, keys, where: str) -> None:
    unknown = sorted(set(keys) - set(_field_names(cls)))
    if unknown:
        where = f"{where.rstrip(': .')}: " if where else ""
        raise ValueError(f"{where}{cls.__name__} has no field(s) {', '.join(map(repr, unknown))}; "
                         f"known: {', '.join(sorted(_field_names(cls)))}")


def _tuples(x):
    if isinstance(x, list):
        return tuple(_tuples(v) for v in x)
    return x


def _nested_class(cls, name: str):
    """The config class of field ``name`` if its default is a config instance, else None."""
    f = {f.name: f for f in dataclasses.fields(cls)}[name]
    return type(f.default) if is_config(f.default) else None


#: how the JSON form names a non-finite float (strict JSON has no Infinity or NaN)
NONFINITE_NAMES = {"inf": math.inf, "-inf": -math.inf, "nan": math.nan}


def finite_json(value):
    """``value`` (already of JSON's types) with each non-finite float replaced by its name in
    :data:`NONFINITE_NAMES`, so that ``json.dumps(..., allow_nan=False)`` writes it; :func:`from_dict`
    reads a float field's name back. Other values pass through."""
    if isinstance(value, float) and not math.isfinite(value):
        return "nan" if math.isnan(value) else ("inf" if value > 0 else "-inf")
    if isinstance(value, dict):
        return {k: finite_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [finite_json(v) for v in value]
    return value


def from_dict(cls, values: dict | None, where: str = ""):
    """``cls`` built from ``values`` (its JSON form, possibly partial): nested configs from their
    dicts, lists as tuples, a float field's ``"inf"``, ``"-inf"`` or ``"nan"`` as that float,
    missing fields at their defaults. Unknown fields: ValueError."""
    values = dict(values or {})
    _unknown(cls, values, where)
    kwargs = {}
    for name, value in values.items():
        sub = _nested_class(cls, name)
        if sub is not None and isinstance(value, dict):
            kwargs[name] = from_dict(sub, value, f"{where}{name}: ")
        elif isinstance(_default(cls, name), float) and value in NONFINITE_NAMES:
            kwargs[name] = NONFINITE_NAMES[value]
        else:
            kwargs[name] = _tuples(value)
    return cls(**kwargs)


def coerce(cls, config, owner: str):
    """``config`` as a ``cls``: None gives the defaults, a dict is read by :func:`from_dict`, a ``cls``
    passes through. ``owner`` (e.g. ``"method 'hmdp'"``) starts the one-line errors."""
    if config is None:
        return cls()
    if isinstance(config, dict):
        unknown = sorted(set(config) - set(_field_names(cls)))
        if unknown:
            hints = [f"{k!r} is a field of {n!r}, given inside it: {n}={{\"{k}\": <value>}}"
                     for k in unknown for n in _field_names(cls)
                     if _nested_class(cls, n) is not None and k in _field_names(_nested_class(cls, n))]
            raise ValueError(f"{owner}: unknown config field(s) {unknown}{'; ' if hints else ''}{'; '.join(hints)}; "
                             f"known: {sorted(_field_names(cls))}")
        return from_dict(cls, config)
    if type(config) is not cls:
        raise TypeError(f"{owner}: config must be None, a dict or a {cls.__name__}, got {type(config).__name__}")
    return config


def with_overrides(obj, overrides: dict | None, where: str = ""):
    """``obj`` with fields replaced by name; a dict for a nested config field is merged into that config.

    A value must be of the kind of the field's default (a number, a string, true/false, a JSON object
    for a nested config); a field whose default is None takes anything its class accepts. The result
    is validated by the class as any new instance is.
    """
    if not overrides:
        return obj
    cls = type(obj)
    _unknown(cls, overrides, where)
    changes = {}
    for name, value in overrides.items():
        current = getattr(obj, name)
        if is_config(current):
            if isinstance(value, dict):
                value = with_overrides(current, value, f"{where}{name}.")
            elif not isinstance(value, type(current)):
                raise ValueError(f"{where}{name}: expected a JSON object of {type(current).__name__} fields, "
                                 f"got {json.dumps(value, default=str)}")
        else:
            _check_kind(_default(cls, name), value, f"{where}{name}")
            value = _tuples(value)
        changes[name] = value
    return dataclasses.replace(obj, **changes)


def _default(cls, name: str):
    f = {f.name: f for f in dataclasses.fields(cls)}[name]
    return f.default


def _check_kind(default, value, key: str) -> None:
    """ValueError unless ``value`` is of the kind of ``default`` (None and missing defaults accept anything)."""
    if value is None or default is None or default is dataclasses.MISSING:
        return
    if isinstance(default, bool):
        ok, kind = isinstance(value, bool), "true or false"
    elif isinstance(default, (int, float)):
        ok, kind = isinstance(value, (int, float)) and not isinstance(value, bool), "a number"
    elif isinstance(default, str):
        ok, kind = isinstance(value, str), "a string"
    elif isinstance(default, tuple):
        ok, kind = isinstance(value, (list, tuple)), "a list"
    else:
        return
    if not ok:
        raise ValueError(f"{key}: expected {kind}, got {json.dumps(value, default=str)}")


def to_dict(obj) -> dict:
    """The JSON form of a config (every field, nested configs as dicts); :func:`from_dict` inverts it."""
    return dataclasses.asdict(obj)


__all__ = ["NONFINITE_NAMES", "check_modes", "finite_json", "from_dict", "is_config", "modes", "to_dict", "with_overrides"]
