"""One validation layer for every entry point: what an argument of a public function (or a command's option) may
be, checked before any work. A bad value is one ``SettingError`` line naming the argument as its caller spells it
(``seq_len`` from Python, ``--seq-len`` on the command line), never a TypeError from deep inside."""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from seqvpr.errors import SettingError

#: the torch device types seqvpr runs on
DEVICE_TYPES = ("cpu", "cuda", "mps", "xpu")
#: how an image encoder runs (``seqvpr.features.engines``)
ENGINES = ("auto", "torch", "onnx")


def shown(value: Any) -> str:
    """A value as an error message shows it: its repr, cut to 60 characters."""
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def range_text(low: float | None, high: float | None, open_low: bool = False) -> str:
    """An interval as messages write it: ``[1, inf]``, ``(0, 1]``."""
    return f"{'(' if open_low else '['}{'-inf' if low is None else f'{low:g}'}, {'inf' if high is None else f'{high:g}'}]"


def in_range(number: float, low: float | None, high: float | None, open_low: bool = False) -> bool:
    """Whether ``number`` lies in ``range_text(low, high, open_low)``."""
    below = low is not None and (number <= low if open_low else number < low)
    return not below and (high is None or number <= high)


def is_whole(value: Any) -> bool:
    """A Python or numpy integer; never a bool (``True`` is no count) nor a float (``5.0`` is a measure)."""
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))


def whole(value: Any, name: str, low: int | None = None, high: int | None = None) -> int:
    """``value`` as an int within [low, high] (``is_whole``)."""
    if not is_whole(value) or not in_range(int(value), low, high):
        raise SettingError(f"{{{name}}} must be an integer in {range_text(low, high)}, got {shown(value)}")
    return int(value)


def optional_whole(value: Any, name: str, low: int | None = None, high: int | None = None) -> int | None:
    """``whole``, or None as given."""
    return None if value is None else whole(value, name, low, high)


def finite(value: Any, name: str, low: float | None = None, high: float | None = None, open_low: bool = False) -> float:
    """``value`` as a finite float within the interval (a bool is no number)."""
    ok = isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))
    if not ok or not math.isfinite(value) or not in_range(float(value), low, high, open_low):
        raise SettingError(f"{{{name}}} must be a finite number in {range_text(low, high, open_low)}, got {shown(value)}")
    return float(value)


def flag(value: Any, name: str) -> bool:
    """``value`` as a bool: True or False (numpy's too), nothing truthy."""
    if not isinstance(value, (bool, np.bool_)):
        raise SettingError(f"{{{name}}} must be True or False, got {shown(value)}")
    return bool(value)


def text(value: Any, name: str, choices: Sequence[str] | None = None) -> str:
    """``value`` as non-empty text, one of ``choices`` when given."""
    if not isinstance(value, str) or not value.strip():
        raise SettingError(f"{{{name}}} must be text{_choices(choices)}, got {shown(value)}")
    if choices is not None and value not in choices:
        raise SettingError(f"{{{name}}} must be{_choices(choices)}, got {shown(value)}")
    return value


def _choices(choices: Sequence[str] | None) -> str:
    return "" if choices is None else " one of " + ", ".join(repr(c) for c in choices)


def a_path(value: Any, name: str) -> Path:
    """``value`` as a path: text or an ``os.PathLike``, not empty (bytes are refused: seqvpr names files in text)."""
    if isinstance(value, os.PathLike):
        value = os.fspath(value)
    if not isinstance(value, str) or not value.strip():
        raise SettingError(f"{{{name}}} must be a path (text or pathlib.Path), got {shown(value)}")
    return Path(value)


def paths(value: Any, name: str) -> list[str]:
    """One path or a sequence of paths, as a list of texts (a single text is one path, never its characters)."""
    if isinstance(value, (str, os.PathLike)):
        return [str(a_path(value, name))]
    if not isinstance(value, Iterable) or isinstance(value, (bytes, Mapping)):
        raise SettingError(f"{{{name}}} must be a path or a list of paths, got {shown(value)}")
    listed = [str(a_path(item, name)) for item in value]
    if not listed:
        raise SettingError(f"{{{name}}} must name at least one path, got {shown(value)}")
    return listed


def whole_numbers(values: Any, name: str, low: int | None = 1) -> tuple[int, ...]:
    """A non-empty sequence of integers (each ``whole``), as a tuple; one number alone is refused as a list."""
    if isinstance(values, (str, bytes)) or not isinstance(values, Iterable):
        raise SettingError(f"{{{name}}} must be a list of integers, got {shown(values)}")
    numbers = tuple(whole(v, name, low) for v in values)
    if not numbers:
        raise SettingError(f"{{{name}}} must hold at least one integer")
    return numbers


def function(value: Any, name: str) -> Callable | None:
    """A callable, or None as given."""
    if value is not None and not callable(value):
        raise SettingError(f"{{{name}}} must be a function (or None), got {shown(value)}")
    return value


def instance(value: Any, name: str, kind: type | tuple[type, ...], what: str) -> Any:
    """``value`` when it is a ``kind`` (``what`` says which, in words)."""
    if not isinstance(value, kind):
        raise SettingError(f"{{{name}}} must be {what}, got {type(value).__name__} {shown(value)}")
    return value


def device(value: Any, name: str = "device") -> str:
    """A torch device this machine can use (``cpu``, ``cuda``, ``cuda:1``, ``mps``); torch is imported only for a
    device other than ``cpu``."""
    if value == "cpu":
        return value
    if not isinstance(value, str):
        raise SettingError(f"{{{name}}} must be a device name such as 'cpu' or 'cuda', got {shown(value)}")
    import torch

    try:
        if torch.device(value).type not in DEVICE_TYPES:
            raise ValueError(f"seqvpr runs on {', '.join(DEVICE_TYPES)}")
        torch.empty(1, device=value)
    except (RuntimeError, AssertionError, ValueError, TypeError, NotImplementedError) as error:
        reason = str(error).splitlines()[0] if str(error) else type(error).__name__
        raise SettingError(f"{{{name}}} {value!r} is not usable here ({reason})") from None
    return value
