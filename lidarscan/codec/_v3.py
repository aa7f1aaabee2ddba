"""Format version 3 of :mod:`lidarscan.codec`: cross-channel prediction of a channel block.

Version 3 is version 2 (same container, same methods 0..6, read by the same code) plus one
method, XPREDICT (id 7): an integer block f (e.g. Ouster's ``reflectivity``) predicted from two
earlier blocks of the same (H, W) grid and count 1, a "signal" s (integer, e.g. ``signal`` /
``intensity``) and a range (float32 metres or integer units, e.g. ``range``). Reflectivity is a
calibrated function of signal and range (signal times a range-dependent gain, compressed above
about 100): this predicts it to within a count or two where the neighbour predictors of version
2 are off by the texture of the scene. The residual ``d = (f - P) mod 2**(8 * size)`` is an
unsigned grid coded exactly as a PREDICT2 payload (its own neighbour predictor, mask of zero
values, symbols and low bits).

Byte format of XPREDICT (every integer little-endian)::

    params  := PREDICT2 params of the residual grid d (u8 datatype, u8 bigendian, u32 H,
               u32 W, u32 count = 1, u8 predictor 0..3 (no REF), u8 rolled, u8 extra,
               u8 masked [, H x i32 row shifts when rolled])
               u32 signal_offset  u8 signal_datatype  u32 range_offset  u8 range_datatype
               i32 bin0  u16 n_gain  n_gain x u32 gain  u16 n_row  n_row x u16 row_gain
               u32 knee  i32 ubin0  u16 n_comp  n_comp x u16 comp
    payload := the PREDICT2 payload of d

The signal and range blocks are earlier blocks of the scan's data (offsets inside ``data``,
ending at or before this block's offset), in the scan's byte order, of the same H x W and count
1; signal_datatype an integer type, range_datatype FLOAT32 or an integer type (read as its
value). The prediction P of a pixel with signal s >= 0 (a signed signal below 0 counts as 0)
and range value r:

* no prediction (P = 0) when r is not finite or r <= 0;
* range bin ``rb = (bits(float32(r)) >> 18) - bin0`` (bits: the IEEE-754 word of the positive
  float32; 32 bins per octave), clamped to 0 .. n_gain - 1;
* linear value ``u = (s * gain[rb] * row_gain[y] + 2**30) >> 31`` for a pixel of row y
  (64-bit integers, wrapping, a negative result counts as 0; gain: 16 fractional bits,
  row_gain: 15; n_row = H);
* P = u when u < knee, else ``comp[clamp((bits(float32(u)) >> 20) - ubin0, 0, n_comp - 1)]``
  (8 bins per octave of u); P is finally clamped to the block type's unsigned range.

P and d are computed in the scan's (measurement) order; d is then rolled (row shifts, as
PREDICT2) before its neighbour prediction, and the decoder rolls it back before adding P.

Every step is integer or exact IEEE float32 conversion, so encoder and decoder agree bit for bit
on any machine. The tables are the encoder's choice (any tables decode losslessly); the encoder
uses the knee 80 and fits gain[b] as the median of f / s over the pixels of bin b with f below
the knee, then row_gain[y] as the median ratio of f to that prediction in row y (the beams
differ by a few per cent), then gain again with the row gains, and comp[k] as the median f over
the pixels of u bin k (all on every n-th column, about 16 384 pixels); it keeps the gains below
2**24 (no wrapping). It then estimates both codings of the block, XPREDICT and version 2 (the
residual bits of each one's best predictor on a band of up to 32 rows, scaled to the grid, plus
XPREDICT's tables): XPREDICT alone when its estimate is below 0.8 times version 2's, version 2
alone above 1.25 times, else both, the smaller kept; a large XPREDICT residual (at least
65 536 pixels) with at least a quarter zeros is coded with its zeros masked only. Version 3
buffers start with version byte 3; a version 3 decoder reads versions 1 and 2 unchanged.

Code layout: the functions here are the numpy reference (and test oracle) of the fit and of the
prediction; a :class:`lidarscan.codec._bits.ResidualCoder` may carry compiled ones (fields
``xfit`` and ``xpredict``: :mod:`lidarscan.codec._compiled_v3`, same values), which the block coding
below calls when present.
"""

from __future__ import annotations

import struct
from typing import Any

import numpy as np

