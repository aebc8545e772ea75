"""Map codec: bytes and single-thread encode / decode time of the cache's per-pixel maps, by codec.

The maps are read back from a prep cache (``--cache DIR``; otherwise a one-frame Waymo-v1 scene at
1920 x 1280 / 886 is synthesised and prepped into a temporary folder, ~3 min), as the integers the
cache stores (16-bit depths and ids, 8-bit confidences and codes). Each candidate codec encodes and
decodes every map of a kind (all cameras of the first ``--frames`` frames); a candidate that does not
give the exact integers back fails the run. Times are medians over ``--repeats`` runs, on one thread
(``cv2.setNumThreads(1)``; zstd and libpng are single-threaded anyway). Arrow IPC buffer compression
(zstd / lz4 of each column buffer) is what the ``zstd raw`` / ``lz4`` rows measure: the same
compressor over the same bytes.

Usage: ``.venv/bin/python benchmarks/codec.py [--cache DIR] [--frames 2] [--repeats 5] [--update]``
(``--update`` writes the section "Map codec" of BENCHMARKS.md).
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pyarrow as pa

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _report import Report, add_update_flag

from phigenesis.data import codec
from phigenesis.data.shards import CacheReader

#: Stored map columns: (column, kind, dtype, channels).
COLUMNS: tuple[tuple[str, str, type, int], ...] = (
    ("depth_sparse_png", "sparse depth (16-bit)", np.uint16, 1),
    ("depth_dense_png", "dense depth (16-bit)", np.uint16, 1),
    ("truth_depth_png", "truth depth (16-bit)", np.uint16, 1),
    ("depth_sparse_confidence_png", "confidence (8-bit)", np.uint8, 1),
    ("depth_dense_confidence_png", "confidence (8-bit)", np.uint8, 1),
    ("pseudo_semantic_confidence_png", "confidence (8-bit)", np.uint8, 1),
    ("truth_semantic_png", "labels and codes (8-bit)", np.uint8, 1),
    ("label_semantic_png", "labels and codes (8-bit)", np.uint8, 1),
    ("pseudo_semantic_png", "labels and codes (8-bit)", np.uint8, 1),
    ("pseudo_semantic_source_png", "labels and codes (8-bit)", np.uint8, 1),
    ("depth_sparse_origin_png", "labels and codes (8-bit)", np.uint8, 1),
    ("depth_dense_origin_png", "labels and codes (8-bit)", np.uint8, 1),
    ("truth_instance_png", "instance ids (16-bit)", np.uint16, 1),
    ("label_instance_png", "instance ids (16-bit)", np.uint16, 1),
    ("truth_flow_png", "flow (16-bit x 3)", np.uint16, 3),
)


@dataclass(frozen=True)
class Candidate:
    """A lossless codec: ``encode(array) -> bytes``, ``decode(bytes, like) -> array``; ``for_8bit`` /
    ``for_16bit`` say which maps it applies to."""

    name: str
    encode: Callable[[np.ndarray], bytes]
    decode: Callable[[bytes, np.ndarray], np.ndarray]
    for_8bit: bool = True
    for_16bit: bool = True


def _cv2_encode(ext: str, params: list[int]) -> Callable[[np.ndarray], bytes]:
    def encode(a: np.ndarray) -> bytes:
        ok, buf = cv2.imencode(ext, a, params)
        if not ok:
            raise RuntimeError(f"cv2 could not encode {ext} {params}")
        return buf.tobytes()

    return encode


def _cv2_decode(data: bytes, like: np.ndarray) -> np.ndarray:
    return cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)


def _webp_decode(data: bytes, like: np.ndarray) -> np.ndarray:
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    return img if like.ndim == 3 else img[..., 0].copy()


def _shuffle(a: np.ndarray) -> np.ndarray:
    """Byte planes of a 16-bit array (low bytes, then high bytes), split by OpenCV as the codec does."""
    if a.dtype.itemsize == 1:
        return np.ascontiguousarray(a)
    planes = np.empty((2, a.shape[0], a.size // a.shape[0]), np.uint8)
    cv2.split(np.ascontiguousarray(a).view(np.uint8).reshape(*planes.shape[1:], 2), [planes[0], planes[1]])
    return planes


def _unshuffle(raw: pa.Buffer | bytes, like: np.ndarray) -> np.ndarray:
    flat = np.frombuffer(raw, np.uint8)
    if like.dtype.itemsize == 1:
        return flat.reshape(like.shape)
    planes = flat.reshape(2, like.shape[0], -1)
    return cv2.merge([planes[0], planes[1]]).view(like.dtype).reshape(like.shape)


def _compressed(name: str, level: int | None, shuffle: bool) -> Candidate:
    encoder = pa.Codec(name, compression_level=level) if level is not None else pa.Codec(name)
    decoder = pa.Codec(name)

    def encode(a: np.ndarray) -> bytes:
        return encoder.compress(_shuffle(a) if shuffle else np.ascontiguousarray(a), asbytes=True)

    def decode(data: bytes, like: np.ndarray) -> np.ndarray:
        raw = decoder.decompress(data, decompressed_size=like.nbytes)
        return _unshuffle(raw, like) if shuffle else np.frombuffer(raw, like.dtype).reshape(like.shape)

    label = f"{name}{'' if level is None else f'-{level}'} {'shuffle' if shuffle else 'raw'}"
    return Candidate(label, encode, decode, for_8bit=not shuffle)


def candidates() -> list[Candidate]:
    """Every codec measured; the first is the encoding of older caches, the second the chosen one."""
    png = [
        Candidate(f"png-{lvl}", _cv2_encode(".png", [cv2.IMWRITE_PNG_COMPRESSION, lvl]), _cv2_decode)
        for lvl in (0, 1, 3, 6, 9)
    ]
    png_rle = [
        Candidate(
            f"png-{lvl} rle",
            _cv2_encode(
                ".png",
                [cv2.IMWRITE_PNG_COMPRESSION, lvl, cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_RLE],
            ),
            _cv2_decode,
        )
        for lvl in (1, 3)
    ]
    tiff = [
        Candidate(
            f"tiff {label}+predictor",
            _cv2_encode(
                ".tiff",
                [
                    cv2.IMWRITE_TIFF_COMPRESSION,
                    compression,
                    cv2.IMWRITE_TIFF_PREDICTOR,
                    cv2.IMWRITE_TIFF_PREDICTOR_HORIZONTAL,
                ],
            ),
            _cv2_decode,
        )
        # OpenCV's libtiff here has no zstd (it falls back to LZW): deflate only.
        for label, compression in (("deflate", cv2.IMWRITE_TIFF_COMPRESSION_ADOBE_DEFLATE),)
    ]

    def blob(level: int) -> Candidate:
        return Candidate(
            f"map blob, zstd-{level}" + (" (chosen)" if level == codec.ZSTD_LEVEL else ""),
            lambda a: codec.encode_array(a, level=level),
            lambda data, like: codec.decode_array(
                data, like.dtype.type, 1 if like.ndim == 2 else like.shape[2]
            ),
        )

    webp = Candidate(
        "webp lossless", _cv2_encode(".webp", [cv2.IMWRITE_WEBP_QUALITY, 101]), _webp_decode, for_16bit=False
    )
    return [
        png[2],
        blob(codec.ZSTD_LEVEL),
        *(blob(level) for level in (-1, 3, 6) if level != codec.ZSTD_LEVEL),
        *png[:2],
        *png[3:],
        *png_rle,
        *tiff,
        webp,
        _compressed("zstd", 1, shuffle=False),
        _compressed("zstd", 3, shuffle=False),
        _compressed("zstd", 1, shuffle=True),
        _compressed("zstd", 3, shuffle=True),
        _compressed("lz4", None, shuffle=False),
        _compressed("lz4", None, shuffle=True),
    ]


def make_cache(root: Path) -> Path:
    """A one-frame full-size Waymo-v1 synthetic scene prepped into ``root / cache`` (by the CLIs)."""
    bindir = Path(sys.executable).parent
    src, cache = root / "src", root / "cache"
    subprocess.run(
        [
            bindir / "phigenesis-synth",
            "--format",
            "waymo-v1",
            "--height",
            "1280",
            "--width",
            "1920",
            "--frames",
            "1",
            "--out",
            src,
        ],
        check=True,
    )
    subprocess.run(
        [bindir / "phigenesis-prep", "waymo", "--input", src, "--out", cache, "--workers", "1"], check=True
    )
    return cache


def read_maps(cache: Path, frames: int) -> dict[str, list[np.ndarray]]:
    """The stored integers of every map column present, by column, over the first ``frames`` frames."""
    reader = CacheReader(cache)
    maps: dict[str, list[np.ndarray]] = {}
    kinds = {column: (dtype, channels) for column, _, dtype, channels in COLUMNS}
    for frame in range(min(frames, len(reader))):
        cameras = reader.read(frame).column("cameras")[0].values
        for field in cameras.type:
            if field.name not in kinds:
                continue
            dtype, channels = kinds[field.name]
            for blob in cameras.field(field.name).to_pylist():
                if blob is not None:
                    maps.setdefault(field.name, []).append(
                        codec.decode_array(blob, dtype, channels, field.name)
                    )
    return maps


def _median_ms(run: Callable[[], object], repeats: int, budget_s: float = 10.0) -> float:
    """Median ms of ``run`` over ``repeats`` runs, fewer (at least one) once ``budget_s`` is spent."""
    times: list[float] = []
    while len(times) < repeats and sum(times) < budget_s:
        t0 = time.perf_counter()
        run()
        times.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(times)


def measure(c: Candidate, arrays: list[np.ndarray], repeats: int) -> tuple[float, float, float]:
    """(bytes, encode ms, decode ms) per map, averaged over ``arrays``; checks the exact round trip."""
    blobs = [c.encode(a) for a in arrays]
    for a, b in zip(arrays, blobs, strict=True):
        back = c.decode(b, a)
        if back.dtype != a.dtype or not np.array_equal(back, a):
            raise AssertionError(f"{c.name}: not lossless on a {a.dtype} {a.shape} map")
    enc = _median_ms(lambda: [c.encode(a) for a in arrays], repeats)
    dec = _median_ms(lambda: [c.decode(b, a) for a, b in zip(arrays, blobs, strict=True)], repeats)
    n = len(arrays)
    return sum(map(len, blobs)) / n, enc / n, dec / n


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--cache", type=Path, help="a prep cache to take the maps from (default: make one)")
    parser.add_argument("--frames", type=int, default=2, help="frames of the cache to take maps from")
    parser.add_argument("--repeats", type=int, default=5)
    add_update_flag(parser)
    args = parser.parse_args()
    cv2.setNumThreads(1)

    with tempfile.TemporaryDirectory(prefix="codec-bench-") as tmp:
        cache = args.cache or make_cache(Path(tmp))
        maps = read_maps(cache, args.frames)
        n_frames = min(args.frames, len(CacheReader(cache)))
    kinds: dict[str, list[np.ndarray]] = {}
    columns_of: dict[str, list[str]] = {}
    for column, kind, _, _ in COLUMNS:
        if column in maps:
            kinds.setdefault(kind, []).extend(maps[column])
            columns_of.setdefault(kind, []).append(column)
    sizes = sorted({f"{a.shape[1]}x{a.shape[0]}" for arrays in kinds.values() for a in arrays})
    report = Report(
        "map-codec",
        "Map codec: per-pixel maps of the cache (benchmarks/codec.py)",
        f"Maps of {n_frames} frames of `{cache if args.cache else 'a synthetic Waymo-v1 scene (made here)'}` "
        f"({', '.join(sizes)} pixels), the integers the cache stores. Per map: mean bytes, median encode and "
        f"decode ms on one thread ({args.repeats} runs, fewer once 10 s are spent); every codec round-trips "
        "exactly. `png-3` is the encoding of caches before schema version 7; `map blob` is "
        "`codec.encode_array`, what prep writes.",
    )
    per_frame: dict[str, list[float]] = {}
    for kind, arrays in kinds.items():
        rows = []
        is_16 = arrays[0].dtype == np.uint16
        for c in candidates():
            if (is_16 and not c.for_16bit) or (not is_16 and not c.for_8bit):
                continue
            if c.name.startswith("webp") and arrays[0].ndim == 3:
                continue
            size, enc, dec = measure(c, arrays, args.repeats)
            raw = sum(a.nbytes for a in arrays) / len(arrays)
            rows.append([c.name, f"{size / 1e3:,.1f}", f"{raw / size:.1f}", f"{enc:.1f}", f"{dec:.1f}"])
            totals = per_frame.setdefault(c.name, [0.0, 0.0, 0.0])
            for i, value in enumerate((size, enc, dec)):
                totals[i] += value * len(arrays) / n_frames
        report.table(
            f"{kind}: {len(arrays)} maps",
            ["codec", "kB / map", "ratio to raw", "encode ms", "decode ms"],
            rows,
            note=f"Columns: {', '.join(f'`{c}`' for c in columns_of[kind])}.",
        )
    everywhere = {c.name for c in candidates() if c.for_8bit and c.for_16bit}
    complete = {name: t for name, t in per_frame.items() if name in everywhere}
    report.table(
        "Every map of a frame",
        ["codec", "MB / frame", "encode ms / frame", "decode ms / frame"],
        [[name, f"{t[0] / 1e6:.2f}", f"{t[1]:.0f}", f"{t[2]:.0f}"] for name, t in complete.items()],
        note="Codecs that apply to every map (16-bit and 8-bit), summed over the maps of one frame.",
    )
    report.write(update=args.update)


if __name__ == "__main__":
    main()
