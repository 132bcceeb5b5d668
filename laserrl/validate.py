"""Checks of single config values, for the builders and dataclasses that own them.

Every message starts with the value's config key (``optim.lr must be > 0, got -0.001``), so
that ``laserrl.config.user_errors`` can print it as the one line a user sees.
"""
from __future__ import annotations

import math
from typing import Iterable


class ConfigError(ValueError):
    """A config value is out of range or of the wrong type."""


def check_number(value, name: str, *, low=None, high=None, integer: bool = False, low_open: bool = False,
                 optional: bool = False):
    """``value`` if it is a finite number within [low, high] (or (low, high] with ``low_open``;
    a whole number with ``integer``; None too with ``optional``), else a ConfigError naming ``name``."""
    if optional and value is None:
        return None
    kind = "an integer" if integer else "a number"
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ConfigError(f"{name} must be {kind}, got {value!r}")
    if isinstance(value, float) and not math.isfinite(value):  # before int(), which raises its own error on inf, NaN
        raise ConfigError(f"{name} must be finite, got {value!r}")
    if integer and int(value) != value:
        raise ConfigError(f"{name} must be {kind}, got {value!r}")
    if low is not None and (value <= low if low_open else value < low):
        raise ConfigError(f"{name} must be {'>' if low_open else '>='} {low}, got {value!r}")
    if high is not None and value > high:
        raise ConfigError(f"{name} must be <= {high}, got {value!r}")
    return int(value) if integer else value


def check_numbers(values, name: str, *, optional: bool = False, scalar_ok: bool = False, **limits) -> list | None:
    """A non-empty list of numbers (or, with ``scalar_ok``, one number), each checked like ``check_number``."""
    if optional and values is None:
        return None
    if scalar_ok and not _is_list(values):
        return [check_number(values, name, **limits)]
    if not _is_list(values) or len(values) == 0:
        raise ConfigError(f"{name} must be a non-empty list of numbers, got {values!r}")
    return [check_number(v, f"{name}[{i}]", **limits) for i, v in enumerate(values)]


def check_one_of(value, name: str, choices: Iterable):
    choices = tuple(choices)
    if value not in choices:
        raise ConfigError(f"{name} must be one of {', '.join(map(str, choices))}, got {value!r}")
    return value


def _is_list(value) -> bool:
    from omegaconf import ListConfig

    return isinstance(value, (list, tuple, ListConfig))
