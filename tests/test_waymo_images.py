"""Camera images are checked where the Waymo source reads them: a JPEG cut short, or one whose
header reads but which does not decode, is an error naming the file, the record and the camera,
and under ``on_error="skip"`` loses only that image (the frame keeps its other cameras, the
manifest counts it). A cache that nevertheless holds such an image (written before the check, or
crafted) fails in the loader, the range-view loader, the VAE's and the segmenter's image readers
and the preview with an error naming the shard, the row and the camera.

Each record is written with valid TFRecord CRCs: only the JPEG inside is damaged.
"""

from __future__ import annotations

import copy
import io
import json
import random
import re
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest

from phigenesis import prep
from phigenesis.data import image_headers
from phigenesis.data.loader import FrameDataset
from phigenesis.data.pipeline import PipelineSpec, PrepError, prepare
from phigenesis.data.records import CameraImage, InvalidRecord, check_image_decodes
from phigenesis.data.shards import CacheReader
from phigenesis.data.sources.synthetic import SyntheticScene
from phigenesis.data.sources.synthetic.waymo_export import raw_frame
from phigenesis.data.sources.waymo import WaymoConfig, WaymoSource, convert, protos, tfrecord, v1, v2
from phigenesis.data.sources.waymo.raw import CAMERAS_LEFT_OUT, RawFrame, WaymoFormatError
from phigenesis.errors import CacheError
from phigenesis.train.segmenter import LabelledImage, LabelledImages, SegmenterTrainConfig
from phigenesis.train.vae import ClipImages
from tests.test_waymo_hostile import CONFIG, FRONT_RIGHT
from tests.test_waymo_hostile import SPEC as NO_STAGES
from tests.test_waymo_real import PANOPTIC

SEGMENT = "images"
#: The frame (and v1 record) whose FRONT_RIGHT image the tests damage.
DAMAGED = 1
Damage = Callable[[bytes], bytes]


