"""Tests for phigenesis.data.loader: FrameDataset samples, collate_frames and DataLoader workers."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader

from phigenesis.data import loader
from phigenesis.data.loader import FIELD_GROUPS, FrameDataset, collate_frames
from phigenesis.data.shards import CacheReader
from tests.conftest import TINY_PREP_ARGS

TORCH_DTYPES = {
    "uint8": torch.uint8,
    "int32": torch.int32,
    "int64": torch.int64,
    "float32": torch.float32,
    "float64": torch.float64,
}


def documented_entries() -> dict[str, str]:
    """key -> type as the table in the loader's module docstring gives them."""
    lines = (loader.__doc__ or "").splitlines()
    rules = [i for i, line in enumerate(lines) if line.startswith("====")]
    assert len(rules) == 3, "the docstring should hold one reST table"
    columns = [m.start() for m in re.finditer(r"=+", lines[rules[0]])]
    entries = {}
    for line in lines[rules[1] + 1 : rules[2]]:
        keys = line[columns[0] : columns[1]].strip().split(", ")
        kind = line[columns[1] : columns[2]].strip()
        types = kind.split(", ") if len(keys) > 1 else [kind]  # "scene_id, frame_index  str, int"
        entries.update(zip(keys, types, strict=True))
    return entries


def assert_same(a: Any, b: Any, where: str = "") -> None:
    """Deep equality of samples (tensors compared by dtype, shape and values)."""
    assert type(a) is type(b), where
    if isinstance(a, torch.Tensor):
        assert a.dtype == b.dtype and a.shape == b.shape, where
        assert torch.equal(a, b), where
    elif isinstance(a, dict):
        assert list(a) == list(b), where
        for k in a:
            assert_same(a[k], b[k], f"{where}.{k}")
    elif isinstance(a, list):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            assert_same(x, y, f"{where}[{i}]")
    else:
        assert a == b, where


@pytest.fixture(scope="module")
def dataset(tiny_cache: Path) -> FrameDataset:
    return FrameDataset(tiny_cache, fields=FIELD_GROUPS)


def test_dataset_has_one_sample_per_frame_of_the_cache(dataset: FrameDataset) -> None:
    assert len(dataset) == TINY_PREP_ARGS["scenes"] * TINY_PREP_ARGS["frames"]
    assert [dataset[i]["frame_index"] for i in range(len(dataset))] == [0, 1, 2, 0, 1, 2]


def test_samples_hold_exactly_the_documented_keys_with_their_shapes_and_dtypes(
    dataset: FrameDataset, tiny_cache: Path
) -> None:
    entries = documented_entries()
    reader = CacheReader(tiny_cache)
    for index in (0, len(dataset) - 1):
        sample = dataset[index]
        record = reader.frame(index)
        sizes = {
            "C": len(record.cameras),
            "H": TINY_PREP_ARGS["height"],
            "W": TINY_PREP_ARGS["width"],
            "N": len(record.lidar),
            "M": len(record.boxes),
        }
        assert set(sample) == set(entries)
        for key, spec in entries.items():
            value = sample[key]
            if spec in ("str", "int"):
                assert type(value) is {"str": str, "int": int}[spec], key
                continue
            m = re.fullmatch(r"list\[str\] \((\w)\)", spec)
            if m:
                assert isinstance(value, list) and all(isinstance(v, str) for v in value), key
                assert len(value) == sizes[m.group(1)], key
                continue
            m = re.fullmatch(r"(\w+) \[(.*)\]", spec)
            assert m, f"undocumented type {spec!r} of {key}"
            shape = tuple(int(d) if d.isdigit() else sizes[d] for d in m.group(2).split(", "))
            assert isinstance(value, torch.Tensor), key
            assert value.dtype == TORCH_DTYPES[m.group(1)], key
            assert tuple(value.shape) == shape, key


