"""Lossless encodings of per-pixel maps: a filtered, zstd-compressed array behind a small header.

What a map's integers mean (the quantisation; unchanged since the PNG encoding):

- depth: 16-bit, ``depth_m = value / 256`` (KITTI's convention): 3.9 mm steps up to 255.996 m; 0 means
  unknown (sky, no data, or beyond the encodable range).
- semantic: 8-bit unified class ids (255 = ignore); also the 8-bit code maps (origins, sources).
- instance: 16-bit instance ids (0 = none).
- confidence: 8-bit, ``confidence = value / 255`` (steps of 0.004 in [0, 1]).
- flow (3D velocity): 16-bit x, y, z as ``value = round(v_mps * 256) + 32768``: 3.9 mm/s steps within
  +-128 m/s.

How they are stored (``docs/design/cache.md``, "Maps as zstd-compressed arrays", says why): a
:data:`HEADER_SIZE`-byte header (:data:`MAGIC`, format version, bytes per value, channels, filter bits,
height, width, payload length; little-endian) then one zstd frame of the filtered array: rows
delta-coded (each minus the row above) where that compresses smaller, and 16-bit values split into a
plane of low bytes then a plane of high bytes (the high bytes of depths and ids are long runs). Caches
written before schema version 7 hold the same integers as grey (flow: RGB) PNGs; decoding dispatches on
the blob's first bytes (PNG signature or :data:`MAGIC`), so both read.

A decoder checks the declared height and width against the expected shape (the ``out`` array's, or
``shape``) and against :data:`MAX_PIXELS` before it allocates anything, so a damaged or hostile header
cannot make it allocate gigabytes; every problem raises :class:`MapDecodeError` naming the map and what
is wrong.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Sequence
from typing import Literal

import cv2
import numpy as np
import pyarrow as pa
from numpy.typing import NDArray

DEPTH_SCALE = 256.0
DEPTH_MAX_M = 65535 / DEPTH_SCALE
CONFIDENCE_SCALE = 255.0
FLOW_SCALE = 256.0
FLOW_OFFSET = 32768

#: First bytes of a map blob; the high first byte (like PNG's) never starts text or a PNG.
MAGIC = b"\x8bPHM"
#: Version of the blob layout below the magic.
FORMAT_VERSION = 1
_HEADER = struct.Struct("<4sBBBBIII")  # magic, version, itemsize, channels, filter, height, width, payload
HEADER_SIZE = _HEADER.size
#: Filter bits of the header (applied before zstd, undone after): 16-bit values split into byte
#: planes; rows delta-coded (each row minus the one above, wrapping).
FILTER_NONE, FILTER_SHUFFLE, FILTER_DELTA = 0, 1, 2
#: zstd level of new blobs (BENCHMARKS.md "Map codec": level 1 against 3 and PNG).
ZSTD_LEVEL = 1
#: The largest map a decoder accepts without an expected shape: 8192 x 8192 pixels (64 Mi).
MAX_PIXELS = 1 << 26
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_END = b"\x00\x00\x00\x00IEND\xaeB`\x82"

_ZSTD_ENCODERS = {ZSTD_LEVEL: pa.Codec("zstd", compression_level=ZSTD_LEVEL)}
_ZSTD_DECODER = pa.Codec("zstd")

Blob = bytes | bytearray | memoryview | NDArray[np.uint8]
Layout = Literal["png", "zstd"]


class MapDecodeError(ValueError):
    """A stored map's bytes do not decode to the map expected; the message names the map and why."""


def _blob_bytes(data: Blob) -> memoryview:
    view = memoryview(data)
    return view.cast("B") if view.format != "B" or view.ndim != 1 else view


def _check_shape(what: str, h: int, w: int, shape: Sequence[int] | None, source: str) -> None:
    """Refuses a declared size before anything is allocated for it."""
    if shape is not None and (h, w) != tuple(shape[:2]):
        raise MapDecodeError(f"{what}: {source} declares {w}x{h} pixels, expected {shape[1]}x{shape[0]}")
    if h < 1 or w < 1 or h * w > MAX_PIXELS:
        raise MapDecodeError(f"{what}: {source} declares {w}x{h} pixels (at most {MAX_PIXELS} accepted)")


def _delta_rows(a: np.ndarray) -> np.ndarray:
    """Each row minus the row above it (wrapping integers), the first row kept."""
    d = a.copy()
    np.subtract(a[1:], a[:-1], out=d[1:])
    return d


