"""A user's own encoder (``--descriptor torchscript:PATH``): a scripted or exported model gives through
``seqvpr extract`` and ``seqvpr match`` the descriptors that calling it directly gives; normalisation, caching and
bad files."""

import json
import os
from dataclasses import replace

import numpy as np
import pytest
import torch
from PIL import Image
from torch import nn

from seqvpr.features.extraction import (
    IMAGENET_MEAN,
    IMAGENET_STD,
    ExtractorConfig,
    build_encoder,
    cache_key,
    extract_descriptors,
)
from seqvpr.features.torchscript import load_encoder
from seqvpr.features.describe import descriptor_config
from tests.helpers import raises_one_line, run_cli

W, H = 64, 48
pytestmark = pytest.mark.filterwarnings("ignore:`torch.jit.script` is deprecated:DeprecationWarning")


class Encoder(nn.Module):
    """Convolution, mean-pool over a flattened map (a ``view``: it needs a contiguous batch), linear: [B, 16]."""

    def __init__(self, seed: int = 0) -> None:
        super().__init__()
        torch.manual_seed(seed)
        self.conv = nn.Conv2d(3, 8, 3, stride=2)
        self.fc = nn.Linear(8, 16)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        features = torch.relu(self.conv(x))
        return self.fc(features.view(features.shape[0], features.shape[1], -1).mean(dim=2))


class FeatureMap(nn.Module):
    """An encoder that forgot to pool: [B, 8, h, w]."""

    def __init__(self) -> None:
        super().__init__()
        self.conv = nn.Conv2d(3, 8, 3)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.conv(x)


def scripted(path, module: nn.Module | None = None):
    """``module`` (default ``Encoder()``) scripted and saved at ``path``; returns the scripted module."""
    model = torch.jit.script((module or Encoder()).eval())
    model.save(str(path))
    return model


def exported(path, dynamic_batch: bool = True):
    """``Encoder()`` exported with ``torch.export`` (batch dimension dynamic unless told not) and saved at
    ``path``; returns the eager module."""
    model = Encoder().eval()
    shapes = {"x": {0: torch.export.Dim("batch", min=1)}} if dynamic_batch else None
    torch.export.save(torch.export.export(model, (torch.rand(2, 3, H, W),), dynamic_shapes=shapes), str(path))
    return model


@pytest.fixture
def images(tmp_path):
    rng = np.random.default_rng(0)
    folder = tmp_path / "images"
    folder.mkdir()
    for i in range(7):
        Image.fromarray(rng.integers(0, 255, size=(30, 40, 3), dtype=np.uint8)).save(folder / f"{i:03d}.png")
    return sorted(folder.glob("*.png"))


def direct(model, paths, mean=IMAGENET_MEAN, std=IMAGENET_STD) -> np.ndarray:
    """The model called on the images resized to W x H (bilinear), scaled to [0, 1] and normalised."""
    pixels = [np.asarray(Image.open(p).convert("RGB").resize((W, H), Image.BILINEAR), np.float32) / 255 for p in paths]
    batch = torch.from_numpy(np.stack(pixels)).permute(0, 3, 1, 2)
    batch = (batch - torch.tensor(mean).view(1, 3, 1, 1)) / torch.tensor(std).view(1, 3, 1, 1)
    with torch.no_grad():
        return model(batch).numpy()


def extract(monkeypatch, capsys, folder, model_file, out, *options):
    """``seqvpr extract`` with the model file; (exit status, stdout, stderr)."""
    return run_cli(monkeypatch, capsys, "extract", folder, "--descriptor", f"torchscript:{model_file}",
                   "--image-size", f"{W}x{H}", "--batch-size", "3", "--out", out, *options)