def test_sample_values_match_the_frame_records_decoded_by_the_reader(
    dataset: FrameDataset, tiny_cache: Path
) -> None:
    reader = CacheReader(tiny_cache)
    index = 4
    s, f = dataset[index], reader.frame(index)
    assert (s["scene_id"], s["frame_index"], s["frame_timestamp_micros"]) == (
        f.scene_id,
        f.frame_index,
        f.timestamp_micros,
    )
    assert np.array_equal(s["world_from_ego"].numpy(), f.world_from_ego)
    assert s["camera_names"] == [c.name for c in f.cameras]
    for i, cam in enumerate(f.cameras):
        assert np.array_equal(s["images"][i].permute(1, 2, 0).numpy(), cam.decode_image())
        assert np.array_equal(s["intrinsics"][i].numpy(), cam.calibration.intrinsics.astype(np.float32))
        assert np.array_equal(s["distortion"][i].numpy(), cam.calibration.distortion.astype(np.float32))
        assert np.array_equal(s["ego_from_camera"][i].numpy(), cam.calibration.ego_from_camera)
        assert np.array_equal(s["camera_world_from_ego"][i].numpy(), cam.world_from_ego)
        assert s["camera_timestamp_micros"][i].item() == cam.timestamp_micros
        assert np.array_equal(s["truth_depth"][i].numpy(), cam.truth.depth_m)
        assert np.array_equal(s["truth_semantic"][i].numpy(), cam.truth.semantic)
        assert np.array_equal(s["truth_instance"][i].numpy(), cam.truth.instance)
        assert np.array_equal(s["truth_flow"][i].permute(1, 2, 0).numpy(), cam.truth.flow_world_mps)
    lidar = f.lidar
    assert np.array_equal(s["lidar_points_ego"].numpy(), lidar.points_ego)
    assert np.array_equal(s["lidar_intensity"].numpy(), lidar.intensity)
    assert np.array_equal(s["lidar_beam_index"].numpy(), lidar.beam_index)
    assert np.array_equal(s["lidar_origins_ego"].numpy(), lidar.origins_ego)
    assert np.array_equal(s["lidar_truth_semantic"].numpy(), lidar.semantic)
    assert np.array_equal(s["lidar_truth_instance"].numpy(), lidar.instance)
    b = f.boxes
    assert s["boxes_track_id"] == b.track_id
    for name in ("center_world", "size_lwh", "yaw_world", "velocity_world", "class_id", "instance_id"):
        assert np.array_equal(s[f"boxes_{name}"].numpy(), getattr(b, name)), name


def test_only_the_requested_field_groups_are_decoded(tiny_cache: Path) -> None:
    sample = FrameDataset(tiny_cache, fields=("boxes",))[0]
    assert {k for k in sample if k.startswith("boxes_")} == {
        k for k in documented_entries() if k.startswith("boxes_")
    }
    assert not {"images", "intrinsics", "truth_depth", "lidar_points_ego"} & set(sample)


def test_default_fields_leave_out_the_lidar(tiny_cache: Path) -> None:
    sample = FrameDataset(tiny_cache)[0]
    assert {"images", "intrinsics", "truth_depth", "boxes_center_world"} <= set(sample)
    assert not [k for k in sample if k.startswith("lidar_")]


def test_unknown_field_groups_are_rejected(tiny_cache: Path) -> None:
    with pytest.raises(ValueError, match=r"unknown field groups \['radar'\]"):
        FrameDataset(tiny_cache, fields=("images", "radar"))


@pytest.mark.slow
def test_dataloader_with_two_workers_yields_the_same_batches_as_without_workers(
    dataset: FrameDataset,
) -> None:
    def batches(workers: int) -> list[dict[str, Any]]:
        dl = DataLoader(dataset, batch_size=2, shuffle=False, num_workers=workers, collate_fn=collate_frames)
        return list(dl)

    inline, parallel = batches(0), batches(2)
    assert len(inline) == len(dataset) // 2
    assert [b["frame_index"].tolist() for b in parallel] == [[0, 1], [2, 0], [1, 2]]
    assert_same(parallel, inline)