def _undelta_rows(x: np.ndarray) -> None:
    """Inverts :func:`_delta_rows` in place on an (H, M) array: a running sum down the rows.

    Blocked (blocks of about sqrt(H) rows: a running sum inside every block at once, then each
    block's last row carried into the next), so numpy makes about 2 sqrt(H) calls instead of H."""
    h = x.shape[0]
    block = max(2, math.isqrt(h))
    n = h // block
    if n:
        blocks = x[: n * block].reshape(n, block, -1)
        for j in range(1, block):
            np.add(blocks[:, j], blocks[:, j - 1], out=blocks[:, j])
        for k in range(1, n):
            np.add(blocks[k], blocks[k - 1, -1], out=blocks[k])
    for i in range(max(1, n * block), h):
        np.add(x[i], x[i - 1], out=x[i])


#: Filter choice on a sample: maps of at least this many rows choose delta coding or not from bands
#: of :data:`SAMPLE_BAND` rows, one every :data:`SAMPLE_STRIDE` rows (an eighth of the map), each
#: compressed both ways; smaller maps are compressed both ways whole.
SAMPLE_MIN_ROWS = 256
SAMPLE_BAND = 16
SAMPLE_STRIDE = 128


def encode_array(image: NDArray[np.integer], what: str = "map", level: int = ZSTD_LEVEL) -> bytes:
    """An (H, W) or (H, W, C) uint8 / uint16 array to a map blob (header + zstd frame at ``level``),
    losslessly.

    16-bit values are split into a plane of low bytes and a plane of high bytes, and the rows are
    delta-coded (each minus the row above) where that compresses smaller (delta wins on dense
    depth and on labels, loses on sparse maps, where it doubles the non-zero values, and on
    confidences). Which is smaller is measured on a sample of the rows (:func:`_delta_wins`), so
    the map is compressed once; the header records the filters."""
    a = np.asarray(image)
    if a.dtype not in (np.uint8, np.uint16) or a.ndim not in (2, 3) or 0 in a.shape:
        raise ValueError(
            f"could not encode {what}: expected a non-empty (H, W[, C]) uint8/uint16 array, "
            f"got {a.dtype} {a.shape}"
        )
    h, w = a.shape[:2]
    channels = 1 if a.ndim == 2 else a.shape[2]
    if not 1 <= channels <= 4:
        raise ValueError(f"could not encode {what}: {channels} channels (1 to 4 accepted)")
    rows = np.ascontiguousarray(a.reshape(h, w * channels), dtype=a.dtype.newbyteorder("<"))
    if level not in _ZSTD_ENCODERS:
        _ZSTD_ENCODERS[level] = pa.Codec("zstd", compression_level=level)
    zstd = _ZSTD_ENCODERS[level]
    if h >= SAMPLE_MIN_ROWS:
        delta = _delta_wins(rows, zstd)
        payload, filt = _compressed(_delta_rows(rows) if delta else rows, zstd, FILTER_DELTA if delta else 0)
    else:
        payload, filt = _compressed(rows, zstd, FILTER_NONE)
        if h > 1:
            coded = _compressed(_delta_rows(rows), zstd, FILTER_DELTA)
            if len(coded[0]) < len(payload):
                payload, filt = coded
    return _HEADER.pack(MAGIC, FORMAT_VERSION, a.dtype.itemsize, channels, filt, h, w, len(payload)) + payload


def encode_array_reference(image: NDArray[np.integer], what: str = "map", level: int = ZSTD_LEVEL) -> bytes:
    """:func:`encode_array` choosing the filter by compressing the whole map both ways (twice the
    work): the reference its sampled choice is measured against (tests/test_codec.py)."""
    a = np.asarray(image)
    h, w = a.shape[:2]
    channels = 1 if a.ndim == 2 else a.shape[2]
    rows = np.ascontiguousarray(a.reshape(h, w * channels), dtype=a.dtype.newbyteorder("<"))
    zstd = pa.Codec("zstd", compression_level=level)
    payload, filt = _compressed(rows, zstd, FILTER_NONE)
    if h > 1:
        coded = _compressed(_delta_rows(rows), zstd, FILTER_DELTA)
        if len(coded[0]) < len(payload):
            payload, filt = coded
    return _HEADER.pack(MAGIC, FORMAT_VERSION, a.dtype.itemsize, channels, filt, h, w, len(payload)) + payload


