"""Build an op's config dataclass from a model-card section, with errors that name the field; and
the checks every verb makes of its arguments before it works (types, counts, writable and
non-destructive output paths, ``--set`` pairs)."""

from __future__ import annotations

import collections.abc
import dataclasses
import functools
import inspect
import math
import numbers
import os
import types
import typing
from pathlib import Path
from typing import Any, Callable, Mapping, Type, TypeVar

import numpy as np
import yaml

from .errors import ConfigError

T = TypeVar("T")


@dataclasses.dataclass(frozen=True)
class Range:
    """The values a numeric card field may take: ``low`` .. ``high``, each end closed unless marked
    open. A tuple field's range applies to each of its numbers."""

    low: float
    high: float
    low_open: bool = False
    high_open: bool = False

    def __contains__(self, v) -> bool:
        above = v > self.low if self.low_open else v >= self.low
        below = v < self.high if self.high_open else v <= self.high
        return bool(above and below)

    def __str__(self) -> str:
        return f"{'(' if self.low_open else '['}{self.low:g}, {self.high:g}{')' if self.high_open else ']'}"


def positive(high: float) -> Range:
    """``(0, high]``: sizes, radii, thresholds that must exceed zero."""
    return Range(0.0, high, low_open=True)


def card_ranges(**ranges: Range | tuple) -> Callable[[Type[T]], Type[T]]:
    """Class decorator: the allowed range of each numeric field of a card-section dataclass,
    checked by :func:`config_from_dict` (a pair ``(low, high)`` is the closed range).
    ``tests/test_config.py`` asserts that every numeric field of every card section has one."""

    def attach(cls: Type[T]) -> Type[T]:
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = set(ranges) - names
        if unknown:
            raise TypeError(f"card_ranges on {cls.__name__}: no field(s) {sorted(unknown)}")
        cls.__card_ranges__ = {k: v if isinstance(v, Range) else Range(*v) for k, v in ranges.items()}
        return cls

    return attach


def field_range(cls: type, name: str) -> Range | None:
    """The declared range of field ``name`` of card section ``cls`` (None if it has none)."""
    return getattr(cls, "__card_ranges__", {}).get(name)


def _numbers(value) -> list:
    """Every leaf of a (nested) tuple/list, or [value] for a scalar."""
    if isinstance(value, (tuple, list)):
        return [x for v in value for x in _numbers(v)]
    return [value]


def check_numbers(value, rng: Range | None, integral: bool, where: str):
    """Each number in ``value`` (a number or nested tuple of numbers) is finite, of the right kind
    and inside ``rng``; ConfigError naming ``where`` and the range otherwise."""
    kind = "an integer" if integral else "a number"
    span = f" in {rng}" if rng is not None else ""
    for x in _numbers(value):
        if isinstance(x, bool) or not isinstance(x, (int, float)):
            raise ConfigError(f"{where}: expected {kind}{span}, got {value!r}")
        if not math.isfinite(x):
            raise ConfigError(f"{where}: expected a finite number{span}, got {value!r}")
        if integral and isinstance(x, float) and not x.is_integer():
            raise ConfigError(f"{where}: expected an integer{span}, got {value!r}")
        if rng is not None and x not in rng:
            raise ConfigError(f"{where}: {x!r} is out of range; allowed {rng}")


def _integral_default(default) -> bool:
    nums = _numbers(default)
    return bool(nums) and all(isinstance(x, int) and not isinstance(x, bool) for x in nums)


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
    ``<=`` check and silently breaks the graph) and inside the field's declared range
    (:func:`card_ranges`); tuples of numbers are checked number by number.
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
        rng = field_range(cls, name)
        if isinstance(default, tuple) and isinstance(value, list):
            value = _tuples(value)
        if isinstance(default, bool) and not isinstance(value, bool):
            raise ConfigError(f"{where}.{name}: expected true/false, got {value!r}")
        if isinstance(default, str) and not isinstance(value, str):
            raise ConfigError(f"{where}.{name}: expected a string, got {value!r}")
        if isinstance(default, tuple) and not isinstance(value, tuple):
            raise ConfigError(f"{where}.{name}: expected a list, got {value!r}")
        if isinstance(default, (int, float)) and not isinstance(default, bool):
            if isinstance(value, (list, tuple, dict)):
                kind = "an integer" if isinstance(default, int) else "a number"
                raise ConfigError(f"{where}.{name}: expected {kind}{f' in {rng}' if rng else ''}, got {value!r}")
            check_numbers(value, rng, isinstance(default, int), f"{where}.{name}")
            value = float(value) if isinstance(default, float) else int(value)
        elif rng is not None or (
            isinstance(default, tuple)
            and default
            and _numbers(default)
            and all(isinstance(x, (int, float)) for x in _numbers(default))
        ):
            check_numbers(value, rng, _integral_default(default), f"{where}.{name}")
        kwargs[name] = value
    missing = [
        f.name
        for f in fields.values()
        if f.name not in kwargs and f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING
    ]
    if missing:
        raise ConfigError(f"{where}: missing field(s) {missing}")
    try:
        obj = cls(**kwargs)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{where}: {exc}") from exc
    return obj


def _tuples(value):
    """A YAML list as a tuple, nested lists included."""
    return tuple(_tuples(v) for v in value) if isinstance(value, list) else value


def check_writable_dir(directory, option: str, create: bool = False) -> None:
    """ConfigError naming ``option`` unless files can be written into ``directory``: its nearest
    existing ancestor is a writable directory (checked before a long run, not after it, and
    without leaving anything behind); with ``create`` the directory is made now."""
    directory = Path(directory)
    if create:
        try:
            directory.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise ConfigError(f"{option}: cannot create the directory {directory} ({exc.strerror or exc})") from None
    existing = directory
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        raise ConfigError(f"{option}: cannot create {directory}: {existing} is not a directory")
    if not os.access(existing, os.W_OK):
        raise ConfigError(f"{option}: {existing} is not writable")


