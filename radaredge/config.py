"""Build an op's config dataclass from a model-card section, with errors that name the field."""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Mapping, Type, TypeVar

from .errors import ConfigError

T = TypeVar("T")


def check_count(name: str, value, low: int, high: int) -> int:
    """``value`` as an int in ``low`` .. ``high``; ConfigError naming ``name`` and the range otherwise
    (case, run and thread counts of the verbs)."""
    if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
        raise ConfigError(f"{name}: expected an integer from {low} to {high}, got {value!r}")
    return value


def config_from_dict(cls: Type[T], data: Mapping[str, Any] | None, where: str) -> T:
    """Instantiate dataclass ``cls`` from ``data``; unknown keys and bad types raise ConfigError.

    ``where`` is the card path of the section (e.g. ``"tdfanet.yaml: preprocess.ransac"``) and
    appears in every message. Missing keys take the dataclass defaults. Lists become tuples when
    the default is a tuple. Numbers must be finite (a NaN or infinite threshold passes every
    ``<=`` check and silently breaks the graph).
    """
    data = dict(data or {})
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise ConfigError(f"{where}: unknown field(s) {unknown}; expected some of {sorted(fields)}")
    kwargs = {}
    for name, value in data.items():
        f = fields[name]
        default = f.default if f.default is not dataclasses.MISSING else None
        if isinstance(default, tuple) and isinstance(value, list):
            value = tuple(value)
        if isinstance(default, bool) and not isinstance(value, bool):
            raise ConfigError(f"{where}.{name}: expected true/false, got {value!r}")
        if isinstance(default, (int, float)) and not isinstance(default, bool):
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ConfigError(f"{where}.{name}: expected a number, got {value!r}")
            if not math.isfinite(value):
                raise ConfigError(f"{where}.{name}: expected a finite number, got {value!r}")
            if isinstance(default, float):
                value = float(value)
            elif isinstance(value, float) and not value.is_integer():
                raise ConfigError(f"{where}.{name}: expected an integer, got {value!r}")
            else:
                value = int(value)
        kwargs[name] = value
    try:
        obj = cls(**kwargs)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{where}: {exc}") from exc
    return obj
