"""The map encodings: exact round trips within their quantisation (and of the stored integers, for
every shape and content), the PNGs of older caches still decoding, decoding into given arrays, and
clear errors for maps of the wrong kind or size, cut or damaged blobs and size bombs."""

from __future__ import annotations

import struct
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from phigenesis.data import cache_run, codec, schema
from phigenesis.data.shards import CacheReader, verify_cache
from tests.conftest import TINY_PREP_ARGS


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(3)


def test_depth_round_trips_within_half_a_step_and_marks_out_of_range_unknown(rng: np.random.Generator):
    depth = rng.uniform(0.5, 250.0, size=(12, 17)).astype(np.float32)
    depth[0, 0], depth[0, 1], depth[0, 2], depth[0, 3] = 0.0, np.inf, np.nan, 300.0
    back = codec.decode_depth(codec.encode_depth(depth))
    ok = np.isfinite(depth) & (depth > 0) & (depth < codec.DEPTH_MAX_M)
    assert np.abs(back[ok] - depth[ok]).max() <= 0.5 / codec.DEPTH_SCALE + 1e-6
    assert np.all(back[0, :4] == 0.0)


def test_flow_round_trips_in_both_layouts_and_into_a_given_array(rng: np.random.Generator):
    flow = rng.uniform(-30.0, 30.0, size=(9, 11, 3)).astype(np.float32)
    data = codec.encode_flow(flow)
    hwc = codec.decode_flow(data)
    assert np.abs(hwc - flow).max() <= 0.5 / codec.FLOW_SCALE + 1e-6
    out = np.full((3, 9, 11), np.nan, np.float32)
    chw = codec.decode_flow(data, out, channels_first=True)
    assert chw is out
    assert np.array_equal(chw, hwc.transpose(2, 0, 1))


def test_decoding_into_given_arrays_equals_plain_decoding(rng: np.random.Generator):
    depth = rng.uniform(1.0, 80.0, size=(6, 7))
    sem = rng.integers(0, 19, size=(6, 7), dtype=np.uint8)
    inst = rng.integers(0, 60000, size=(6, 7), dtype=np.uint16)
    d_out, s_out, i_out = np.empty((6, 7), np.float32), np.empty((6, 7), np.uint8), np.empty((6, 7), np.int32)
    assert np.array_equal(
        codec.decode_depth(codec.encode_depth(depth), d_out), codec.decode_depth(codec.encode_depth(depth))
    )
    assert np.array_equal(codec.decode_semantic(codec.encode_semantic(sem), s_out), sem)
    assert np.array_equal(codec.decode_instance(codec.encode_instance(inst), i_out), inst.astype(np.int32))
    assert i_out.dtype == np.int32


def test_a_map_of_the_wrong_kind_or_size_is_refused():
    with pytest.raises(
        codec.MapDecodeError, match="expected a 1-channel uint16 map, got a 1-channel 8-bit map"
    ):
        codec.decode_depth(codec.encode_semantic(np.zeros((4, 4), np.uint8)))
    with pytest.raises(codec.MapDecodeError, match="neither a PNG nor a phigenesis map blob"):
        codec.decode_flow(b"garbage")
    with pytest.raises(codec.MapDecodeError, match="declares 4x4 pixels, expected 4x5"):
        codec.decode_depth(codec.encode_depth(np.ones((4, 4))), np.empty((5, 4), np.float32))
    with pytest.raises(codec.MapDecodeError, match="declares 4x4 pixels, expected 3x4"):
        codec.decode_semantic(codec.encode_semantic(np.ones((4, 4), np.uint8)), shape=(4, 3))
    with pytest.raises(codec.MapDecodeError, match="expected a 3-channel uint16 map"):
        codec.decode_flow(codec.encode_instance(np.ones((4, 4), np.uint16)))