def _accepts(hint, value) -> bool:
    """Whether ``value`` is of the annotated type ``hint`` (a class, a union, a parametrised
    list / tuple / dict / Callable; their items are not looked into). A ``Path`` accepts any
    ``os.PathLike``, a ``float`` an ``int``; ``Any`` anything."""
    if hint is Any or hint is object:
        return True
    if hint is None or hint is type(None):
        return value is None
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        return any(_accepts(h, value) for h in typing.get_args(hint))
    if origin is collections.abc.Callable or hint is collections.abc.Callable:
        return callable(value)
    cls = origin or hint
    if not isinstance(cls, type):
        return True  # a TypeVar, a Literal: left to the function
    if issubclass(cls, os.PathLike) or cls is Path:
        return isinstance(value, (str, os.PathLike))
    if cls in (int, float):  # numpy's scalars too (np.int64, np.float32); a bool is no count
        wanted = numbers.Integral if cls is int else numbers.Real
        return isinstance(value, wanted) and not isinstance(value, (bool, np.bool_))
    return isinstance(value, cls)


def _type_name(hint) -> str:
    if hint is None or hint is type(None):
        return "None"
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        return " or ".join(_type_name(h) for h in typing.get_args(hint))
    if typing.get_origin(hint) is collections.abc.Callable or hint is collections.abc.Callable:
        return "a callable"
    cls = typing.get_origin(hint) or hint
    return "a path" if cls is Path else getattr(cls, "__name__", str(hint))


def checked_arguments(fn: Callable) -> Callable:
    """``fn`` with every argument checked against its annotation before the call: a value of
    another type (None where a path is needed, an int for a path, a generator for a list) is a
    ConfigError naming the function, the parameter and what it takes, never a TypeError from
    deep inside. The API verbs and the runtime's loaders are wrapped with it."""
    signature = inspect.signature(fn)
    hints: dict = {}

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        if not hints:
            hints.update(typing.get_type_hints(fn))
            hints.pop("return", None)
        try:
            bound = signature.bind(*args, **kwargs)
        except TypeError as exc:
            raise ConfigError(f"{fn.__name__}: {exc}") from None
        for name, value in bound.arguments.items():
            hint = hints.get(name)
            if (
                hint is not None
                and signature.parameters[name].kind
                not in (inspect.Parameter.VAR_POSITIONAL, inspect.Parameter.VAR_KEYWORD)
                and not _accepts(hint, value)
            ):
                shown = repr(value) if len(repr(value)) <= 60 else repr(value)[:57] + "..."
                raise ConfigError(
                    f"{fn.__name__}: {name}: expected {_type_name(hint)}, got {type(value).__name__} {shown}"
                )
        return fn(*args, **kwargs)

    return wrapper


def same_path(a, b) -> bool:
    """True when ``a`` and ``b`` name the same file or directory: :func:`os.path.samefile` when
    both exist (symlinks followed, hard links seen), else their absolute, symlink-resolved paths
    are equal (a file not yet written)."""
    a, b = Path(a), Path(b)
    try:
        if a.exists() and b.exists():
            return os.path.samefile(a, b)
        return a.resolve() == b.resolve()
    except (OSError, RuntimeError):  # a symlink loop, a path too long: not the same file
        return False


def _paths(value) -> list[Path]:
    """``value`` as a list of paths: None is none, a path one, an iterable of paths each."""
    if value is None:
        return []
    if isinstance(value, (str, os.PathLike)):
        return [Path(value)]
    return [Path(v) for v in value if v is not None]


def refuse_overwriting_inputs(outputs: Mapping[str, Any], inputs: Mapping[str, Any]) -> None:
    """ConfigError (before anything is written) when a path the command would write is one of
    its inputs, or two of its outputs are one file. ``outputs`` maps an option (``--out``) to
    the path, or the paths, written under it (a directory output lists the directory and the
    files it will hold); ``inputs`` maps an option to the path or paths it reads (None: not
    given). Paths are compared resolved, symlinks and hard links followed (:func:`same_path`)."""
    given = [(option, path) for option, value in inputs.items() for path in _paths(value)]
    seen: list[tuple[str, Path]] = []
    for option, value in outputs.items():
        for path in _paths(value):
            for in_option, source in given:
                if same_path(path, source):
                    raise ConfigError(
                        f"{option} {path}: that is the {in_option} input {source}; writing it "
                        f"would destroy the input: choose another {option}"
                    )
            for other_option, other in seen:
                if other_option != option and same_path(path, other):
                    raise ConfigError(
                        f"{option} {path}: {other_option} writes the same file; give them different paths"
                    )
            seen.append((option, path))


def parse_settings(pairs: tuple[str, ...], option: str = "--set", example: str = "negatives=8") -> dict:
    """``KEY=VALUE`` pairs (``--set`` options) as a dict, values read as YAML scalars (numbers,
    true/false, words); ConfigError naming ``option`` for a malformed pair or a list/mapping value."""
    out = {}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep or not key.strip():
            raise ConfigError(f"{option} {pair!r}: expected KEY=VALUE, e.g. {option} {example}")
        try:
            parsed = yaml.safe_load(value) if value.strip() else None
        except yaml.YAMLError:
            parsed = value
        if isinstance(parsed, (dict, list)):
            raise ConfigError(
                f"{option} {pair!r}: expected a number, true/false or a word, got a {type(parsed).__name__}"
            )
        out[key.strip()] = parsed
    return out
