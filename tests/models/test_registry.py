"""The model registry: any trained model folder loads by its format, with its kind and sequence length."""

from __future__ import annotations

import json

import torch

from seqvpr.models.configs import JistConfig, TransformConfig
from seqvpr.models.cosplace import build_cosplace, save_cosplace
from seqvpr.models.jist import build_jist, save_jist
from seqvpr.models.registry import MODEL_KINDS, load_trained_model, model_kind
from seqvpr.models.seqmatchnet import FrameTransform, save_seqmatchnet
from seqvpr.models.seqnet import save_seqnet
from seqvpr.sequences.descriptors import SeqNet
from tests.helpers import raises_one_line


def test_every_kind_loads_by_its_format(tmp_path):
    transform = FrameTransform(TransformConfig(6), seed=2)
    save_seqmatchnet(tmp_path / "a", transform, {"sequence": {"length": 4}})
    save_seqnet(tmp_path / "b", SeqNet(6, 5, 2), {"sequence": {"length": 7}})
    config = JistConfig(backbone="efficientnet-lite0", out_dim=8, seq_length=3)
    save_jist(tmp_path / "c", build_jist(config), config, {"image_size": [40, 30]})
    encoder = build_cosplace("resnet18", 16)
    save_cosplace(tmp_path / "d", encoder, "resnet18", {"image_size": [48, 32]})
    loaded = [load_trained_model(tmp_path / name) for name in "abcd"]
    assert [(m.kind, m.length) for m in loaded] == [("seqmatchnet", 4), ("seqnet", 7), ("jist", 3), ("cosplace", 1)]
    assert loaded[2].image_size == (40, 30) and loaded[1].module.out_dim == 5 and loaded[3].image_size == (48, 32)
    assert all(torch.equal(loaded[0].module.state_dict()[k], v) for k, v in transform.state_dict().items())
    assert all(torch.equal(loaded[3].module.state_dict()[k], v) for k, v in encoder.state_dict().items())
    assert [model_kind(tmp_path / name).name for name in "abcd"] == list(MODEL_KINDS)


def test_a_cosplace_folder_without_an_image_size_reads_images_at_the_default(tmp_path):
    from seqvpr.models.cosplace import DEFAULT_IMAGE_SIZE

    save_cosplace(tmp_path / "c", build_cosplace("resnet18", 8), "resnet18", {})
    assert load_trained_model(tmp_path / "c").image_size == DEFAULT_IMAGE_SIZE == (512, 384)
    config = {"format": "seqvpr-cosplace", "config": {"backbone": "vgg16", "out_dim": 8}}
    (tmp_path / "c" / "config.json").write_text(json.dumps(config))
    raises_one_line("CosPlace backbone must be one of resnet18, resnet50", load_trained_model, tmp_path / "c")


def test_bad_folders_are_one_line_errors(tmp_path):
    raises_one_line("no such model folder", load_trained_model, tmp_path / "absent")
    (tmp_path / "x").mkdir()
    (tmp_path / "x" / "config.json").write_text('{"format": "someone-elses"}')
    raises_one_line("unknown model format 'someone-elses'", load_trained_model, tmp_path / "x")
    save_seqnet(tmp_path / "s", SeqNet(6, 5, 2), {})
    (tmp_path / "s" / "model.safetensors").write_bytes(b"garbage")
    raises_one_line("model.safetensors: its content is not what", load_trained_model, tmp_path / "s")