from lidarscan.codec._bits import roll
from lidarscan.codec._format import _FLOAT32, _GRID2, _INT_CODES, _SIZES, XPREDICT, _shift_params
from lidarscan.codec._v2 import _choose_masked, _decode_int2, _encode_int2, _read_grid2
from lidarscan.errors import DecodeError
from lidarscan.scan import _find

__all__ = ["XParams", "decode_block", "encode_block", "fit", "fit_step", "pack_params", "predict",
           "residual", "source_names", "unpack_params"]

_SRC = struct.Struct("<IBIBiH")   # signal offset, signal datatype, range offset, range datatype,
                                  # bin0, n_gain
_COMP = struct.Struct("<IiH")     # knee, ubin0, n_comp
_FIT_PIXELS = 1 << 14  # the encoder fits its tables on about this many pixels
_KNEE = 80  # the encoder's knee: reflectivity is linear in the signal below about 100
#: the encoder's choice between XPREDICT and the version 2 coding of a block by an estimate of
#: their bytes (:func:`encode_block`): XPREDICT only below _SURE times the version 2 estimate,
#: version 2 only above _SKIP times it, both coded in between (the smaller wins)
_SURE, _SKIP = 0.8, 1.25
#: XPREDICT's residual grid of at least _LARGE pixels is coded with its zeros masked only
#: (not also unmasked, the smaller kept) from the fraction _MASKED_ONLY of zeros: real Ouster
#: frames have half or more, and the masked coding is 7-19 % smaller (the mask's frame is
#: a fixed cost only on small grids, which are cheap to code twice)
_MASKED_ONLY, _LARGE = 0.25, 1 << 16
#: (target channel prefix, signal channel names, range channel prefix): the encoder's search;
#: a suffix (e.g. "2" of a second return) is carried over to the sources.
TARGETS = (("reflectivity", ("signal", "intensity"), "range"),)


class XParams:
    """The prediction tables of one XPREDICT block (see the module docstring)."""

    def __init__(self, signal_offset: int, signal_datatype: int, range_offset: int,
                 range_datatype: int, bin0: int, gain: np.ndarray[Any, Any],
                 row_gain: np.ndarray[Any, Any], knee: int, ubin0: int,
                 comp: np.ndarray[Any, Any]) -> None:
        self.signal_offset, self.signal_datatype = int(signal_offset), int(signal_datatype)
        self.range_offset, self.range_datatype = int(range_offset), int(range_datatype)
        self.bin0, self.knee, self.ubin0 = int(bin0), int(knee), int(ubin0)
        self.gain = np.asarray(gain, np.uint32)
        self.row_gain = np.asarray(row_gain, np.uint16)
        self.comp = np.asarray(comp, np.uint16)


def pack_params(p: XParams) -> bytes:
    """The XPREDICT part of the params (after the PREDICT2 params)."""
    return (_SRC.pack(p.signal_offset, p.signal_datatype, p.range_offset, p.range_datatype,
                      p.bin0, p.gain.size) + p.gain.astype("<u4").tobytes()
            + struct.pack("<H", p.row_gain.size) + p.row_gain.astype("<u2").tobytes()
            + _COMP.pack(p.knee, p.ubin0, p.comp.size) + p.comp.astype("<u2").tobytes())


def unpack_params(buf: bytes, what: str) -> XParams:
    """Inverse of :func:`pack_params` (all of ``buf``); DecodeError when malformed."""
    if len(buf) < _SRC.size:
        raise DecodeError(f"{what} params", len(buf), f"at least {_SRC.size} XPREDICT bytes")
    so, sd, ro, rd, bin0, ng = _SRC.unpack_from(buf)
    pos = _SRC.size + 4 * ng
    if len(buf) < pos + 2:
        raise DecodeError(f"{what} params", len(buf), f"at least {pos + 2} bytes")
    gain = np.frombuffer(buf, "<u4", ng, _SRC.size).astype(np.uint32)
    (nr,) = struct.unpack_from("<H", buf, pos)
    pos += 2 + 2 * nr
    if len(buf) < pos + _COMP.size:
        raise DecodeError(f"{what} params", len(buf), f"at least {pos + _COMP.size} bytes")
    row_gain = np.frombuffer(buf, "<u2", nr, pos - 2 * nr).astype(np.uint16)
    knee, ubin0, nc = _COMP.unpack_from(buf, pos)
    end = pos + _COMP.size + 2 * nc
    if len(buf) != end:
        raise DecodeError(f"{what} params", len(buf), f"{end} bytes")
    comp = np.frombuffer(buf, "<u2", nc, pos + _COMP.size).astype(np.uint16)
    if sd not in _INT_CODES or (rd not in _INT_CODES and rd != _FLOAT32) or ng < 1 or nc < 1:
        raise DecodeError(f"{what} params", (sd, rd, ng, nc),
                          "integer signal, float32 or integer range, non-empty tables")
    return XParams(so, sd, ro, rd, bin0, gain, row_gain, knee, ubin0, comp)