def _sample(points: int, boxes: int, frame_index: int) -> dict[str, Any]:
    return {
        "scene_id": "s",
        "frame_index": frame_index,
        "images": torch.zeros(2, 3, 4, 5, dtype=torch.uint8),
        "camera_names": ["A", "B"],
        "lidar_points_ego": torch.zeros(points, 3),
        "boxes_center_world": torch.zeros(boxes, 3, dtype=torch.float64),
        "boxes_track_id": [f"t{i}" for i in range(boxes)],
    }


def test_collate_stacks_equal_shapes_and_keeps_lists_for_variable_sizes() -> None:
    samples = [_sample(10, 2, 0), _sample(7, 2, 1), _sample(12, 0, 2)]
    batch = collate_frames(samples)
    assert batch["images"].shape == (3, 2, 3, 4, 5)
    assert batch["frame_index"].tolist() == [0, 1, 2]
    assert batch["scene_id"] == ["s", "s", "s"]
    assert batch["camera_names"] == [["A", "B"]] * 3
    assert isinstance(batch["lidar_points_ego"], list)
    assert [t.shape[0] for t in batch["lidar_points_ego"]] == [10, 7, 12]
    assert isinstance(batch["boxes_center_world"], list)
    assert [t.shape[0] for t in batch["boxes_center_world"]] == [2, 2, 0]
    assert batch["boxes_track_id"] == [["t0", "t1"], ["t0", "t1"], []]


def test_collate_of_real_samples_stacks_images_and_keeps_lidar_of_different_sizes_as_lists(
    dataset: FrameDataset,
) -> None:
    samples = [dataset[i] for i in range(len(dataset))]
    first = samples[0]
    other = next(s for s in samples if len(s["lidar_points_ego"]) != len(first["lidar_points_ego"]))
    batch = collate_frames([first, other])
    assert torch.equal(batch["images"], torch.stack([first["images"], other["images"]]))
    assert torch.equal(batch["truth_flow"][1], other["truth_flow"])
    assert isinstance(batch["lidar_points_ego"], list)
    assert torch.equal(batch["lidar_points_ego"][1], other["lidar_points_ego"])
    assert batch["boxes_track_id"] == [first["boxes_track_id"], other["boxes_track_id"]]


def test_a_collated_batch_crosses_processes_in_one_buffer_and_arrives_unchanged(tiny_cache: Path) -> None:
    import pickle

    ds = FrameDataset(tiny_cache, fields=FIELD_GROUPS)
    batch = collate_frames([ds[0], ds[1]])
    rebuilt = pickle.loads(pickle.dumps(batch))
    assert_same(dict(rebuilt), dict(batch))
    storages = {
        t.untyped_storage().data_ptr()
        for v in rebuilt.values()
        for t in (v if isinstance(v, list) else [v])
        if isinstance(t, torch.Tensor)
    }
    assert len(storages) == 1


def test_cameras_of_different_sizes_come_as_per_camera_lists(tmp_path: Path) -> None:
    from phigenesis import prep

    args = {**TINY_PREP_ARGS, "scenes": 1, "frames": 1, "uniform_image_size": False}
    prep.synthetic(tmp_path, progress=False, **args)
    sample = FrameDataset(tmp_path, fields=("images", "truth"))[0]
    heights = [t.shape[1] for t in sample["images"]]
    assert isinstance(sample["images"], list) and len(set(heights)) == 2  # Waymo's side cameras are shorter
    for key in ("truth_depth", "truth_semantic", "truth_instance"):
        assert [t.shape[0] for t in sample[key]] == heights
    assert [t.shape[:2] for t in sample["truth_flow"]] == [(3, h) for h in heights]
    frame = CacheReader(tmp_path).frame(0)
    for cam, image, depth in zip(frame.cameras, sample["images"], sample["truth_depth"], strict=True):
        assert np.array_equal(image.numpy().transpose(1, 2, 0), cam.decode_image())
        assert np.array_equal(depth.numpy(), cam.truth.depth_m)


