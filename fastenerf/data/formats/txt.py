"""Text event files: one event per line, `t x y p` or `x y t p`, whitespace-separated.

- Header: an optional first line `width height` (two integers), as in the rpg / ECD-style
  files; `#` starts a comment; blank lines are skipped.
- Column order: `order="txyp"` or `"xytp"`, or detected (None): the time column is the one
  that does not decrease and may hold fractions, x and y are non-negative integers (inside
  the sensor when its size is known). A file that fits both orders equally (e.g. one event)
  needs `order`.
- Time: `time_unit` "s", "ms", "us" or "ns" per unit of the file's t; detected (None) as
  seconds when t is written with a decimal point or exponent (ECD: `0.000102 33 39 1`), else
  integer microseconds. Stored as int64 µs (rounded to the nearest µs).
- Sensor: `width`/`height` arguments, else the header, else max(x) + 1 by max(y) + 1.
- Polarity: ±1 or 0/1 (stored as ±1).
Malformed lines raise one `InputError` naming the file and the line number.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from ...errors import InputError
from ..events import EventStream

ORDERS = {"txyp": (0, 1, 2), "xytp": (2, 0, 1)}  # column of (t, x, y); p is always the 4th
TIME_UNITS_US = {"s": 1e6, "ms": 1e3, "us": 1.0, "ns": 1e-3}


def read_txt(
    path: str | Path,
    width: int | None = None,
    height: int | None = None,
    *,
    order: str | None = None,
    time_unit: str | None = None,
) -> EventStream:
    """Read a text event file into an `EventStream` (t in int64 µs; see the module docstring)."""
    path = Path(path)
    if order is not None and order not in ORDERS:
        raise InputError(f"{path}: order must be one of {list(ORDERS)}, got {order!r}")
    if time_unit is not None and time_unit not in TIME_UNITS_US:
        raise InputError(
            f"{path}: time_unit must be one of {list(TIME_UNITS_US)}, got {time_unit!r}"
        )
    header, skip, first_data = _header(path)
    if width is None or height is None:
        width, height = header if header else (None, None)
    try:
        with warnings.catch_warnings():  # an empty file is reported below, in one line
            warnings.simplefilter("ignore", UserWarning)
            arr = np.loadtxt(path, comments="#", skiprows=skip, ndmin=2, dtype=np.float64)
    except ValueError as e:
        raise _locate_error(path, skip, e) from None
    except OSError as e:
        raise InputError(f"{path}: cannot read ({e})") from None
    if arr.size == 0:
        raise InputError(f"{path}: no events")
    if arr.shape[1] != 4:
        raise InputError(
            f"{path}: line {first_data}: expected 4 columns (t x y p or x y t p), "
            f"found {arr.shape[1]}"
        )
    order = order or _detect_order(path, arr, width, height)
    ti, xi, yi = ORDERS[order]
    t, x, y, p = arr[:, ti], arr[:, xi], arr[:, yi], arr[:, 3]
    if time_unit is None:
        time_unit = "s" if _looks_fractional(path, skip, ti, t) else "us"
    t_us = np.round(t * TIME_UNITS_US[time_unit]) if np.all(np.isfinite(t)) else t
    if width is None or height is None:
        ok = np.isfinite(x).all() and np.isfinite(y).all() and len(x)
        width = int(max(x.max(), 0)) + 1 if ok else 1
        height = int(max(y.max(), 0)) + 1 if ok else 1
    try:
        return EventStream.from_arrays(x, y, t_us, p, width, height, source=str(path))
    except InputError:  # say it again with file line numbers (a slow pass, errors only)
        lines = _data_line_numbers(path, skip)
        return EventStream.from_arrays(x, y, t_us, p, width, height, source=str(path), lines=lines)


def txt_header(path: str | Path) -> tuple[int, int] | None:
    """The (width, height) header line of a text event file, or None."""
    return _header(Path(path))[0]


def _lines(path: Path):
    """(1-based line number, text) of every line, read lazily."""
    try:
        with open(path, encoding="utf-8", errors="replace") as f:
            yield from enumerate(f, 1)
    except OSError as e:
        raise InputError(f"{path}: cannot read ({e})") from None


def _tokens(line: str) -> list[str]:
    return line.split("#", 1)[0].split()


def _header(path: Path) -> tuple[tuple[int, int] | None, int, int]:
    """(header size or None, lines to skip before the data, line number of the first data)."""
    if not path.is_file():
        raise InputError(f"{path}: file not found")
    for no, line in _lines(path):
        tok = _tokens(line)
        if not tok:
            continue
        if len(tok) == 2 and all(s.isdigit() for s in tok):
            w, h = int(tok[0]), int(tok[1])
            if w <= 0 or h <= 0:
                raise InputError(f"{path}: line {no}: sensor size {w}x{h} is not valid")
            return (w, h), no, no + 1
        return None, 0, no
    raise InputError(f"{path}: no events")


def _data_rows(path: Path, skip: int):
    for no, line in _lines(path):
        if no <= skip:
            continue
        tok = _tokens(line)
        if tok:
            yield no, tok


def _data_line_numbers(path: Path, skip: int) -> np.ndarray:
    return np.fromiter((no for no, _ in _data_rows(path, skip)), dtype=np.int64)


def _locate_error(path: Path, skip: int, err: Exception) -> InputError:
    """Find the first malformed line again in Python, for a message with its number."""
    for no, tok in _data_rows(path, skip):
        if len(tok) != 4:
            return InputError(
                f"{path}: line {no}: expected 4 columns (t x y p or x y t p), found {len(tok)}"
            )
        for s in tok:
            try:
                float(s)
            except ValueError:
                return InputError(f"{path}: line {no}: {s!r} is not a number")
    return InputError(f"{path}: cannot parse ({err})")


def _integral(a: np.ndarray) -> bool:
    return bool(np.all(np.isfinite(a)) and np.all(a == np.round(a)))


def _detect_order(path: Path, arr: np.ndarray, width: int | None, height: int | None) -> str:
    def score(order: str) -> tuple[bool, bool, float]:
        ti, xi, yi = ORDERS[order]
        x, y, t = arr[:, xi], arr[:, yi], arr[:, ti]
        coords_ok = _integral(x) and _integral(y) and x.min() >= 0 and y.min() >= 0
        if width is not None and coords_ok:
            coords_ok = x.max() < width and y.max() < height
        sorted_frac = float(np.mean(np.diff(t) >= 0)) if len(t) > 1 else 1.0
        return coords_ok, not _integral(t), sorted_frac

    scores = {o: score(o) for o in ORDERS}
    best = sorted(ORDERS, key=lambda o: scores[o], reverse=True)
    if scores[best[0]] == scores[best[1]]:
        raise InputError(
            f"{path}: cannot tell whether the columns are t x y p or x y t p; "
            "pass order='txyp' or order='xytp'"
        )
    return best[0]


def _looks_fractional(path: Path, skip: int, ti: int, t: np.ndarray) -> bool:
    """Seconds if any t has a fraction or the first t is written as a decimal or exponent."""
    if not _integral(t):
        return True
    for _, tok in _data_rows(path, skip):
        return any(c in tok[ti] for c in ".eE")
    return False
