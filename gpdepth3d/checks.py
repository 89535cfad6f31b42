"""One validation vocabulary for the package's configs and public arguments (kornia ``core/check.py`` style).

Every check raises `InvalidInputError` naming the argument, what was expected and what came, and returns the
value in its canonical type (a Python ``int``, ``float`` or ``bool``), so a frozen config stores what it
checked. The same rules hold everywhere: a bool is never a number, a float is never an integer (``3.0`` is
refused where an integer is expected), numbers are finite.

A config states its fields' rules as a table and checks them in one call::

    check_fields(self, {"max_points": Int(1), "ratio": Real(0, 1, low_open=True), "fit": Bool()})

Depends on `errors` only, so that every layer (`gp` included) may use it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from .errors import InvalidInputError, describe


def is_real(value: Any) -> bool:
    """True for a real number (int or float, numpy scalars included); False for bool, str, None."""
    return not isinstance(value, (bool, np.bool_)) and isinstance(value, (int, float, np.integer, np.floating))


def is_integer(value: Any) -> bool:
    """True for an int or numpy integer; False for bool and for floats, even integral ones."""
    return not isinstance(value, (bool, np.bool_)) and isinstance(value, (int, np.integer))


def check_bool(name: str, value: Any) -> bool:
    """``value`` as a bool when it is True or False (numpy's included), else `InvalidInputError`."""
    if not isinstance(value, (bool, np.bool_)):
        raise InvalidInputError(name, "True or False", describe(value))
    return bool(value)


def _interval(low: float, high: float, low_open: bool, high_open: bool) -> str:
    if math.isinf(high):
        return f"{'>' if low_open else '>='} {low:g}"
    if math.isinf(low):
        return f"{'<' if high_open else '<='} {high:g}"
    return f"in {'(' if low_open else '['}{low:g}, {high:g}{')' if high_open else ']'}"


def check_int(name: str, value: Any, low: int | None = None, high: int | None = None, *, optional: bool = False):
    """``value`` as an int in [low, high] (None: unbounded; ``optional``: None passes), else `InvalidInputError`."""
    if value is None and optional:
        return None
    if not is_integer(value) or (low is not None and value < low) or (high is not None and value > high):
        lo, hi = -math.inf if low is None else low, math.inf if high is None else high
        bound = "" if lo == -math.inf and hi == math.inf else " " + _interval(lo, hi, False, False)
        expected = f"an integer{bound}" + (", or None" if optional else "")
        raise InvalidInputError(name, expected, describe(value))
    return int(value)


def check_real(
    name: str,
    value: Any,
    low: float = -math.inf,
    high: float = math.inf,
    *,
    low_open: bool = False,
    high_open: bool = False,
    unit: str = "",
    optional: bool = False,
):
    """``value`` as a finite float in the interval (bounds closed unless ``*_open``; ``optional``: None passes)."""
    if value is None and optional:
        return None
    ok = is_real(value) and math.isfinite(value)
    if ok and not ((value > low if low_open else value >= low) and (value < high if high_open else value <= high)):
        ok = False
    if not ok:
        if math.isinf(low) and math.isinf(high):
            expected = "a finite number"
        elif math.isinf(low) or math.isinf(high):
            expected = f"a finite number {_interval(low, high, low_open, high_open)}"
        else:  # an interval is finite
            expected = f"a number {_interval(low, high, low_open, high_open)}"
        expected += (f" ({unit})" if unit else "") + (", or None" if optional else "")
        raise InvalidInputError(name, expected, describe(value))
    return float(value)


def check_choice(name: str, value: Any, choices: tuple) -> Any:
    """``value`` when it is one of ``choices`` (strings compared as strings only), else `InvalidInputError`."""
    if not isinstance(value, (str, type(None))) or value not in choices:
        raise InvalidInputError(name, " or ".join(repr(c) for c in choices), describe(value))
    return value


class Rule(Protocol):
    """A field's check: the value in its canonical type, or `InvalidInputError` naming the field."""

    def __call__(self, name: str, value: Any) -> Any: ...


@dataclass(frozen=True)
class Bool:
    """True or False."""

    def __call__(self, name: str, value: Any) -> bool:
        return check_bool(name, value)


@dataclass(frozen=True)
class Int:
    """An integer in [low, high] (`check_int`)."""

    low: int | None = None
    high: int | None = None
    optional: bool = False

    def __call__(self, name: str, value: Any):
        return check_int(name, value, self.low, self.high, optional=self.optional)


@dataclass(frozen=True)
class Real:
    """A finite number in an interval, with its unit (`check_real`)."""

    low: float = -math.inf
    high: float = math.inf
    low_open: bool = False
    high_open: bool = False
    unit: str = ""
    optional: bool = False

    def __call__(self, name: str, value: Any):
        return check_real(
            name,
            value,
            self.low,
            self.high,
            low_open=self.low_open,
            high_open=self.high_open,
            unit=self.unit,
            optional=self.optional,
        )


@dataclass(frozen=True)
class Reals:
    """A non-empty sequence of numbers, each checked by ``each``; stored as a tuple of floats."""

    each: Real

    def __call__(self, name: str, value: Any) -> tuple:
        if isinstance(value, (str, bytes)) or not hasattr(value, "__len__") or not len(value):
            raise InvalidInputError(name, "a non-empty tuple of numbers", describe(value))
        return tuple(self.each(name, v) for v in value)


@dataclass(frozen=True)
class Choice:
    """One of the given values."""

    options: tuple

    def __call__(self, name: str, value: Any):
        return check_choice(name, value, self.options)


@dataclass(frozen=True)
class Instance:
    """An instance of ``kind`` (a nested config)."""

    kind: type

    def __call__(self, name: str, value: Any):
        if not isinstance(value, self.kind):
            raise InvalidInputError(name, f"a {self.kind.__name__}", describe(value))
        return value


def positive(unit: str = "", *, optional: bool = False) -> Real:
    """A finite number > 0."""
    return Real(0.0, low_open=True, unit=unit, optional=optional)


def non_negative(unit: str = "", *, optional: bool = False) -> Real:
    """A finite number >= 0."""
    return Real(0.0, unit=unit, optional=optional)


def check_fields(config: Any, rules: dict[str, Rule]) -> None:
    """Checks each field of ``config`` by its rule and stores the checked value (frozen dataclasses included)."""
    for name, rule in rules.items():
        object.__setattr__(config, name, rule(name, getattr(config, name)))
