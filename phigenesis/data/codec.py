"""Lossless PNG encodings of per-pixel maps, readable by any PNG decoder.

- depth: 16-bit grey PNG, ``depth_m = value / 256`` (KITTI's convention): 3.9 mm steps up to
  255.996 m; 0 means unknown (sky, no data, or beyond the encodable range).
- semantic: 8-bit grey PNG of unified class ids (255 = ignore).
- instance: 16-bit grey PNG of instance ids (0 = none).
- confidence: 8-bit grey PNG, ``confidence = value / 255`` (steps of 0.004 in [0, 1]).
- flow (3D velocity): 16-bit RGB PNG holding x, y, z as ``value = round(v_mps * 256) + 32768``:
  3.9 mm/s steps within +-128 m/s.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

DEPTH_SCALE = 256.0
DEPTH_MAX_M = 65535 / DEPTH_SCALE
CONFIDENCE_SCALE = 255.0
FLOW_SCALE = 256.0
FLOW_OFFSET = 32768


def _encode_png(image: np.ndarray, what: str) -> bytes:
    ok, buf = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, 3])
    if not ok:
        raise ValueError(f"could not encode {what} of shape {image.shape} as PNG")
    return buf.tobytes()


def _decode_png(data: bytes, dtype: type, channels: int, what: str) -> np.ndarray:
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ValueError(f"{what}: PNG bytes do not decode ({len(data)} bytes)")
    if img.dtype != dtype or (img.ndim == 3) != (channels == 3):
        raise ValueError(
            f"{what}: expected a {channels}-channel {np.dtype(dtype).name} PNG, got {img.dtype} {img.shape}"
        )
    return img


def encode_depth(depth_m: NDArray[np.floating]) -> bytes:
    """(H, W) metres (0 = unknown) to a 16-bit PNG; depths beyond 255.996 m become 0 (unknown)."""
    d = np.asarray(depth_m, dtype=np.float64)
    q = np.round(d * DEPTH_SCALE)
    q[~np.isfinite(d) | (d <= 0) | (q > 65535)] = 0
    return _encode_png(q.astype(np.uint16), "depth")


def decode_depth(data: bytes, out: NDArray[np.float32] | None = None) -> NDArray[np.float32]:
    """16-bit PNG to (H, W) float32 metres (0 = unknown), written into ``out`` if given."""
    q = _decode_png(data, np.uint16, 1, "depth")
    out = np.empty(q.shape, np.float32) if out is None else out
    return np.multiply(q, np.float32(1.0 / DEPTH_SCALE), out=out, dtype=np.float32)


def encode_confidence(confidence: NDArray[np.floating]) -> bytes:
    """(H, W) confidences in [0, 1] to an 8-bit PNG (``value / 255``); out-of-range values clip."""
    c = np.nan_to_num(np.asarray(confidence, dtype=np.float64), nan=0.0)
    return _encode_png(np.round(np.clip(c, 0.0, 1.0) * CONFIDENCE_SCALE).astype(np.uint8), "confidence map")


def decode_confidence(data: bytes, out: NDArray[np.float32] | None = None) -> NDArray[np.float32]:
    """8-bit PNG to (H, W) float32 confidences in [0, 1], written into ``out`` if given."""
    q = _decode_png(data, np.uint8, 1, "confidence map")
    out = np.empty(q.shape, np.float32) if out is None else out
    return np.multiply(q, np.float32(1.0 / CONFIDENCE_SCALE), out=out, dtype=np.float32)


def encode_semantic(semantic: NDArray[np.uint8]) -> bytes:
    return _encode_png(np.asarray(semantic, dtype=np.uint8), "semantic map")


def decode_semantic(data: bytes, out: NDArray[np.uint8] | None = None) -> NDArray[np.uint8]:
    q = _decode_png(data, np.uint8, 1, "semantic map")
    if out is None:
        return q
    np.copyto(out, q)
    return out


def encode_instance(instance: NDArray[np.uint16]) -> bytes:
    return _encode_png(np.asarray(instance, dtype=np.uint16), "instance map")


def decode_instance(data: bytes, out: NDArray[np.integer] | None = None) -> NDArray[np.integer]:
    """16-bit PNG to (H, W) uint16 ids, or written (widened) into ``out`` (e.g. int32)."""
    q = _decode_png(data, np.uint16, 1, "instance map")
    if out is None:
        return q
    np.copyto(out, q, casting="safe")
    return out


def encode_flow(flow_mps: NDArray[np.floating]) -> bytes:
    """(H, W, 3) m/s to a 16-bit RGB PNG (R = x, G = y, B = z), saturating at +-128 m/s."""
    f = np.asarray(flow_mps, dtype=np.float64)
    q = np.clip(np.round(f * FLOW_SCALE) + FLOW_OFFSET, 0, 65535).astype(np.uint16)
    return _encode_png(q[..., ::-1], "flow map")  # OpenCV writes BGR


def decode_flow(
    data: bytes, out: NDArray[np.float32] | None = None, channels_first: bool = False
) -> NDArray[np.float32]:
    """16-bit RGB PNG to float32 m/s, (H, W, 3) or (3, H, W) with ``channels_first``, written
    into ``out`` if given."""
    q = _decode_png(data, np.uint16, 3, "flow map")  # OpenCV order: B, G, R = z, y, x
    h, w = q.shape[:2]
    if out is None:
        out = np.empty((3, h, w) if channels_first else (h, w, 3), np.float32)
    planes = out if channels_first else np.moveaxis(out, -1, 0)
    for axis, channel in enumerate(cv2.split(q)[::-1]):
        np.subtract(channel, np.float32(FLOW_OFFSET), out=planes[axis], dtype=np.float32)
    out *= np.float32(1.0 / FLOW_SCALE)
    return out
