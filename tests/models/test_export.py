"""``seqvpr export`` and ``--descriptor onnx:FILE``: every encoder seqvpr runs, written and read back, gives the
original's descriptors (each built-in backbone, a trained JIST's and CosPlace's frame encoder, JIST's thumbnail
CNN, in each format); a user's ONNX file is checked at load, one line for what seqvpr cannot feed."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from PIL import Image
from torch import nn

from seqvpr.features.engines import TOLERANCE
from seqvpr.features.extraction import ExtractorConfig, build_encoder, build_extractor
from seqvpr.models.export import export_encoder
from tests.helpers import raises_one_line, run_cli

IMAGES = torch.rand(3, 3, 48, 64, generator=torch.Generator().manual_seed(3))


def read_back(path, width=64, height=48, backbone="onnx"):
    return build_encoder(ExtractorConfig(backbone, str(path), width=width, height=height))


@pytest.mark.parametrize("backbone, weights", [("efficientnet-lite0", "imagenet"), ("resnet18", None),
                                               ("resnet50", None)])
def test_a_backbone_written_as_onnx_and_read_back_gives_its_descriptors(tmp_path, backbone, weights):
    torch.manual_seed(0)  # random weights: the same draw for the file and the original
    written = export_encoder(backbone, tmp_path / "e.onnx", "onnx", (64, 48), weights=weights)
    assert (written.width, written.height) == (64, 48) and written.difference <= TOLERANCE
    torch.manual_seed(0)
    original = build_extractor(ExtractorConfig(backbone, weights, width=64, height=48))
    with torch.no_grad():
        assert float((original(IMAGES) - read_back(written.path)(IMAGES)).abs().max()) <= TOLERANCE


@pytest.mark.parametrize("file_format", ["torchscript", "export"])
def test_torchscript_and_torch_export_files_read_back_alike(tmp_path, file_format):
    suffix = {"torchscript": "pt", "export": "pt2"}[file_format]
    written = export_encoder("efficientnet-lite0", tmp_path / f"e.{suffix}", file_format, (64, 48))
    original = build_extractor(ExtractorConfig(width=64, height=48))
    config = ExtractorConfig("torchscript", str(written.path), width=64, height=48, mean=(0, 0, 0), std=(1, 1, 1))
    with torch.no_grad():
        assert float((original(IMAGES) - build_encoder(config)(IMAGES)).abs().max()) <= TOLERANCE


@pytest.mark.parametrize("backbone", ["resnet18", "thumbnail-cnn"])
def test_a_trained_jists_frame_encoder_exports(tmp_path, backbone):
    from seqvpr.models.configs import JistConfig
    from seqvpr.models.jist import build_jist, save_jist
    from seqvpr.models.registry import load_trained_model

    config = JistConfig(backbone=backbone, weights=None, out_dim=16, seq_length=3)
    save_jist(tmp_path / "jist", build_jist(config), config, {"image_size": [64, 48]})
    written = export_encoder(str(tmp_path / "jist"), tmp_path / "j.onnx")
    assert (written.width, written.height, written.dim) == (64, 48, 16)
    encoder = load_trained_model(tmp_path / "jist").module.encoder.eval()
    with torch.no_grad():
        assert float((encoder(IMAGES) - read_back(written.path)(IMAGES)).abs().max()) <= TOLERANCE


def test_the_command_writes_a_file_extract_reads_with_the_same_descriptors(tmp_path, monkeypatch, capsys):
    folder = tmp_path / "images"
    folder.mkdir()
    rng = np.random.default_rng(0)
    for i in range(4):
        Image.fromarray(rng.integers(0, 255, (60, 80, 3), dtype=np.uint8)).save(folder / f"{i}.jpg")
    code, out, err = run_cli(monkeypatch, capsys, "export", "efficientnet-lite0", "--image-size", "64x48", "--out",
                             tmp_path / "l0.onnx")
    assert code == 0 and "[batch, 3, 48, 64] RGB in [0, 1] -> [batch, 1280]" in out, err
    rows = {}
    for name, options in (("torch", ("--descriptor", "efficientnet-lite0", "--image-size", "64x48", "--engine",
                                     "torch")),
                          ("file", ("--descriptor", f"onnx:{tmp_path / 'l0.onnx'}"))):  # its size read from the file
        code, _, err = run_cli(monkeypatch, capsys, "extract", folder, *options, "--out", tmp_path / f"{name}.npz")
        assert code == 0, err
        rows[name] = np.load(tmp_path / f"{name}.npz")["descriptors"]
    assert np.abs(rows["torch"] - rows["file"]).max() <= TOLERANCE


class TwoInputs(nn.Module):
    def forward(self, images, other):
        return images.mean(dim=(2, 3)) + other.mean(dim=(2, 3))


class Counts(nn.Module):
    def forward(self, images):
        return (images.mean(dim=(2, 3)) * 100).long()


def onnx_file(path, module, inputs=1, dynamic_size=False):
    probe = tuple(torch.rand(1, 3, 48, 64) for _ in range(inputs))
    names = [f"x{i}" for i in range(inputs)]
    axes = {name: ({0: "b", 2: "h", 3: "w"} if dynamic_size else {0: "b"}) for name in names}
    torch.onnx.export(module, probe, str(path), input_names=names, dynamic_axes=axes, dynamo=False)
    return path


def test_what_seqvpr_cannot_feed_is_one_line(tmp_path, monkeypatch, capsys):
    from seqvpr.features.engines import load_onnx_encoder

    none = ((0.0,) * 3, (1.0,) * 3)
    two = onnx_file(tmp_path / "two.onnx", TwoInputs(), inputs=2)
    raises_one_line("two.onnx: the model has 2 inputs (x0, x1)", load_onnx_encoder, two, 64, 48, None, none)
    counts = onnx_file(tmp_path / "counts.onnx", Counts())
    raises_one_line("counts.onnx: the model returned int64 [1, 3] for one image; expected float", load_onnx_encoder,
                    counts, 64, 48, None, none)
    fixed = onnx_file(tmp_path / "fixed.onnx", nn.Sequential(nn.AdaptiveAvgPool2d(1), nn.Flatten()))
    raises_one_line("the model takes 64x48 images (width x height), not 32x32: give --image-size 64x48",
                    load_onnx_encoder, fixed, 32, 32, None, none)
    (tmp_path / "cut.onnx").write_bytes(fixed.read_bytes()[:40])
    raises_one_line("cut.onnx: not an ONNX model ONNX Runtime can run", load_onnx_encoder, tmp_path / "cut.onnx", 64,
                    48, None, none)
    free = onnx_file(tmp_path / "free.onnx", nn.Sequential(nn.AdaptiveAvgPool2d(1), nn.Flatten()), dynamic_size=True)
    (tmp_path / "imgs").mkdir()
    Image.new("RGB", (8, 6)).save(tmp_path / "imgs" / "0.png")
    code, _, err = run_cli(monkeypatch, capsys, "extract", tmp_path / "imgs", "--descriptor", f"onnx:{free}", "--out",
                           tmp_path / "o.npz")
    assert code == 2 and "input size is not fixed; give --image-size WxH" in err and err.count("\n") == 1, err
    code, _, err = run_cli(monkeypatch, capsys, "export", str(tmp_path), "--out", tmp_path / "x.onnx")
    assert code == 2 and err.count("\n") == 1 and not (tmp_path / "x.onnx").exists(), err
    (tmp_path / "mine.npz").write_bytes(b"a user's file")
    code, _, err = run_cli(monkeypatch, capsys, "export", "efficientnet-lite0", "--out", tmp_path / "mine.npz")
    assert code == 2 and "onnx files are named .onnx" in err and (tmp_path / "mine.npz").read_bytes() == b"a user's file"


@pytest.mark.parametrize("arguments, fragment", [
    ({"image_size": "320x240"}, "image_size must be (width, height)"),
    ({"image_size": (0, 48)}, "image_size must be an integer in [1, inf]"),
    ({"pooling": "netvlad"}, "pooling must be one of 'gem'"),
    ({"format": "tensorrt"}, "format must be one of 'onnx', 'torchscript', 'export'"),
    ({"out": 3}, "out must be a path"),
    ({"source": "nope"}, "nope"),
])
def test_bad_arguments_from_python_are_one_line(tmp_path, arguments, fragment):
    given = {"source": "efficientnet-lite0", "out": tmp_path / "e.onnx", **arguments}
    raises_one_line(fragment, export_encoder, **given)
    assert not (tmp_path / "e.onnx").exists()


def test_an_export_that_differs_from_torch_replaces_nothing(tmp_path, monkeypatch):
    from seqvpr.features import engines

    (tmp_path / "e.onnx").write_bytes(b"the user's earlier export")
    monkeypatch.setattr(engines, "probe_difference", lambda *args: 0.5)
    raises_one_line("e.onnx: the exported encoder differs from torch by 0.5", export_encoder, "efficientnet-lite0",
                    tmp_path / "e.onnx", image_size=(64, 48))
    assert (tmp_path / "e.onnx").read_bytes() == b"the user's earlier export"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["e.onnx"]