def test_extract_gives_the_scripted_models_own_descriptors(monkeypatch, capsys, tmp_path, images):
    model = scripted(tmp_path / "encoder.pt")
    code, stdout, err = extract(monkeypatch, capsys, images[0].parent, tmp_path / "encoder.pt", tmp_path / "x.npz")
    assert code == 0, err
    assert "7 frames, 16-D" in stdout
    with np.load(tmp_path / "x.npz") as saved:
        assert np.allclose(saved["descriptors"], direct(model, images), atol=1e-5)


def test_extract_gives_the_exported_programs_own_descriptors(monkeypatch, capsys, tmp_path, images):
    model = exported(tmp_path / "encoder.pt2")
    mean, std = (0.5, 0.4, 0.3), (0.2, 0.25, 0.3)
    code, _, err = extract(monkeypatch, capsys, images[0].parent, tmp_path / "encoder.pt2", tmp_path / "x.npz",
                           "--normalize", "0.5,0.4,0.3/0.2,0.25,0.3")
    assert code == 0, err
    with np.load(tmp_path / "x.npz") as saved:
        assert np.allclose(saved["descriptors"], direct(model, images, mean, std), atol=1e-5)


def test_the_default_normalization_is_imagenets_and_none_feeds_pixels_in_0_1(tmp_path, images):
    model = scripted(tmp_path / "encoder.pt")
    config = descriptor_config(f"torchscript:{tmp_path / 'encoder.pt'}", ExtractorConfig(width=W, height=H))
    assert np.allclose(extract_descriptors(images, config).descriptors, direct(model, images), atol=1e-5)
    plain = replace(config, mean=(0.0, 0.0, 0.0), std=(1.0, 1.0, 1.0))
    expected = direct(model, images, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0))
    assert np.allclose(extract_descriptors(images, plain).descriptors, expected, atol=1e-5)


def test_descriptors_are_kept_as_the_model_returns_them(tmp_path, images):
    scripted(tmp_path / "encoder.pt")
    config = ExtractorConfig("torchscript", str(tmp_path / "encoder.pt"), width=W, height=H)
    norms = np.linalg.norm(extract_descriptors(images, config).descriptors, axis=1)
    assert not np.allclose(norms, 1.0)  # not L2-normalised here; matching does that unless --no-normalize


def test_match_with_a_torchscript_encoder_finds_each_frame_itself(monkeypatch, capsys, tmp_path, images):
    scripted(tmp_path / "encoder.pt")
    folder = images[0].parent
    code, stdout, err = run_cli(monkeypatch, capsys, "match", "-r", folder, "-q", folder, "--radius", "0f",
                                "--descriptor", f"torchscript:{tmp_path / 'encoder.pt'}", "--image-size", f"{W}x{H}",
                                "--json", "--out", tmp_path / "m")
    assert code == 0, err
    result = json.loads(stdout)
    assert result["recall"]["1"] == 1.0
    assert result["settings"]["descriptor"] == f"torchscript:{tmp_path / 'encoder.pt'}"
    assert result["settings"]["image_normalization"] == "imagenet"  # --normalize (not the match's L2 switch)


@pytest.mark.parametrize("case", ["missing", "not a model", "state dict", "bogus name", "weights", "normalize",
                                  "bad normalize", "netvlad"])
def test_bad_encoder_options_are_one_line(monkeypatch, capsys, tmp_path, images, case):
    scripted(tmp_path / "encoder.pt")
    torch.save(Encoder().state_dict(), tmp_path / "state.pt")
    good = f"torchscript:{tmp_path / 'encoder.pt'}"
    args, needle = {
        "missing": (["--descriptor", f"torchscript:{tmp_path / 'gone.pt'}"], "gone.pt: no such model file"),
        "not a model": (["--descriptor", f"torchscript:{images[0]}"], "000.png: not a TorchScript or torch.export"),
        "state dict": (["--descriptor", f"torchscript:{tmp_path / 'state.pt'}"], "a state dict or pickled model"),
        "bogus name": (["--descriptor", "megaloc"], "torchscript:PATH"),
        "weights": (["--descriptor", good, "--weights", "x.pth"], "--weights does not apply"),
        "normalize": (["--descriptor", "resnet18", "--normalize", "none"], "--normalize applies to torchscript"),
        "bad normalize": (["--descriptor", good, "--normalize", "0.5/0.5"], "--normalize '0.5/0.5'"),
        "netvlad": (["--descriptor", good, "--pooling", "netvlad"], "pooling 'netvlad' does not apply"),
    }[case]
    out = tmp_path / "x.npz"
    code, _, err = run_cli(monkeypatch, capsys, "extract", images[0].parent, *args, "--out", out)
    assert code == 2 and not out.exists()
    assert err.startswith("seqvpr: error:") and err.count("\n") == 1 and needle in err, err