def test_samples_held_while_later_frames_are_decoded_stay_intact(tiny_cache: Path) -> None:
    ds = FrameDataset(tiny_cache, fields=("images", "truth"))
    reference = [FrameDataset(tiny_cache, fields=("images", "truth"))[i] for i in range(len(ds))]
    held = [ds[i] for i in range(len(ds))]  # more than the dataset keeps allocations for
    for _ in range(2):
        for i in range(len(ds)):
            assert_same(ds[i], reference[i], f"frame {i}")
    assert_same(held, reference)
    addresses = {ds[0]["images"].untyped_storage().data_ptr() for _ in range(3)}
    assert len(addresses) == 1  # a freed frame's allocation is reused
    kept = ds[0]
    assert ds[0]["images"].untyped_storage().data_ptr() != kept["images"].untyped_storage().data_ptr()


def test_decoding_on_several_threads_gives_the_same_samples(
    tiny_cache: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(loader, "MIN_THREADED_PIXELS", 0)  # the tiny frames would decode on one thread
    one = FrameDataset(tiny_cache, fields=FIELD_GROUPS, decode_threads=1)
    three = FrameDataset(tiny_cache, fields=FIELD_GROUPS, decode_threads=3)
    for i in range(len(one)):
        assert_same(three[i], one[i], f"frame {i}")


def _camera_fields(images: list[bytes], height: int, width: int) -> dict[str, Any]:
    import pyarrow as pa

    n = len(images)
    return {
        "height": pa.array([height] * n),
        "width": pa.array([width] * n),
        "image": pa.array(images, pa.binary()),
    }


@pytest.mark.parametrize("threads", [1, 2, 3])
def test_an_image_that_does_not_decode_is_named_by_its_camera_on_any_thread_count(
    threads: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    import cv2

    monkeypatch.setattr(loader, "MIN_THREADED_PIXELS", 0)
    good = cv2.imencode(".jpg", np.full((8, 12, 3), 128, np.uint8))[1].tobytes()
    wrong_size = cv2.imencode(".jpg", np.full((8, 10, 3), 128, np.uint8))[1].tobytes()
    jobs = [loader._IMAGE_JOB]
    cf = _camera_fields([good, b"not a jpeg", good, good], 8, 12)
    with pytest.raises(
        ValueError, match=r"^camera B: image holds 10 bytes that are neither a JPEG nor a PNG stream$"
    ):
        loader._decode_maps(cf, ["A", "B", "C", "D"], jobs, loader._Arenas(), threads)
    cf = _camera_fields([good, good, good, wrong_size], 8, 12)
    with pytest.raises(ValueError, match=r"^camera D: image is 10x8, the calibration says 12x8$"):
        loader._decode_maps(cf, ["A", "B", "C", "D"], jobs, loader._Arenas(), threads)
    out = loader._decode_maps(
        _camera_fields([good] * 4, 8, 12), list("ABCD"), jobs, loader._Arenas(), threads
    )
    assert out["images"].shape == (4, 3, 8, 12)
    assert int((out["images"].int() - 128).abs().max()) <= 1


def test_decode_threads_are_checked_and_shared_out_among_workers(tiny_cache: Path) -> None:
    with pytest.raises(ValueError, match="decode_threads must be >= 1"):
        FrameDataset(tiny_cache, decode_threads=0)
    cores = loader.usable_cores()
    assert loader.auto_decode_threads() == min(loader.MAX_DECODE_THREADS, cores)  # not in a worker
    assert loader.auto_decode_threads(num_workers=cores) == 1
    assert loader.auto_decode_threads(num_workers=4 * cores) == 1
