"""PointField datatype ids <-> numpy dtypes, with explicit byte order.

The ids are those of ``sensor_msgs/PointField`` (and ``lidarscan_msgs/LidarChannel``):
INT8=1, UINT8=2, INT16=3, UINT16=4, INT32=5, UINT32=6, FLOAT32=7, FLOAT64=8.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from lidarscan.errors import UnknownDatatypeError

__all__ = [
    "INT8",
    "UINT8",
    "INT16",
    "UINT16",
    "INT32",
    "UINT32",
    "FLOAT32",
    "FLOAT64",
    "DATATYPE_NAMES",
    "DTYPES",
    "dtype_of",
    "datatype_of",
    "itemsize_of",
]

INT8, UINT8, INT16, UINT16, INT32, UINT32, FLOAT32, FLOAT64 = 1, 2, 3, 4, 5, 6, 7, 8

_CODES = {INT8: "i1", UINT8: "u1", INT16: "i2", UINT16: "u2",
          INT32: "i4", UINT32: "u4", FLOAT32: "f4", FLOAT64: "f8"}
DATATYPE_NAMES = {INT8: "INT8", UINT8: "UINT8", INT16: "INT16", UINT16: "UINT16",
                  INT32: "INT32", UINT32: "UINT32", FLOAT32: "FLOAT32", FLOAT64: "FLOAT64"}
_IDS = {code: ident for ident, code in _CODES.items()}
#: (datatype id, is_bigendian) -> numpy dtype: the table :func:`dtype_of` reads (a lookup for
#: hot paths; :func:`dtype_of` is the checked form that names a bad id)
DTYPES: dict[tuple[int, bool], np.dtype[Any]] = {
    (ident, big): np.dtype((">" if big else "<") + code)
    for ident, code in _CODES.items() for big in (False, True)}


def dtype_of(datatype: int, is_bigendian: bool = False, *,
             field: str = "datatype") -> np.dtype[Any]:
    """numpy dtype for a PointField datatype id and byte order.

    Raises:
        UnknownDatatypeError: ``datatype`` is not 1..8.
    """
    try:
        return DTYPES[int(datatype), bool(is_bigendian)]
    except (KeyError, TypeError, ValueError):
        raise UnknownDatatypeError(field, datatype, "a PointField datatype id 1..8 "
                                   "(INT8, UINT8, INT16, UINT16, INT32, UINT32, FLOAT32, FLOAT64)"
                                   ) from None


def itemsize_of(datatype: int, *, field: str = "datatype") -> int:
    """Bytes per element of a datatype id."""
    return dtype_of(datatype, field=field).itemsize


def datatype_of(dtype: Any, *, field: str = "dtype") -> int:
    """PointField datatype id of a numpy dtype (byte order ignored).

    Raises:
        UnknownDatatypeError: the dtype has no PointField id (bool, int64, float16, ...).
    """
    dt = np.dtype(dtype)
    code = dt.kind + str(dt.itemsize)
    if code not in _IDS:
        raise UnknownDatatypeError(field, str(dt), "one of int8, uint8, int16, uint16, int32, "
                                   "uint32, float32, float64 (PointField has no other types)")
    return _IDS[code]
