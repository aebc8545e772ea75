"""The SegFormer models and registry, checkpoints, segmentation metrics and the segmenter trainer."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from phigenesis import taxonomy as tx
from phigenesis.cli import train as train_cli
from phigenesis.models import create_model, list_models
from phigenesis.models.checkpoint import load_checkpoint
from phigenesis.models.metrics import confusion_matrix, segmentation_scores
from phigenesis.models.segformer import SegFormerConfig
from phigenesis.train.checkpoint import CheckpointError, save_checkpoint
from phigenesis.train.segmenter import split_by_scene, train_segmenter


@pytest.mark.parametrize("name", list_models("segformer"))
def test_every_registered_variant_maps_images_to_quarter_resolution_logits(name: str) -> None:
    torch.manual_seed(0)
    model = create_model(name).eval()
    assert model.name == name
    with torch.no_grad():
        logits = model(torch.rand(2, 3, 64, 96))
    assert logits.shape == (2, tx.NUM_CLASSES, 16, 24)
    assert torch.isfinite(logits).all()


def test_predict_gives_probabilities_at_the_input_size_for_odd_sizes() -> None:
    model = create_model("segformer_tiny")
    prob = model.predict(torch.randint(0, 255, (1, 3, 61, 91), dtype=torch.uint8))
    assert prob.shape == (1, tx.NUM_CLASSES, 61, 91)
    assert torch.allclose(prob.sum(dim=1), torch.ones(1, 61, 91), atol=1e-5)
    assert model.training  # predict restores the mode


def test_registry_lists_the_variants_and_applies_overrides() -> None:
    assert {"segformer_tiny", "segformer_b0", "segformer_b1"} <= set(list_models())
    model = create_model("segformer_tiny", num_classes=5)
    assert model.config.num_classes == 5 and model(torch.rand(1, 3, 32, 32)).shape[1] == 5
    # MiT-B0's size: 3.7 M parameters (with a 19-class head).
    assert 3.6e6 < create_model("segformer_b0").num_parameters() < 3.8e6
    with pytest.raises(KeyError, match="unknown model 'segformer_b9'"):
        create_model("segformer_b9")


def test_config_rejects_stage_tuples_of_different_lengths_and_indivisible_heads() -> None:
    with pytest.raises(ValueError, match="4 entries"):
        SegFormerConfig(depths=(1, 1, 1))
    with pytest.raises(ValueError, match="divide by their heads"):
        SegFormerConfig(embed_dims=(30, 64, 160, 256), num_heads=(4, 2, 5, 8))


def test_checkpoint_round_trip_gives_the_same_outputs(tmp_path: Path) -> None:
    torch.manual_seed(1)
    model = create_model("segformer_tiny").eval()
    path = save_checkpoint(tmp_path / "m.pt", model, {"note": "x", "miou": 0.5})
    loaded = load_checkpoint(path, "segformer_tiny")
    x = torch.rand(1, 3, 48, 64)
    with torch.no_grad():
        assert torch.equal(model(x), loaded.model(x))
    assert loaded.model_name == "segformer_tiny" and loaded.meta == {"note": "x", "miou": 0.5}
    assert not loaded.model.training


def test_checkpoint_of_another_config_is_a_clear_error(tmp_path: Path) -> None:
    path = save_checkpoint(tmp_path / "m.pt", create_model("segformer_tiny"))
    with pytest.raises(CheckpointError, match=r"model 'segformer_tiny', not 'segformer_b0'.*embed_dims"):
        load_checkpoint(path, "segformer_b0")
    other = save_checkpoint(tmp_path / "five.pt", create_model("segformer_tiny", num_classes=5))
    with pytest.raises(CheckpointError, match=r"config fields differ: num_classes"):
        load_checkpoint(other, "segformer_tiny")
    assert load_checkpoint(other).model.config.num_classes == 5  # without an expectation it loads
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError, match="not a readable checkpoint"):
        load_checkpoint(tmp_path / "junk.pt")


def test_segmentation_scores_count_abstentions_as_misses() -> None:
    truth = np.array([0, 0, 1, 1, 2, 255])
    pred = np.array([0, 1, 1, 255, 0, 2])
    cm = confusion_matrix(pred, truth, num_classes=3)
    assert cm.shape == (3, 4) and cm.sum() == 5
    s = segmentation_scores(cm)
    # class 0: TP 1, FP 1 (the 2 predicted 0), FN 1 -> 1/3; class 1: TP 1, FP 1, FN 1 (abstained) -> 1/3;
    # class 2: TP 0 -> 0.
    assert s.iou == pytest.approx((1 / 3, 1 / 3, 0.0))
    assert s.miou == pytest.approx(2 / 9)
    assert s.pixel_accuracy == pytest.approx(2 / 5) and s.labelled == pytest.approx(4 / 5)
    assert s.labelled_accuracy == pytest.approx(2 / 4)
    assert math.isnan(segmentation_scores(confusion_matrix(pred, truth, num_classes=4)).iou[3])


def test_validation_split_holds_out_whole_scenes() -> None:
    from phigenesis.train.segmenter import LabelledImage

    images = {
        f"s{k}": [LabelledImage(10 * k + i, 0, "truth_semantic_png") for i in range(3)] for k in range(5)
    }
    train, val, _, val_items = split_by_scene(images, 0.4, seed=3)
    assert len(val) == 2 and not set(train) & set(val) and len(train) == 3
    assert {i.frame // 10 for i in val_items} == {int(s[1]) for s in val}
    _, _, train1, val_items1 = split_by_scene({"s0": images["s0"]}, 0.34, seed=0)
    assert [i.frame for i in train1] == [0, 1] and [i.frame for i in val_items1] == [2]


def test_training_on_a_tiny_cache_lowers_the_loss_and_writes_checkpoints(
    tiny_cache: Path, tmp_path: Path
) -> None:
    run = train_segmenter(
        tiny_cache, tmp_path / "run", steps=30, batch_size=4, eval_every=10, lr=3e-3, seed=0
    )
    losses = [r["train_loss"] for r in run.history]
    assert len(losses) == 3 and losses[-1] < 0.7 * losses[0]
    assert len(run.val_scenes) == 1 and not set(run.val_scenes) & set(run.train_scenes)
    assert 0.0 < run.scores["miou"] <= 1.0 and "road" in run.scores["iou"] and run.scores["images"] == 15
    best = load_checkpoint(run.best, "segformer_tiny")
    assert best.meta["val_scenes"] == run.val_scenes and best.meta["training"]["steps"] == 30
    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert [r["step"] for r in metrics["history"]] == [10, 20, 30]


def test_cli_trains_and_reports_the_validation_miou(tiny_cache: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "cli"
    assert train_cli.main(["segmenter", "--shards", str(tiny_cache), "--out", str(out), "--steps", "2"]) == 0
    printed = capsys.readouterr().out
    assert "validation mIoU" in printed and (out / "best.pt").exists()
    code = train_cli.main(
        [
            *("segmenter", "--shards", str(tiny_cache), "--out", str(tmp_path / "b0")),
            *("--config", "segformer_b0", "--steps", "1", "--init", str(out / "best.pt")),
        ]
    )
    assert code == 2 and "not 'segformer_b0'" in capsys.readouterr().err


def _to_hf_layout(model: torch.nn.Module) -> dict[str, torch.Tensor]:
    """Our state dict renamed and reshaped into the Hugging Face SegFormer layout, written out by
    hand (the reference for :func:`load_hf_weights`)."""
    out = {}
    for name, value in model.state_dict().items():
        p = name.split(".")
        if p[0] == "stages" and p[2] == "embed":
            part = "proj" if p[3] == "proj" else "layer_norm"
            out[f"segformer.encoder.patch_embeddings.{p[1]}.{part}.{p[4]}"] = value
        elif p[0] == "stages" and p[2] == "norm":
            out[f"segformer.encoder.layer_norm.{p[1]}.{p[3]}"] = value
        elif p[0] == "stages":
            block = f"segformer.encoder.block.{p[1]}.{p[3]}."
            part = ".".join(p[4:-1])
            if part == "attn.kv":
                key, val = value.chunk(2)
                out[block + f"attention.self.key.{p[-1]}"] = key
                out[block + f"attention.self.value.{p[-1]}"] = val
                continue
            hf = {
                "norm1": "layer_norm_1", "norm2": "layer_norm_2", "attn.q": "attention.self.query",
                "attn.reduce": "attention.self.sr", "attn.reduce_norm": "attention.self.layer_norm",
                "attn.proj": "attention.output.dense", "ffn.fc1": "mlp.dense1",
                "ffn.dwconv": "mlp.dwconv.dwconv", "ffn.fc2": "mlp.dense2",
            }[part]  # fmt: skip
            out[block + f"{hf}.{p[-1]}"] = value
        elif p[1] == "proj":
            out[f"decode_head.linear_c.{p[2]}.proj.{p[3]}"] = value.flatten(1) if value.ndim == 4 else value
        else:
            hf = {"fuse.0": "linear_fuse", "fuse.1": "batch_norm", "classify": "classifier"}[
                ".".join(p[1:-1])
            ]
            out[f"decode_head.{hf}.{p[-1]}"] = value
    return out


def test_hugging_face_layout_weights_load_into_the_same_model(tmp_path: Path) -> None:
    from phigenesis.models.segformer import load_hf_weights

    torch.manual_seed(2)
    source = create_model("segformer_tiny").eval()
    source.decoder.fuse[1].running_mean.uniform_(-1, 1)  # non-trivial BatchNorm statistics
    torch.save(_to_hf_layout(source), tmp_path / "pytorch_model.bin")
    loaded = load_hf_weights(create_model("segformer_tiny"), str(tmp_path / "pytorch_model.bin")).eval()
    x = torch.rand(1, 3, 64, 96)
    with torch.no_grad():
        assert torch.equal(source(x), loaded(x))
    with pytest.raises(ValueError, match="needs"):
        load_hf_weights(create_model("segformer_b0"), str(tmp_path / "pytorch_model.bin"))


def test_hugging_face_weights_that_are_not_a_torch_file_give_one_line_naming_it(tmp_path: Path) -> None:
    from phigenesis.errors import CheckpointError
    from phigenesis.models.segformer import load_hf_weights

    path = tmp_path / "pytorch_model.bin"
    path.write_bytes(b"<html>not the weights</html>")
    with pytest.raises(CheckpointError) as e:
        load_hf_weights(create_model("segformer_tiny"), str(path))
    message = str(e.value)
    assert message.startswith(f"{path}: not a readable checkpoint") and "\n" not in message
    assert "weights_only" not in message