def _stored(kind: str, shape: tuple[int, ...], dtype: type, seed: int) -> np.ndarray:
    """A map of the stored integers: random, sparse (5 % non-zero), constant 0 or max, smooth
    (rows of a ramp, like dense depth) or piecewise constant (like labels)."""
    rng = np.random.default_rng(seed)
    top = np.iinfo(dtype).max
    if kind == "random":
        return rng.integers(0, top, size=shape, endpoint=True, dtype=dtype)
    if kind == "sparse":
        return np.where(rng.random(shape) < 0.05, rng.integers(1, top, size=shape, endpoint=True), 0).astype(
            dtype
        )
    if kind in ("zero", "max"):
        return np.full(shape, 0 if kind == "zero" else top, dtype)
    rows = np.arange(shape[0]).reshape(-1, *([1] * (len(shape) - 1)))
    if kind == "smooth":
        return ((rows * 37 + rng.integers(0, 3, size=shape)) % (top + 1)).astype(dtype)
    return np.broadcast_to((rows // 5) % 7 * (top // 7), shape).astype(dtype)


@settings(max_examples=150, deadline=None)
@given(
    h=st.sampled_from([1, 2, 3, 7, 31, 37, 64, 886]),
    w=st.sampled_from([1, 2, 5, 33, 160]),
    channels=st.sampled_from([1, 3]),
    dtype=st.sampled_from([np.uint8, np.uint16]),
    kind=st.sampled_from(["random", "sparse", "zero", "max", "smooth", "labels"]),
    seed=st.integers(0, 2**16),
)
def test_every_map_round_trips_exactly(h: int, w: int, channels: int, dtype: type, kind: str, seed: int):
    shape = (h, w) if channels == 1 else (h, w, channels)
    image = _stored(kind, shape, dtype, seed)
    blob = codec.encode_array(image)
    assert codec.layout_of(blob) == "zstd"
    back = codec.decode_array(blob, dtype, channels, shape=(h, w))
    assert back.dtype == dtype and back.shape == shape
    assert np.array_equal(back, image)


def test_delta_coding_is_kept_where_it_compresses_smaller():
    smooth = _stored("smooth", (886, 160), np.uint16, 1)
    sparse = _stored("sparse", (886, 160), np.uint16, 1)
    filt = {name: codec.encode_array(a)[7] for name, a in (("smooth", smooth), ("sparse", sparse))}
    assert filt == {"smooth": codec.FILTER_SHUFFLE | codec.FILTER_DELTA, "sparse": codec.FILTER_SHUFFLE}
    assert codec.encode_array(np.zeros((5, 5), np.uint8))[7] == codec.FILTER_NONE
    # A ramp of 37 per row plus noise of 0-2: 125,038 bytes byte-shuffled without delta coding.
    assert len(codec.encode_array(smooth)) < 0.4 * 125_038
    assert len(codec.encode_array(smooth)) < len(codec.encode_png(smooth))


def test_the_sampled_filter_choice_matches_compressing_both_ways():
    """encode_array picks delta coding from an eighth of the rows; the reference compresses the
    whole map both ways. On these maps (1280 rows: dense-depth ramps, sparse LiDAR, labels, noise)
    it picks the same filter and the blob is byte-identical."""
    shape = (1280, 480)
    for kind in ("random", "sparse", "smooth", "labels", "zero"):
        for dtype in (np.uint8, np.uint16):
            image = _stored(kind, shape, dtype, 3)
            blob, reference = codec.encode_array(image), codec.encode_array_reference(image)
            assert blob == reference, (kind, dtype)
            assert np.array_equal(codec.decode_array(blob, dtype, shape=shape), image)


def test_quantisation_matches_its_float64_definition():
    """The float32 fast paths give the stored integers of the float64 definitions exactly,
    including NaN, infinities, negatives, values beyond the range and ties."""
    rng = np.random.default_rng(2)
    depth = rng.uniform(-1.0, 300.0, (64, 64)).astype(np.float32)
    depth[0, :6] = [np.nan, np.inf, -np.inf, 0.5 / 256, 1.5 / 256, 255.998]
    want = np.round(depth.astype(np.float64) * 256)
    want[~np.isfinite(depth) | (depth <= 0) | (want > 65535)] = 0
    assert np.array_equal(codec.quantise_depth(depth), want.astype(np.uint16))
    assert np.array_equal(codec.quantise_depth(depth.astype(np.float64)), want.astype(np.uint16))
    conf = rng.uniform(-0.2, 1.2, (64, 64)).astype(np.float32)
    conf[0, :5] = [np.nan, np.inf, -np.inf, 0.5 / 255, 2.5 / 255]
    want_c = np.round(np.clip(np.nan_to_num(conf.astype(np.float64), nan=0.0), 0, 1) * 255).astype(np.uint8)
    assert np.array_equal(codec.quantise_confidence(conf), want_c)


def test_the_pngs_of_older_caches_still_decode():
    rng = np.random.default_rng(5)
    depth = rng.uniform(0.5, 250.0, size=(886, 1920))
    depth[::7] = 0.0
    q = codec.quantise_depth(depth)
    for old in (codec.encode_png(q), cv2.imencode(".png", q)[1].tobytes()):  # reference, and cv2 as written
        assert codec.layout_of(old) == "png"
        assert np.array_equal(
            codec.decode_depth(old, shape=(886, 1920)), codec.decode_depth(codec.encode_depth(depth))
        )
    sem = rng.integers(0, 19, size=(9, 13), dtype=np.uint8)
    assert np.array_equal(codec.decode_semantic(codec.encode_png(sem)), sem)
    conf = rng.integers(0, 256, size=(9, 13), dtype=np.uint8)
    assert np.array_equal(codec.decode_confidence(codec.encode_png(conf)), conf * np.float32(1 / 255))
    inst = rng.integers(0, 65536, size=(9, 13), dtype=np.uint16)
    assert np.array_equal(codec.decode_instance(codec.encode_png(inst), np.empty((9, 13), np.int32)), inst)
    flow = rng.uniform(-30.0, 30.0, size=(9, 13, 3))
    q_flow = codec.quantise_flow(flow)
    bgr_png = cv2.imencode(".png", q_flow[..., ::-1])[1].tobytes()  # the old encode_flow: OpenCV's BGR order
    assert np.array_equal(codec.decode_flow(bgr_png), codec.decode_flow(codec.encode_flow(flow)))
    out = np.empty((3, 9, 13), np.float32)
    assert np.array_equal(
        codec.decode_flow(bgr_png, out, channels_first=True), codec.decode_flow(bgr_png).transpose(2, 0, 1)
    )


def test_decoders_take_bytes_memoryviews_and_numpy_buffers_and_return_writable_arrays():
    sem = np.arange(60, dtype=np.uint8).reshape(6, 10)
    blob = codec.encode_semantic(sem)
    for data in (blob, memoryview(blob), np.frombuffer(blob, np.uint8), bytearray(blob)):
        back = codec.decode_semantic(data)
        assert np.array_equal(back, sem) and back.flags.writeable


def _damaged(blob: bytes) -> dict[str, tuple[bytes, str]]:
    payload = bytearray(blob)
    payload[codec.HEADER_SIZE + 4 : codec.HEADER_SIZE + 12] = b"\xa5" * 8
    future = bytearray(blob)
    future[4] = codec.FORMAT_VERSION + 1
    unknown_filter = bytearray(blob)
    unknown_filter[7] = 0x80
    return {
        "empty": (b"", "neither a PNG nor"),
        "header cut": (blob[:10], "shorter than the 20-byte map header"),
        "payload cut": (blob[:-5], r"declares a \d+-byte payload, \d+ bytes follow \(cut short\)"),
        "trailing bytes": (blob + b"\0", r"\(trailing bytes\)"),
        "payload overwritten": (bytes(payload), "does not decode to 1179648 bytes"),
        "future version": (bytes(future), f"map format version {codec.FORMAT_VERSION + 1}"),
        "unknown filter": (bytes(unknown_filter), "filter code 128"),
    }


@pytest.mark.parametrize(
    "damage",
    [
        "empty",
        "header cut",
        "payload cut",
        "trailing bytes",
        "payload overwritten",
        "future version",
        "unknown filter",
    ],
)
def test_a_cut_or_damaged_blob_raises_the_codec_error_naming_the_problem(damage: str):
    depth = np.tile(np.linspace(1.0, 80.0, 768), (768, 1))
    data, words = _damaged(codec.encode_depth(depth))[damage]
    with pytest.raises(codec.MapDecodeError, match=words):
        codec.decode_depth(data)


def test_a_cut_or_damaged_png_raises_the_codec_error():
    png = codec.encode_png(np.tile(np.arange(200, dtype=np.uint16), (50, 1)))
    with pytest.raises(codec.MapDecodeError, match="ends without the IEND chunk"):
        codec.decode_instance(png[:-30])
    with pytest.raises(codec.MapDecodeError, match="without an IHDR chunk"):
        codec.decode_instance(png[:20])
    broken = bytearray(png)
    broken[60:80] = b"\xff" * 20
    with pytest.raises(codec.MapDecodeError, match="PNG bytes do not decode"):
        codec.decode_instance(bytes(broken))


def test_a_size_bomb_is_refused_before_anything_is_allocated():
    blob = bytearray(codec.encode_depth(np.ones((4, 4))))
    struct.pack_into("<II", blob, 8, 200_000, 300_000)  # 6e10 pixels: 120 GB if believed
    with pytest.raises(
        codec.MapDecodeError, match=r"declares 300000x200000 pixels \(at most 67108864 accepted\)"
    ):
        codec.decode_depth(bytes(blob))
    with pytest.raises(codec.MapDecodeError, match="declares 300000x200000 pixels, expected 1920x1280"):
        codec.decode_depth(bytes(blob), shape=(1280, 1920))
    # The same lie in a PNG's IHDR chunk is refused before the PNG decoder runs.
    png = bytearray(codec.encode_png(np.ones((4, 4), np.uint16)))
    struct.pack_into(">II", png, 16, 300_000, 200_000)
    with pytest.raises(codec.MapDecodeError, match="the PNG header declares 300000x200000 pixels"):
        codec.decode_depth(bytes(png))
    with pytest.raises(codec.MapDecodeError, match="expected 1920x1280"):
        codec.decode_depth(bytes(png), np.empty((1280, 1920), np.float32))


#: The encoders of caches before schema version 7: the same integers as grey (flow: RGB) PNGs.
PNG_ENCODERS = {
    "encode_depth": lambda d: codec.encode_png(codec.quantise_depth(d)),
    "encode_confidence": lambda c: codec.encode_png(codec.quantise_confidence(c)),
    "encode_semantic": lambda s: codec.encode_png(np.asarray(s, np.uint8)),
    "encode_instance": lambda i: codec.encode_png(np.asarray(i, np.uint16)),
    "encode_flow": lambda f: codec.encode_png(codec.quantise_flow(f)),
}


def test_a_schema_6_cache_of_png_maps_still_verifies_and_reads_the_same_maps(
    tiny_cache: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
):
    from phigenesis import prep

    old = tmp_path / "old"
    with monkeypatch.context() as m:
        for name, encode in PNG_ENCODERS.items():
            m.setattr(codec, name, encode)
        m.setattr(schema, "SCHEMA_VERSION", 6)
        m.setattr(cache_run, "SCHEMA_VERSION", 6)
        prep.synthetic(old, progress=False, **TINY_PREP_ARGS)  # type: ignore[arg-type]

    report = verify_cache(old)
    assert report.status == "OK" and not report.errors
    assert any("schema version 6; this toolkit writes version 7" in w for w in report.warnings)
    old_reader, new_reader = CacheReader(old), CacheReader(tiny_cache)
    blobs = old_reader.read(0, ["cameras"]).column("cameras")[0].values
    assert {codec.layout_of(b) for b in blobs.field("truth_depth_png").to_pylist()} == {"png"}
    new_blobs = new_reader.read(0, ["cameras"]).column("cameras")[0].values
    assert {codec.layout_of(b) for b in new_blobs.field("truth_depth_png").to_pylist()} == {"zstd"}
    assert len(old_reader) == len(new_reader) == 6
    for i in range(len(old_reader)):
        for was, now in zip(old_reader.frame(i).cameras, new_reader.frame(i).cameras, strict=True):
            assert was.truth is not None and now.truth is not None
            for field in ("depth_m", "semantic", "instance", "flow_world_mps"):
                assert np.array_equal(getattr(was.truth, field), getattr(now.truth, field)), (i, field)