def _range_bins(r: np.ndarray[Any, Any]) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]]:
    """(bin of every pixel: the float32 word >> 18, valid: finite and > 0) of a range grid
    (float32 metres or integer units, native byte order)."""
    rf = r.astype(np.float32, copy=False)
    with np.errstate(invalid="ignore"):
        valid = rf > 0
    valid &= np.isfinite(rf)
    bins = np.where(valid, rf, np.float32(1)).view(np.uint32) >> np.uint32(18)
    return bins.astype(np.int64), valid


def _u_bins(u: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    """8 bins per octave of the non-negative int64 values u (float32 word >> 20)."""
    return (u.astype(np.float32).view(np.uint32) >> np.uint32(20)).astype(np.int64)


def _linear(s: np.ndarray[Any, Any], r: np.ndarray[Any, Any], p: XParams
            ) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]]:
    """(u int64, valid) of native signal and range grids."""
    bins, valid = _range_bins(r)
    bins -= p.bin0
    np.clip(bins, 0, p.gain.size - 1, out=bins)
    u = p.gain.astype(np.int64)[bins]
    with np.errstate(over="ignore"):
        u *= p.row_gain.astype(np.int64)[:, None]
        u *= np.maximum(s, 0)  # int64 arithmetic, wrapping
    u += 1 << 30
    u >>= 31
    np.maximum(u, 0, out=u)
    u[~valid] = 0
    return u, valid


def predict(s: np.ndarray[Any, Any], r: np.ndarray[Any, Any], p: XParams,
            dtype: Any) -> np.ndarray[Any, Any]:
    """The prediction P (module docstring) of every pixel, in the unsigned ``dtype`` of the
    target block. s, r: native (H, W) grids of the signal and the range."""
    u, valid = _linear(s, r, p)
    hi = u >= p.knee
    hi &= valid
    if hi.any():
        kb = np.clip(_u_bins(u[hi]) - p.ubin0, 0, p.comp.size - 1)
        u[hi] = p.comp.astype(np.int64)[kb]
    np.minimum(u, np.iinfo(dtype).max, out=u)
    return u.astype(dtype)


def residual(x: np.ndarray[Any, Any], s: np.ndarray[Any, Any], r: np.ndarray[Any, Any],
             p: XParams, shifts: np.ndarray[Any, Any] | None, sign: int
             ) -> np.ndarray[Any, Any]:
    """sign 1 (encoding): the residual ``(x - P) mod 2**bits`` of the target grid x, rolled
    right by the row shifts (None: not rolled); sign -1 (decoding): the target grid ``(x
    rolled back + P) mod 2**bits`` of the rolled residual grid x. x: native unsigned (H, W)
    (returned likewise); s, r: the native signal and range grids."""
    h, w = s.shape
    if sign > 0:
        return roll((x - predict(s, r, p, x.dtype)).reshape(h, w, 1), shifts, 1).reshape(h, w)
    back = roll(x.reshape(h, w, 1), shifts, -1).reshape(h, w)
    return (back + predict(s, r, p, x.dtype)).astype(x.dtype)  # wrapping