def cut_in_half(jpeg: bytes) -> bytes:
    """The first half of ``jpeg``: its header still reads (the size is the calibration's)."""
    half = jpeg[: len(jpeg) // 2]
    assert image_headers.jpeg_size(io.BytesIO(half).read) == image_headers.jpeg_size(io.BytesIO(jpeg).read)
    return half


def _scan_start(jpeg: bytes) -> int:
    """Offset of the start-of-scan marker (FF DA), walking the marker segments before it."""
    pos = 2
    while jpeg[pos + 1] != 0xDA:
        pos += 2 + int.from_bytes(jpeg[pos + 2 : pos + 4], "big")
    return pos


def undecodable(jpeg: bytes) -> bytes:
    """``jpeg`` with its scan selecting Huffman tables 3 (none is defined): the header reads and
    the stream ends with its end-of-image marker, but no decoder can decode it."""
    out = bytearray(jpeg)
    sos = _scan_start(jpeg)
    for k in range(out[sos + 4]):  # Ns components, each (selector, Td << 4 | Ta)
        out[sos + 6 + 2 * k] = 0x33
    return bytes(out)


DAMAGES: dict[str, tuple[Damage, str]] = {
    "cut in half": (cut_in_half, "end without the JPEG end-of-image marker FF D9 (cut short)"),
    "undecodable": (undecodable, "do not decode"),
}


@pytest.fixture(scope="module")
def raws() -> list[RawFrame]:
    scene = SyntheticScene(CONFIG, 0)
    return [raw_frame(scene, k) for k in range(CONFIG.frames)]


def _image(raw: RawFrame, code: int = FRONT_RIGHT):
    return next(im for im in raw.images if im.name == code)


def _damaged(raws: list[RawFrame], damage: Damage) -> list[RawFrame]:
    """A deep copy of ``raws`` with frame DAMAGED's FRONT_RIGHT JPEG damaged."""
    frames = copy.deepcopy(raws)
    image = _image(frames[DAMAGED])
    image.jpeg = damage(image.jpeg)
    return frames


def _v1(tmp_path: Path, frames: list[RawFrame]) -> Path:
    """The frames as a v1 file (records with valid CRCs)."""
    path = tmp_path / "in" / f"segment-{SEGMENT}_with_camera_labels.tfrecord"
    path.parent.mkdir(parents=True, exist_ok=True)
    tfrecord.write_records(path, [v1.serialize_frame(f) for f in frames])
    return path


def _where(path: Path, record: int) -> str:
    return f"{path} (record {record} at byte {tfrecord.index_records(path)[record].offset})"


def _prep(out: Path, path: Path, pipeline: PipelineSpec | str = NO_STAGES, on_error: str = "raise"):
    return prepare(
        out, "waymo", {"input": str(path), "on_error": on_error}, pipeline=pipeline, progress=False
    )


def _first_frame_message(path: Path) -> protos.Frame:
    """The first record of a v1 file as a Frame message, to edit."""
    message = protos.Frame()
    message.ParseFromString(v1.V1File(path).record(0))
    return message


# --------------------------------------------------------------------------------------------
# The check itself


def test_end_problem_says_a_stream_is_cut_short_and_passes_whole_ones() -> None:
    rgb = np.random.default_rng(0).integers(0, 255, (16, 24, 3), np.uint8)
    for ext, words in ((".jpg", "JPEG end-of-image marker FF D9"), (".png", "PNG IEND chunk")):
        data = cv2.imencode(ext, rgb)[1].tobytes()
        assert image_headers.end_problem(data) is None
        assert image_headers.end_problem(np.frombuffer(data, np.uint8)) is None
        assert image_headers.end_problem(data[:-1]) == f"end without the {words} (cut short)"
    assert image_headers.end_problem(b"GIF89a") == "are neither a JPEG nor a PNG stream"
    assert image_headers.end_problem(b"") == "are neither a JPEG nor a PNG stream"


def _variants(data: bytes, count: int, rng: random.Random) -> list[bytes]:
    """``count`` damaged copies of a JPEG: cut (and re-terminated), header bytes overwritten,
    bits flipped, scan bytes overwritten, spans deleted."""
    scan = _scan_start(data)
    out = []
    for k in range(count):
        b = bytearray(data)
        kind = k % 5
        if kind == 0:
            b = b[: rng.randrange(2, len(b))] + bytearray(image_headers.JPEG_END)
        elif kind == 1:
            b[rng.randrange(2, scan + 12)] = rng.randrange(256)
        elif kind == 2:
            b[rng.randrange(2, len(b) - 2)] ^= 1 << rng.randrange(8)
        elif kind == 3:
            for _ in range(rng.randrange(1, 20)):
                b[rng.randrange(scan, len(b) - 2)] = rng.randrange(256)
        else:
            i = rng.randrange(2, len(b) - 2)
            del b[i : min(len(b) - 2, i + rng.randrange(1, 64))]
        out.append(bytes(b))
    return out


@pytest.mark.parametrize("progressive", [False, True])
def test_the_eighth_scale_check_fails_exactly_where_a_full_decode_fails(progressive: bool) -> None:
    rgb = cv2.GaussianBlur(np.random.default_rng(1).integers(0, 255, (48, 64, 3), np.uint8), (5, 5), 2)
    data = cv2.imencode(".jpg", rgb, [cv2.IMWRITE_JPEG_PROGRESSIVE, int(progressive)])[1].tobytes()
    failures = 0
    for damaged in _variants(data, 500, random.Random(int(progressive))):
        full = cv2.imdecode(np.frombuffer(damaged, np.uint8), cv2.IMREAD_COLOR) is None
        try:
            check_image_decodes(damaged)
            checked = False
        except InvalidRecord:
            checked = True
        ends = image_headers.end_problem(damaged) is not None
        assert checked == (full or ends), damaged
        failures += full
    assert failures > 20  # the damage reaches the decoder, not only the end marker


# --------------------------------------------------------------------------------------------
# v1 and v2 readers


def test_a_v1_jpeg_cut_in_half_names_the_file_record_and_camera_with_the_bundled_pipeline(
    tmp_path: Path, raws: list[RawFrame]
) -> None:
    path = _v1(tmp_path, _damaged(raws, cut_in_half))
    size = len(_image(raws[DAMAGED]).jpeg) // 2
    words = f"camera FRONT_RIGHT image_bytes holds {size} bytes that end without the JPEG end-of-image marker"
    with pytest.raises(PrepError, match=re.escape(f"{_where(path, DAMAGED)}: {words}")):
        _prep(tmp_path / "out", path, "waymo")


def test_a_v1_jpeg_that_does_not_decode_names_the_file_record_and_camera(
    tmp_path: Path, raws: list[RawFrame]
) -> None:
    path = _v1(tmp_path, _damaged(raws, undecodable))
    size = len(_image(raws[DAMAGED]).jpeg)
    words = f"camera FRONT_RIGHT image_bytes holds {size} bytes that do not decode"
    with pytest.raises(PrepError, match=re.escape(f"{_where(path, DAMAGED)}: {words}")):
        _prep(tmp_path / "out", path)


@pytest.mark.parametrize("damage", list(DAMAGES))
def test_under_skip_with_the_bundled_pipeline_only_the_damaged_image_is_left_out(
    tmp_path: Path, raws: list[RawFrame], damage: str
) -> None:
    path = _v1(tmp_path, _damaged(raws, DAMAGES[damage][0]))
    out = tmp_path / "out"
    summary = _prep(out, path, "waymo", on_error="skip")
    assert summary.frames_written == CONFIG.frames and not summary.scenes_skipped
    (scene,) = json.loads((out / "manifest.json").read_text())["scenes"]
    assert (scene["status"], scene["dropped"]) == ("complete", {CAMERAS_LEFT_OUT: 1})
    reader = CacheReader(out)
    cameras = [[c.name for c in reader.frame(i).cameras] for i in range(CONFIG.frames)]
    assert cameras[DAMAGED] == ["FRONT", "FRONT_LEFT", "SIDE_LEFT", "SIDE_RIGHT"]
    assert cameras[0] == cameras[2] == ["FRONT", "FRONT_LEFT", "FRONT_RIGHT", "SIDE_LEFT", "SIDE_RIGHT"]
    # Everything downstream reads the cache: verify, the loader (every image), the preview.
    assert prep.verify(out).ok
    dataset = FrameDataset(out, fields=("images", "cameras"))
    assert [len(dataset[i]["images"]) for i in range(CONFIG.frames)] == [5, 4, 5]
    assert prep.preview(out, frame=DAMAGED).shape[2] == 3


def test_a_v2_jpeg_cut_in_half_names_the_camera_image_file_frame_and_camera_and_skip_leaves_it_out(
    tmp_path: Path, raws: list[RawFrame]
) -> None:
    root = tmp_path / "v2"
    v2.write_v2(root, _damaged(raws, cut_in_half))
    segment = raws[0].segment
    file = root / "camera_image" / f"{segment}.parquet"
    ts = raws[DAMAGED].timestamp_micros
    words = "camera FRONT_RIGHT image_bytes holds"
    with pytest.raises(PrepError, match=re.escape(f"{file} frame {ts}: {words}") + ".* end without the JPEG"):
        _prep(tmp_path / "out", root)
    scene = WaymoSource(WaymoConfig(input=str(root), on_error="skip")).load(segment)
    assert [len(f.cameras) for f in scene.frames] == [5, 4, 5]
    assert scene.dropped.totals() == {CAMERAS_LEFT_OUT: 1}


def test_converting_a_frame_decodes_each_image_once_at_one_eighth_scale(
    raws: list[RawFrame], monkeypatch: pytest.MonkeyPatch
) -> None:
    flags: list[int] = []
    imdecode = cv2.imdecode

    def counting(data: np.ndarray, flag: int) -> np.ndarray | None:
        flags.append(flag)
        return imdecode(data, flag)

    monkeypatch.setattr(cv2, "imdecode", counting)
    frame = convert.frame(raws[0], 0, raws[0].global_from_vehicle[:3, 3].copy())
    assert sum(c.image_bytes is not None for c in frame.cameras) == 5
    assert flags.count(cv2.IMREAD_REDUCED_COLOR_8) == 5  # besides the panoptic labels' PNGs
    assert cv2.IMREAD_COLOR not in flags
    bad = copy.deepcopy(_image(raws[0]))
    bad.jpeg = cut_in_half(bad.jpeg)
    calibration = frame.cameras[2].calibration
    with pytest.raises(
        WaymoFormatError, match=r"^here: camera FRONT_RIGHT image_bytes holds \d+ bytes that end"
    ):
        convert.camera_image(bad, calibration, raws[0].global_from_vehicle[:3, 3].copy(), "here")


@pytest.mark.skipif(not PANOPTIC.exists(), reason=f"the real Waymo sample {PANOPTIC} is not here")
def test_the_real_frames_jpegs_pass_and_its_front_image_cut_in_half_names_record_0(tmp_path: Path) -> None:
    message = _first_frame_message(PANOPTIC)
    for image in message.images:
        check_image_decodes(image.image)  # five real JPEGs: 1920 x 1280 and 1920 x 886
    front = next(im for im in message.images if im.name == 1)
    front.image = front.image[: len(front.image) // 2]
    path = tmp_path / "in" / PANOPTIC.name
    path.parent.mkdir()
    tfrecord.write_records(path, [message.SerializeToString()])
    words = f"camera FRONT image_bytes holds {len(front.image)} bytes that end without the JPEG end-of-image"
    with pytest.raises(PrepError, match=re.escape(f"{_where(path, 0)}: {words}")):
        _prep(tmp_path / "out", path)


# --------------------------------------------------------------------------------------------
# A cache that nevertheless holds such an image


@pytest.mark.parametrize("damage", list(DAMAGES))
def test_a_cache_holding_a_damaged_image_fails_naming_the_shard_row_and_camera(
    tmp_path: Path, raws: list[RawFrame], monkeypatch: pytest.MonkeyPatch, damage: str
) -> None:
    make, words = DAMAGES[damage]
    with monkeypatch.context() as m:  # as a cache written before the source checked images
        m.setattr(CameraImage, "check_image", lambda self: None)
        _prep(tmp_path / "out", _v1(tmp_path, _damaged(raws, make)))
    out = tmp_path / "out"
    reader = CacheReader(out)
    shard, row = reader.locate(DAMAGED)
    size = len(make(_image(raws[DAMAGED]).jpeg))
    where = re.escape(f"{shard}: row {row}: camera FRONT_RIGHT")
    loader_words = re.escape(f"image holds {size} bytes that {words}")
    for fields in (("images",), ("range_view",)):
        dataset = FrameDataset(out, fields=fields, decode_threads=1)
        dataset[0]  # the frame before it loads
        with pytest.raises(CacheError, match=rf"^{where}: {loader_words}$"):
            dataset[DAMAGED]
    with pytest.raises(CacheError, match=rf"^{where}: {loader_words}$"):
        ClipImages(reader, (24, 36)).image(DAMAGED, "FRONT_RIGHT")
    labelled = LabelledImages(
        reader, [LabelledImage(DAMAGED, 2, "label_semantic_png")], SegmenterTrainConfig(), False
    )
    with pytest.raises(CacheError, match=rf"^{where}: {loader_words}$"):
        labelled.load(0)
    at = re.escape(f"{shard}: row {row}: camera FRONT_RIGHT at ")  # and the image's time
    preview_words = re.escape(f" image_bytes holds {size} bytes that {words}")
    with pytest.raises(CacheError, match=rf"^{at}\d+{preview_words}$"):
        prep.preview(out, frame=DAMAGED)