def _compressed(x: np.ndarray, zstd: pa.Codec, filt: int) -> tuple[bytes, int]:
    """The zstd frame of the (H, M) rows ``x`` (16-bit values split into byte planes first) and the
    filter bits with the shuffle bit added where it applies."""
    if x.dtype.itemsize == 2:
        h, m = x.shape
        planes = np.empty((2, h, m), np.uint8)
        cv2.split(x.view(np.uint8).reshape(h, m, 2), [planes[0], planes[1]])
        x, filt = planes, filt | FILTER_SHUFFLE
    return zstd.compress(x, asbytes=True), filt


def _delta_wins(rows: np.ndarray, zstd: pa.Codec) -> bool:
    """Whether delta coding compresses the (H, M) ``rows`` smaller, judged on bands of
    :data:`SAMPLE_BAND` rows every :data:`SAMPLE_STRIDE` rows (each band delta-coded within
    itself, so its first row is kept as in the plain sample and the two differ only in the rest)."""
    h = rows.shape[0]
    starts = np.arange(0, h - SAMPLE_BAND + 1, SAMPLE_STRIDE)
    sample = rows[(starts[:, None] + np.arange(SAMPLE_BAND)).reshape(-1)]
    bands = sample.reshape(len(starts), SAMPLE_BAND, -1)
    coded = bands.copy()
    np.subtract(bands[:, 1:], bands[:, :-1], out=coded[:, 1:])
    plain = len(_compressed(sample, zstd, FILTER_NONE)[0])
    return len(_compressed(coded.reshape(sample.shape), zstd, FILTER_NONE)[0]) < plain


def _decode_zstd(
    view: memoryview, dtype: type, channels: int, what: str, shape: Sequence[int] | None
) -> np.ndarray:
    if len(view) < HEADER_SIZE:
        raise MapDecodeError(
            f"{what}: {len(view)} bytes, shorter than the {HEADER_SIZE}-byte map header (cut short)"
        )
    _, version, itemsize, got_channels, filt, h, w, length = _HEADER.unpack_from(view)
    if version != FORMAT_VERSION:
        raise MapDecodeError(
            f"{what}: map format version {version}, this toolkit reads version {FORMAT_VERSION}"
        )
    want = np.dtype(dtype)
    if itemsize != want.itemsize or got_channels != channels:
        raise MapDecodeError(
            f"{what}: expected a {channels}-channel {want.name} map, got a {got_channels}-channel "
            f"{itemsize * 8}-bit map"
        )
    if filt & ~(FILTER_SHUFFLE | FILTER_DELTA) or bool(filt & FILTER_SHUFFLE) != (itemsize == 2):
        raise MapDecodeError(
            f"{what}: filter code {filt} is not one a {itemsize * 8}-bit map is written with"
        )
    _check_shape(what, h, w, shape, "the map header")
    if len(view) - HEADER_SIZE != length:
        cut = "cut short" if len(view) - HEADER_SIZE < length else "trailing bytes"
        raise MapDecodeError(
            f"{what}: the header declares a {length}-byte payload, {len(view) - HEADER_SIZE} bytes "
            f"follow ({cut})"
        )
    size = h * w * channels * itemsize
    try:
        raw = _ZSTD_DECODER.decompress(view[HEADER_SIZE:], decompressed_size=size)
    except (OSError, pa.ArrowException) as e:
        raise MapDecodeError(
            f"{what}: zstd payload of {length} bytes does not decode to {size} bytes ({e})"
        ) from None
    flat = np.frombuffer(raw, np.uint8)
    if flat.size != size:  # zstd checks the frame's declared size; a guard against a frame without one
        raise MapDecodeError(f"{what}: zstd payload decodes to {flat.size} bytes, the header declares {size}")
    if itemsize == 2:
        planes = flat.reshape(2, h, w * channels)
        rows = cv2.merge([planes[0], planes[1]]).reshape(h, w * channels * 2).view("<u2")
    elif filt & FILTER_DELTA:
        rows = flat.reshape(h, w * channels).copy()
    else:
        rows = flat.reshape(h, w * channels)
    if filt & FILTER_DELTA:
        _undelta_rows(rows)
    return rows.reshape((h, w) if channels == 1 else (h, w, channels)).astype(dtype, copy=False)


def _png_size(view: memoryview) -> tuple[int, int] | None:
    """(height, width) from a PNG's IHDR chunk, or None where there is none."""
    if len(view) < 33 or bytes(view[12:16]) != b"IHDR":
        return None
    w, h = struct.unpack_from(">II", view, 16)
    return h, w


