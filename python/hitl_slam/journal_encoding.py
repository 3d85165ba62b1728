"""The exact encodings of a session file's values: arrays as ``.npy`` bytes (:func:`encode_array`,
:func:`decode_array`) and event payloads as JSON (:func:`encode_payload`, its integer arrays
written with numpy in fixed-width cells). Used by :mod:`hitl_slam.journal`.
"""

from __future__ import annotations

import io
import json
from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = ["decode_array", "encode_array", "encode_payload"]


def encode_array(array: NDArray[Any]) -> bytes:
    """``array`` as the bytes of a ``.npy`` file (exact: dtype, shape and every bit kept)."""
    buffer = io.BytesIO()
    np.save(buffer, np.ascontiguousarray(array), allow_pickle=False)
    return buffer.getvalue()


def decode_array(blob: bytes) -> NDArray[Any]:
    """The array stored by :func:`encode_array`.

    Raises:
        ValueError: ``blob`` is not the bytes of a ``.npy`` file without objects.
    """
    if not isinstance(blob, bytes):
        raise ValueError(f"a stored array is a {type(blob).__name__}, not bytes")
    try:
        array: NDArray[Any] = np.load(io.BytesIO(blob), allow_pickle=False)
    except (ValueError, OSError, EOFError, TypeError, OverflowError, MemoryError) as exc:
        raise ValueError(f"not a .npy array ({exc})") from None
    if not isinstance(array, np.ndarray):  # pragma: no cover - np.load of .npy bytes
        raise ValueError("not a .npy array")
    return array


_EXACT = 10**15  # below 2^53: integers, and their quotients' floors, are exact in float64
_BLANK = 0  # a byte no JSON text holds: the padding dropped from the fixed-width cells
_SMALL = 10**4  # numbers below it are looked up in a table of their digits
_small_digits: NDArray[np.uint8] | None = None


def _digits(values: NDArray[Any], width: int) -> NDArray[np.uint8]:
    """``(M, width)`` the decimal digits of ``values`` (M,), integers of magnitude below
    :data:`_EXACT`, right-aligned, blank before them; a "-" left of a negative number's."""
    # Below 2^53 the floor of a float quotient of integers is the integer quotient.
    magnitude = np.abs(values.astype(np.float64))
    scale = 10.0 ** np.arange(width - 1, -1, -1)  # the power of ten each column holds
    leading = np.floor(magnitude[:, None] / scale)  # the number's digits down to each column
    chars: NDArray[np.uint8] = (leading - 10.0 * np.floor(leading / 10.0) + ord("0")).astype(
        np.uint8
    )
    blank = leading == 0.0
    blank[:, -1] = False  # a zero is "0"
    chars[blank] = _BLANK
    negative = np.flatnonzero(values < 0)
    if negative.size:
        first = blank[negative].sum(axis=1)  # the column of the first digit
        chars[negative, first - 1] = ord("-")
    return chars


def _integers_json(array: NDArray[Any]) -> str:
    """``json.dumps(array.tolist())`` of a 1-D or 2-D integer array, the same text built with
    numpy (digits in fixed-width cells, the padding dropped) instead of a Python list per row:
    an interpretation's observation rows (tens of thousands) cost well under a millisecond, not
    the lists, their encoding and the garbage collections they set off."""
    global _small_digits
    if array.dtype.kind not in "iu" or array.ndim not in (1, 2) or array.size == 0:
        return json.dumps(array.tolist())
    low, high = int(array.min()), int(array.max())
    if low <= -_EXACT or high >= _EXACT:
        return json.dumps(array.tolist())
    flat = array.ravel()  # row-major, the order of tolist()
    width = max(len(str(low)), len(str(high)))
    if low >= 0 and high < _SMALL:  # pose and point indices, as a rule
        if _small_digits is None:
            _small_digits = _digits(np.arange(_SMALL), len(str(_SMALL - 1)))
        chars = _small_digits[flat][:, _small_digits.shape[1] - width :]
    else:
        chars = _digits(flat, width)
    # One cell per number: its digits then ", ".
    columns = 1 if array.ndim == 1 else array.shape[1]
    cells = np.empty((flat.size // columns, columns, width + 2), dtype=np.uint8)
    cells[:, :, :width] = chars.reshape(-1, columns, width)
    cells[:, :, width] = ord(",")
    cells[:, :, width + 1] = ord(" ")
    if array.ndim == 2:
        # A row: "[" + its cells, the last one closed by "], " instead of ", ".
        rows = np.empty((cells.shape[0], 1 + columns * (width + 2) + 1), dtype=np.uint8)
        rows[:, 0] = ord("[")
        rows[:, 1:-1] = cells.reshape(cells.shape[0], -1)
        rows[:, -3:] = (ord("]"), ord(","), ord(" "))
        text = rows.ravel()
    else:
        text = cells.ravel()
    body = text[text != _BLANK][:-2].tobytes().decode("ascii")
    return f"[{body}]"


def encode_payload(payload: dict[str, Any]) -> str:
    """An event's payload as JSON: ``json.dumps(payload)``, except that a value of a dict may
    also be a numpy integer array, written as the JSON of its ``tolist()`` (the same text)."""

    def encode(value: Any) -> str:
        if isinstance(value, np.ndarray):
            return _integers_json(value)
        if isinstance(value, dict) and value and all(isinstance(k, str) for k in value):
            items = ", ".join(f"{json.dumps(k)}: {encode(v)}" for k, v in value.items())
            return f"{{{items}}}"
        return json.dumps(value)

    return encode(payload)
