"""Decoding of the version 1 methods PREDICT (3) and QUANT (4) of :mod:`lidarscan.codec`.

The encoder no longer writes them (it writes PREDICT2 / QUANT2 since version 2); buffers of
version 1 stay decodable. Byte format: the table in :mod:`lidarscan.codec`'s header. Residuals
are the byte planes of zigzag(residual) of the whole grid, inverted by cumulative sums.
"""

from __future__ import annotations

import struct
from typing import Any

import numpy as np

from lidarscan.codec._bits import PLANAR, roll, unresidual, unzigzag
from lidarscan.codec._format import (
    _FLOAT32,
    _GRID,
    _INT_CODES,
    _SIZES,
    PREDICT,
    QUANT,
    _float_bits,
    _unmask_frame,
    _unplanes,
    _zd,
)
from lidarscan.errors import DecodeError

__all__ = ["decode_v1"]


def decode_v1(what: str, length: int, method: int, params: bytes, payload: bytes) -> bytes:
    """The ``length`` bytes of a PREDICT or QUANT segment (``what`` names it in errors).

    Raises:
        DecodeError: bad params or a damaged payload.
    """
    if len(params) < _GRID.size:
        raise DecodeError(f"{what} params", len(params), f"at least {_GRID.size} bytes")
    datatype, big, h, w, c, predictor, rolled = _GRID.unpack_from(params)
    base = _GRID.size + (8 if method == QUANT else 0)
    want = base + (4 * h if rolled else 0)
    if len(params) != want:
        raise DecodeError(f"{what} params", len(params), f"{want} bytes")
    ok_type = datatype in _INT_CODES if method == PREDICT else datatype == _FLOAT32
    if not ok_type or predictor > PLANAR or h * w * c * _SIZES.get(datatype, 0) != length:
        raise DecodeError(f"{what} params", (datatype, h, w, c, predictor),
                          f"a grid of {length} bytes with a known datatype and predictor")
    shifts = (np.frombuffer(params, "<i4", h, base).astype(np.int64) if rolled else None)
    if method == PREDICT:
        size = _SIZES[datatype]
        u = roll(_unpredict(payload, (h, w, c), size, predictor, what), shifts, -1)
        return u.astype(u.dtype.newbyteorder(">" if big else "<")).tobytes()
    (step,) = struct.unpack_from("<d", params, _GRID.size)
    bits = _unquant(payload, (h, w, c), predictor, step, bool(big), what)
    return roll(np.frombuffer(bits, np.uint32).reshape(h, w, c), shifts, -1).tobytes()


def _unpredict(payload: bytes, shape: tuple[int, int, int], itemsize: int, predictor: int,
               what: str) -> np.ndarray[Any, Any]:
    n = shape[0] * shape[1] * shape[2]
    z = _unplanes(_zd(payload, n * itemsize, what), itemsize, n, what).view(f"u{itemsize}")
    return unresidual(unzigzag(z).reshape(shape), predictor)


def _unquant(payload: bytes, shape: tuple[int, int, int], predictor: int, step: float,
             bigendian: bool, what: str) -> bytes:
    n = shape[0] * shape[1] * shape[2]
    pos = 0

    def take() -> bytes:
        nonlocal pos
        if pos + 4 > len(payload):
            raise DecodeError(what, len(payload), "a length-prefixed QUANT part")
        (k,) = struct.unpack_from("<I", payload, pos)
        if pos + 4 + k > len(payload):
            raise DecodeError(what, k, f"at most {len(payload) - pos - 4} bytes")
        part = payload[pos + 4: pos + 4 + k]
        pos += 4 + k
        return part

    q = _unpredict(take(), shape, 4, predictor, what).view(np.int32)
    exc = _unmask_frame(take(), n, what)
    return _float_bits(q, step, bigendian, exc, payload[pos:], what)