def _decode_png(
    view: memoryview, dtype: type, channels: int, what: str, shape: Sequence[int] | None
) -> np.ndarray:
    size = _png_size(view)
    if size is None:
        raise MapDecodeError(f"{what}: PNG of {len(view)} bytes without an IHDR chunk")
    _check_shape(what, *size, shape, "the PNG header")
    if bytes(view[-len(_PNG_END) :]) != _PNG_END:
        raise MapDecodeError(f"{what}: PNG of {len(view)} bytes ends without the IEND chunk (cut short)")
    img = cv2.imdecode(np.frombuffer(view, np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise MapDecodeError(f"{what}: PNG bytes do not decode ({len(view)} bytes)")
    if img.dtype != dtype or (img.ndim == 3) != (channels == 3):
        raise MapDecodeError(
            f"{what}: expected a {channels}-channel {np.dtype(dtype).name} map, "
            f"got a PNG of {img.dtype} {img.shape}"
        )
    if channels == 3:
        img = img[..., ::-1]  # OpenCV reads BGR; the stored channels are R, G, B
    return img


def layout_of(data: Blob) -> Layout:
    """Which encoding a stored map's bytes are in, from their first bytes; raises :class:`MapDecodeError`
    for bytes that are neither."""
    head = bytes(_blob_bytes(data)[:8])
    if head.startswith(MAGIC):
        return "zstd"
    if head == PNG_SIGNATURE:
        return "png"
    raise MapDecodeError(
        f"map bytes start with {head!r}: neither a PNG nor a phigenesis map blob ({MAGIC!r})"
    )


def decode_array(
    data: Blob, dtype: type, channels: int = 1, what: str = "map", shape: Sequence[int] | None = None
) -> np.ndarray:
    """A stored map's integers as an (H, W) or (H, W, C) array of ``dtype`` (channels in stored order).

    Reads map blobs and the PNGs of older caches alike. ``shape`` ((H, W), optional) is the size the
    map must have (the camera's calibration); it is checked before anything is allocated. The result
    may be read-only (a view of the decompressed buffer).
    """
    view = _blob_bytes(data)
    if layout_of(view) == "zstd":
        return _decode_zstd(view, dtype, channels, what, shape)
    return _decode_png(view, dtype, channels, what, shape)


def encode_png(image: NDArray[np.integer], what: str = "map") -> bytes:
    """The encoding of caches before schema version 7 (grey PNG, flow RGB, zlib level 3): kept as the
    reference old caches are checked against and for tools that want PNG files."""
    a = np.asarray(image)
    a = a[..., ::-1] if a.ndim == 3 else a  # OpenCV writes BGR
    ok, buf = cv2.imencode(".png", a, [cv2.IMWRITE_PNG_COMPRESSION, 3])
    if not ok:
        raise ValueError(f"could not encode {what} of shape {image.shape} as PNG")
    return buf.tobytes()


def _shape_of(out: np.ndarray | None, shape: Sequence[int] | None) -> Sequence[int] | None:
    return out.shape[:2] if out is not None and out.ndim == 2 else shape


def quantise_depth(depth_m: NDArray[np.floating]) -> NDArray[np.uint16]:
    """(H, W) metres to the stored 16-bit values; depths beyond 255.996 m, <= 0 or non-finite become 0.

    float32 depths are scaled and rounded in float32, exactly (times 256 is exact, so is rounding),
    without a float64 copy; other inputs in float64."""
    d = np.asarray(depth_m)
    if d.dtype != np.float32:
        d = d.astype(np.float64)
    q = d * d.dtype.type(DEPTH_SCALE)
    np.round(q, out=q)
    # NaN compares false, so NaN, infinities, depths <= 0 and beyond the range all become 0.
    return np.where((q <= 65535) & (d > 0), q, 0).astype(np.uint16)


def encode_depth(depth_m: NDArray[np.floating]) -> bytes:
    """(H, W) metres (0 = unknown) to a 16-bit map blob; depths beyond 255.996 m become 0 (unknown)."""
    return encode_array(quantise_depth(depth_m), "depth")


def decode_depth(
    data: Blob, out: NDArray[np.float32] | None = None, shape: Sequence[int] | None = None
) -> NDArray[np.float32]:
    """A stored depth map to (H, W) float32 metres (0 = unknown), written into ``out`` if given (its
    shape, else ``shape``, is the size the map must have)."""
    q = decode_array(data, np.uint16, 1, "depth", _shape_of(out, shape))
    out = np.empty(q.shape, np.float32) if out is None else out
    return np.multiply(q, np.float32(1.0 / DEPTH_SCALE), out=out, dtype=np.float32)


def quantise_confidence(confidence: NDArray[np.floating]) -> NDArray[np.uint8]:
    """(H, W) confidences in [0, 1] to the stored 8-bit values (``value / 255``); NaN becomes 0, the
    rest clips to [0, 1]. Scaled in float64 (exact for float32 inputs) so that ties round as they
    always have (half to even)."""
    c = np.asarray(confidence)
    if c.dtype not in (np.float32, np.float64):
        c = c.astype(np.float64)
    clipped = np.fmax(c, c.dtype.type(0.0))  # NaN -> 0
    np.minimum(clipped, c.dtype.type(1.0), out=clipped)
    scaled = np.multiply(clipped, CONFIDENCE_SCALE, dtype=np.float64)
    np.rint(scaled, out=scaled)
    return scaled.astype(np.uint8)


def encode_confidence(confidence: NDArray[np.floating]) -> bytes:
    """(H, W) confidences in [0, 1] to an 8-bit map blob (``value / 255``); out-of-range values clip."""
    return encode_array(quantise_confidence(confidence), "confidence map")


def decode_confidence(
    data: Blob, out: NDArray[np.float32] | None = None, shape: Sequence[int] | None = None
) -> NDArray[np.float32]:
    """A stored confidence map to (H, W) float32 confidences in [0, 1], written into ``out`` if given."""
    q = decode_array(data, np.uint8, 1, "confidence map", _shape_of(out, shape))
    out = np.empty(q.shape, np.float32) if out is None else out
    return np.multiply(q, np.float32(1.0 / CONFIDENCE_SCALE), out=out, dtype=np.float32)


def encode_semantic(semantic: NDArray[np.uint8]) -> bytes:
    """(H, W) uint8 class ids (or any 8-bit code map) to a map blob."""
    return encode_array(np.asarray(semantic, dtype=np.uint8), "semantic map")


def decode_semantic(
    data: Blob, out: NDArray[np.uint8] | None = None, shape: Sequence[int] | None = None
) -> NDArray[np.uint8]:
    """A stored 8-bit map to a writable (H, W) uint8 array, or written into ``out``."""
    q = decode_array(data, np.uint8, 1, "semantic map", _shape_of(out, shape))
    if out is None:
        return q if q.flags.writeable else q.copy()
    np.copyto(out, q)
    return out


def encode_instance(instance: NDArray[np.uint16]) -> bytes:
    """(H, W) uint16 instance ids to a map blob."""
    return encode_array(np.asarray(instance, dtype=np.uint16), "instance map")


def decode_instance(
    data: Blob, out: NDArray[np.integer] | None = None, shape: Sequence[int] | None = None
) -> NDArray[np.integer]:
    """A stored 16-bit id map to (H, W) uint16 ids, or written (widened) into ``out`` (e.g. int32)."""
    q = decode_array(data, np.uint16, 1, "instance map", _shape_of(out, shape))
    if out is None:
        return q
    np.copyto(out, q, casting="safe")
    return out


def quantise_flow(flow_mps: NDArray[np.floating]) -> NDArray[np.uint16]:
    """(H, W, 3) m/s to the stored 16-bit values ``round(v * 256) + 32768``, saturating at +-128 m/s."""
    f = np.asarray(flow_mps, dtype=np.float64)
    return np.clip(np.round(f * FLOW_SCALE) + FLOW_OFFSET, 0, 65535).astype(np.uint16)


def encode_flow(flow_mps: NDArray[np.floating]) -> bytes:
    """(H, W, 3) m/s to a 16-bit 3-channel map blob (x, y, z), saturating at +-128 m/s."""
    return encode_array(quantise_flow(flow_mps), "flow map")


def decode_flow(
    data: Blob,
    out: NDArray[np.float32] | None = None,
    channels_first: bool = False,
    shape: Sequence[int] | None = None,
) -> NDArray[np.float32]:
    """A stored flow map to float32 m/s, (H, W, 3) or (3, H, W) with ``channels_first``, written
    into ``out`` if given."""
    if out is not None:
        shape = out.shape[1:] if channels_first else out.shape[:2]
    q = decode_array(data, np.uint16, 3, "flow map", shape)  # x, y, z
    h, w = q.shape[:2]
    if out is None:
        out = np.empty((3, h, w) if channels_first else (h, w, 3), np.float32)
    planes = out if channels_first else np.moveaxis(out, -1, 0)
    for axis in range(3):
        np.subtract(q[..., axis], np.float32(FLOW_OFFSET), out=planes[axis], dtype=np.float32)
    out *= np.float32(1.0 / FLOW_SCALE)
    return out