def test_an_encoder_returning_a_feature_map_is_a_clear_error(tmp_path, images):
    scripted(tmp_path / "map.pt", FeatureMap())
    config = ExtractorConfig("torchscript", str(tmp_path / "map.pt"), width=W, height=H)
    message = raises_one_line("map.pt: the encoder returned shape [2, 8, 46, 62]", extract_descriptors, images, config)
    assert "expected [batch, dim]" in message


def test_an_export_for_another_input_size_is_a_one_line_error(tmp_path, images):
    exported(tmp_path / "encoder.pt2")
    config = ExtractorConfig("torchscript", str(tmp_path / "encoder.pt2"), width=32, height=24)
    raises_one_line("encoder.pt2: the encoder failed on a batch of shape [2, 3, 24, 32]", extract_descriptors,
                    images, config)


def test_the_cache_is_keyed_by_the_model_file_and_the_normalization(tmp_path, images):
    path = tmp_path / "encoder.pt"
    scripted(path)
    config = ExtractorConfig("torchscript", str(path), width=W, height=H, batch_size=3)
    cache = tmp_path / "cache"
    first = extract_descriptors(images, config, cache_dir=cache)
    assert extract_descriptors(images, config, cache_dir=cache).cache_file == first.cache_file
    explicit = ExtractorConfig("torchscript", str(path), width=W, height=H, mean=IMAGENET_MEAN, std=IMAGENET_STD)
    assert cache_key(explicit, images) == cache_key(config, images)  # the default is ImageNet's, spelled or not
    other = ExtractorConfig("torchscript", str(path), width=W, height=H, mean=(0, 0, 0), std=(1, 1, 1))
    assert cache_key(other, images) != cache_key(config, images)
    before = cache_key(config, images)
    new = scripted(path, Encoder(seed=1))  # the same path, another model
    os.utime(path, ns=(1, 1))
    assert cache_key(config, images) != before
    again = extract_descriptors(images, config, cache_dir=cache)
    assert again.cache_file != first.cache_file
    assert np.allclose(again.descriptors, direct(new, images), atol=1e-5)


def test_the_loader_reads_both_formats_and_the_config_checks_its_fields(tmp_path):
    scripted(tmp_path / "a.pt")
    exported(tmp_path / "b.pt2")
    batch = torch.rand(3, 3, H, W)
    for name in ("a.pt", "b.pt2"):
        encoder = load_encoder(tmp_path / name, IMAGENET_MEAN, IMAGENET_STD).eval()
        assert encoder(batch).shape == (3, 16)
    encoder = build_encoder(ExtractorConfig("torchscript", str(tmp_path / "a.pt"), width=W, height=H))
    assert encoder.source == str(tmp_path / "a.pt")
    raises_one_line("needs its model file", ExtractorConfig, "torchscript", "imagenet")
    raises_one_line("mean/std apply to an encoder file only", ExtractorConfig, mean=(0, 0, 0), std=(1, 1, 1))
    raises_one_line("std must be positive", ExtractorConfig, "torchscript", "a.pt", std=(1, 0, 1))
    raises_one_line("descriptor 'vgg' is not known", descriptor_config, "vgg", ExtractorConfig())