def _medians(keys: np.ndarray[Any, Any], values: np.ndarray[Any, Any], n: int
             ) -> np.ndarray[Any, Any]:
    """Median of ``values`` per key 0..n-1 (the mean of the two middle values of an even
    count); a key without values takes the nearest key's median (the lower key on a tie); all
    1.0 when there are no values."""
    out = np.ones(n, np.float64)
    if not keys.size:
        return out
    order = np.lexsort((values, keys))  # by key, then value
    keys, values = keys[order], values[order]
    starts = np.flatnonzero(np.r_[True, keys[1:] != keys[:-1]])
    counts = np.diff(np.r_[starts, keys.size])
    have = keys[starts]
    out[have] = 0.5 * (values[starts + (counts - 1) // 2] + values[starts + counts // 2])
    at = np.clip(np.searchsorted(have, np.arange(n)), 0, have.size - 1)
    below = have[np.maximum(at - 1, 0)]
    above = have[at]
    pick = np.where(np.abs(below - np.arange(n)) <= np.abs(above - np.arange(n)), below, above)
    return out[pick]


def fit_step(size: int) -> int:
    """The encoder fits on every step-th column of a grid of ``size`` pixels (about
    16 384 pixels: the tables travel, a subsample is nearly as good)."""
    return max(1, size // _FIT_PIXELS)


def fit(f: np.ndarray[Any, Any], s: np.ndarray[Any, Any], r: np.ndarray[Any, Any],
        signal: tuple[int, int], rng: tuple[int, int], knee: int = _KNEE) -> XParams | None:
    """Tables of :func:`predict` fitted to a target grid f (native unsigned, (H, W)) from its
    signal s and range r (native (H, W) grids) on every :func:`fit_step`-th column;
    ``signal`` / ``rng``: (offset, datatype) of the sources. None when no pixel has a range
    and a positive signal."""
    step = fit_step(f.size)
    f, s, r = f[:, ::step], s[:, ::step], r[:, ::step]
    bins, valid = _range_bins(r)
    sig = s.astype(np.int64)
    use = valid & (sig > 0)
    if not use.any():
        return None
    bin0 = int(bins[use].min())
    n = int(bins[use].max()) - bin0 + 1
    rb = bins - bin0
    lin = use & (f.astype(np.int64) < knee)
    ratio = f[lin].astype(np.float64) / sig[lin]
    rows = np.broadcast_to(np.arange(f.shape[0])[:, None], f.shape)[lin]
    gain = _medians(rb[lin], ratio, n)
    row_gain = _medians(rows, ratio / np.maximum(gain[rb[lin]], 1e-9), f.shape[0])
    row_gain = np.clip(row_gain, 0.5, 1.99)
    gain = _medians(rb[lin], ratio / row_gain[rows], n)
    p = XParams(signal[0], signal[1], rng[0], rng[1], bin0,
                np.clip(np.rint(gain * 65536), 0, 2**24 - 1).astype(np.uint32),
                np.rint(row_gain * 32768).astype(np.uint16), knee, 0, np.zeros(1, np.uint16))
    u, _ = _linear(s, r, p)
    hi = use & (u >= knee)
    if hi.any():
        ub = _u_bins(u)
        p.ubin0 = int(ub[hi].min())
        comp = _medians(ub[hi] - p.ubin0, f[hi].astype(np.float64),
                        int(ub[hi].max()) - p.ubin0 + 1)
        p.comp = np.clip(np.rint(comp), 0, 65535).astype(np.uint16)
    return p


def source_names(target: str, names: list[str]) -> tuple[str, str] | None:
    """(signal channel, range channel) the encoder predicts ``target`` from, or None: the
    :data:`TARGETS` rule, the target's suffix carried over (reflectivity2 <- signal2,
    range2)."""
    for prefix, signals, rng in TARGETS:
        if target.startswith(prefix):
            suffix = target[len(prefix):]
            if rng + suffix not in names:
                return None
            for sig in signals:
                if sig + suffix in names:
                    return sig + suffix, rng + suffix
    return None


# ------------------------------------------------------------------ the block coding

def encode_block(block: Any, desc: Any, scan: Any, level: int,
                 shifts: np.ndarray[Any, Any] | None, coder: Any,
                 u: np.ndarray[Any, Any] | None = None, ref: np.ndarray[Any, Any] | None = None
                 ) -> tuple[bytes, bytes, bool] | None:
    """(params, payload, sure) of the XPREDICT coding of an integer channel block, or None
    when the block has no sources (:func:`source_names`, earlier blocks of the same grid,
    count 1) or no pixel to fit, or when an estimate says that its version 2 coding is
    clearly smaller. ``u``, ``ref``: the block's rolled unsigned (H, W, 1) grid and the
    reference grid of its version 2 coding (None: no estimate, XPREDICT is coded); sure: the
    estimate says that XPREDICT is clearly smaller (the caller then skips the version 2
    coding). ``coder``: a :class:`lidarscan.codec._bits.ResidualCoder` (its ``xfit`` and
    ``xpredict`` when present, else this module's reference)."""
    from lidarscan.scan import channel, channel_names
    found = source_names(str(desc.name), channel_names(scan))
    if found is None or int(desc.count) != 1:
        return None
    height, width = int(scan.height), int(scan.width)
    sources = [_find(scan, name) for name in found]
    for src, types in zip(sources, (_INT_CODES.keys(), (*_INT_CODES, _FLOAT32)), strict=True):
        end = int(src.offset) + height * width * _SIZES.get(int(src.datatype), 0)
        if int(src.count) != 1 or end > int(desc.offset) or int(src.datatype) not in types:
            return None
    big = bool(scan.is_bigendian)
    size = _SIZES[int(desc.datatype)]
    f = np.frombuffer(block, np.dtype((">" if big else "<") + f"u{size}")).reshape(
        height, width).astype(f"u{size}")
    s = np.asarray(channel(scan, found[0], native=True)).reshape(height, width)
    r = np.asarray(channel(scan, found[1], native=True)).reshape(height, width)
    p = (coder.xfit or fit)(f, s, r, (int(sources[0].offset), int(sources[0].datatype)),
                            (int(sources[1].offset), int(sources[1].datatype)), _KNEE)
    if p is None:
        return None
    d = (coder.xpredict or residual)(f, s, r, p, shifts, 1).reshape(height, width, 1)
    tables = _shift_params(shifts) + pack_params(p)
    if _GRID2.size + len(tables) >= 2**16:  # the container's u16 params length
        return None
    sure = False
    if u is not None:  # estimates of both codings' bytes: the residual bits of their best
        rows = min(height, 32)  # predictor on a band of rows, scaled, plus XPREDICT's tables
        ours = _choose_masked(d, None, None, coder)[1] * height / rows / 8 + len(tables)
        theirs = _choose_masked(u, None, ref, coder)[1] * height / rows / 8
        if ours > _SKIP * theirs:
            return None
        sure = ours < _SURE * theirs
    predictor, extra, masked, payload = _encode_int2(
        d, level, None, coder, _MASKED_ONLY if d.size >= _LARGE else 1.0)
    params = _GRID2.pack(int(desc.datatype), big, height, width, 1, predictor,
                         shifts is not None, extra, masked) + tables
    return params, payload, sure


def _source(data: np.ndarray[Any, Any], offset: int, datatype: int, shape: tuple[int, int],
            big: bool, before: int, what: str) -> np.ndarray[Any, Any]:
    """A native source grid read from the decoded ``data`` (ending at or before ``before``)."""
    size = _SIZES[datatype]
    n = shape[0] * shape[1] * size
    if offset + n > before:
        raise DecodeError(f"{what} source offset", offset,
                          f"a block of {n} bytes decoded before offset {before}")
    code = "f4" if datatype == _FLOAT32 else _INT_CODES[datatype]
    raw = data[offset:offset + n].view((">" if big else "<") + code)  # decoded: not rewritten
    return raw.astype(code, copy=False).reshape(shape)


def decode_block(what: str, offset: int, length: int, params: bytes, payload: bytes,
                 data: np.ndarray[Any, Any], coder: Any) -> np.ndarray[Any, Any]:
    """The bytes (uint8 array) of an XPREDICT segment; ``data``: the scan's data decoded up to
    ``offset``; ``coder`` as for :func:`encode_block`."""
    datatype, big, (h, w, _), predictor, extra, masked, shifts, end = _read_grid2(
        what, XPREDICT, length, params)
    p = unpack_params(params[end:], what)
    if p.row_gain.size != h:
        raise DecodeError(f"{what} params", p.row_gain.size, f"{h} row gains (one per row)")
    s = _source(data, p.signal_offset, p.signal_datatype, (h, w), big, offset, what)
    r = _source(data, p.range_offset, p.range_datatype, (h, w), big, offset, what)
    size = _SIZES[datatype]
    d = _decode_int2(payload, (h, w, 1), size, predictor, extra, masked, what, None, coder)
    f = (coder.xpredict or residual)(d.reshape(h, w), s, r, p, shifts, -1)
    return f.astype(f.dtype.newbyteorder(">" if big else "<")).reshape(-1).view(np.uint8)
