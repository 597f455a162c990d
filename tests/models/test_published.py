"""Published SeqNet and SeqMatchNet checkpoints, built here with the reference codes' exact keys (random values):
strict conversion, containers with numpy scalars, prefixes, and upstream's forward against a plain re-computation."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from seqvpr.models.published import import_checkpoint
from seqvpr.models.registry import load_trained_model
from tests.helpers import raises_one_line, run_cli


def training_container(state: dict, prefix: str = "module.") -> dict:
    """What the reference codes' ``checkpoint.pth.tar`` holds: numpy float64 scalars beside the state dict."""
    return {"epoch": 7, "state_dict": {prefix + k: v for k, v in state.items()},
            "recalls": {1: np.float64(0.5), 5: np.float64(0.75)}, "best_score": np.float64(0.75),
            "optimizer": {}, "parallel": False}


@pytest.fixture
def seqnet_file(tmp_path):
    generator = torch.Generator().manual_seed(0)
    state = {"pool.0.conv.weight": torch.randn(6, 8, 3, generator=generator),
             "pool.0.conv.bias": torch.randn(6, generator=generator)}
    torch.save(training_container(state), tmp_path / "model_best.pth.tar")
    (tmp_path / "flags.json").write_text(json.dumps({"seqL": 5, "w": 3, "outDims": 6, "pooling": "seqnet"}))
    return tmp_path / "model_best.pth.tar", tmp_path / "flags.json", state


def test_seqnet_checkpoint_runs_with_upstreams_forward(seqnet_file, tmp_path):
    path, flags, state = seqnet_file
    imported = import_checkpoint(path, tmp_path / "out", flags)
    model = load_trained_model(imported.folder)
    assert (model.kind, model.length) == ("seqnet", 5)
    config = json.loads((imported.folder / "config.json").read_text())
    assert config["source"]["sha256"] == imported.sha256 and len(imported.sha256) == 64
    windows = torch.randn(4, 5, 8, generator=torch.Generator().manual_seed(1))
    plain = torch.nn.functional.conv1d(windows.transpose(1, 2), state["pool.0.conv.weight"], state["pool.0.conv.bias"])
    expected = torch.nn.functional.normalize(plain.mean(dim=2), dim=1)  # [B, C, T] -> conv -> mean over T-w+1 -> L2
    with torch.no_grad():
        torch.testing.assert_close(model.module(windows), expected, atol=1e-5, rtol=1e-5)


def test_seqmatchnet_checkpoint_is_the_per_frame_transform(tmp_path):
    generator = torch.Generator().manual_seed(2)
    state = {"pool.1.conv.weight": torch.randn(5, 8, 1, generator=generator),
             "pool.1.conv.bias": torch.randn(5, generator=generator)}
    on_several_gpus = {k.replace("pool.", "pool.module."): v for k, v in state.items()}  # pool.module.1.conv.*
    torch.save(training_container(on_several_gpus, prefix=""), tmp_path / "smn.pth.tar")
    model = load_trained_model(import_checkpoint(tmp_path / "smn.pth.tar", tmp_path / "out").folder)
    frames = torch.randn(7, 8, generator=torch.Generator().manual_seed(3)) * 3
    weight, bias = state["pool.1.conv.weight"][:, :, 0], state["pool.1.conv.bias"]
    with torch.no_grad():  # upstream: normalize(W x + B), the input as it is
        torch.testing.assert_close(model.module(frames), torch.nn.functional.normalize(frames @ weight.T + bias, dim=1),
                                   atol=1e-5, rtol=1e-5)
    raw = tmp_path / "raw.pth"
    torch.save(state, raw)  # a raw state dict converts too
    assert load_trained_model(import_checkpoint(raw, tmp_path / "raw").folder).kind == "seqmatchnet"


def test_a_missing_or_unexpected_key_or_wrong_flag_is_a_one_line_error(seqnet_file, tmp_path):
    path, flags, state = seqnet_file
    extra = tmp_path / "extra.pth"
    torch.save({**state, "pool.0.conv.scale": torch.ones(1)}, extra)
    raises_one_line("unexpected key 'pool.0.conv.scale'", import_checkpoint, extra, tmp_path / "a")
    missing = tmp_path / "missing.pth"
    torch.save({"pool.0.conv.weight": state["pool.0.conv.weight"]}, missing)
    raises_one_line("missing key 'pool.0.conv.bias'", import_checkpoint, missing, tmp_path / "b")
    (tmp_path / "bad.json").write_text(json.dumps({"w": 5}))
    raises_one_line("w = 5 but", import_checkpoint, path, tmp_path / "c", tmp_path / "bad.json")
    cosplace = tmp_path / "cosplace.pth"
    torch.save({"aggregation.3.weight": torch.ones(2, 2)}, cosplace)
    raises_one_line("CosPlace checkpoint; importing CosPlace files is not available yet", import_checkpoint, cosplace,
                    tmp_path / "d")
    (tmp_path / "junk.pth").write_bytes(b"not a checkpoint")
    raises_one_line("not a loadable checkpoint", import_checkpoint, tmp_path / "junk.pth", tmp_path / "e")
    assert not any((tmp_path / name).exists() for name in "abcde")


def test_command_line_import_then_match(monkeypatch, capsys, seqnet_file, tmp_path):
    path, flags, _ = seqnet_file
    code, stdout, stderr = run_cli(monkeypatch, capsys, "import", path, "--flags", flags, "--out", tmp_path / "m")
    assert code == 0 and stdout.startswith("seqnet model:"), stderr
    from seqvpr.data.sources import save_traversal_npz
    from seqvpr.data.traversal import Traversal

    rng = np.random.default_rng(0)
    for name in ("ref", "qry"):
        save_traversal_npz(tmp_path / f"{name}.npz", Traversal.from_descriptors(rng.normal(size=(20, 8)), name))
    code, stdout, stderr = run_cli(monkeypatch, capsys, "match", "-r", tmp_path / "ref.npz", "-q", tmp_path / "qry.npz",
                                   "--radius", "1f", "--model", tmp_path / "m", "--json", "--out", tmp_path / "o")
    assert code == 0 and json.loads(stdout)["settings"]["sequence"]["length"] == 5, stderr
    code, _, stderr = run_cli(monkeypatch, capsys, "import", tmp_path / "absent.pth", "--out", tmp_path / "x")
    assert code == 2 and "no such checkpoint file" in stderr and stderr.count("\n") == 1


def upstream_jist_state(seed: int = 0) -> dict[str, torch.Tensor]:
    """A JIST ``best_model.pth`` with the exact upstream keys: CosPlace's under ``model.`` plus ``seq_gem.p``."""
    from seqvpr.features.backbones import COSPLACE_CHILDREN, ResNet

    torch.manual_seed(seed)
    children = {v: k for k, v in COSPLACE_CHILDREN.items()}
    state = {}
    for key, value in ResNet(18).state_dict().items():
        child, _, rest = key.partition(".")
        state[f"model.backbone.{children[child]}.{rest}"] = value + 0.01 * torch.randn_like(value.float()).to(value.dtype)
    state["model.aggregation.1.p"] = torch.tensor([3.2])
    state["model.aggregation.3.weight"] = torch.randn(512, 512) / 20
    state["model.aggregation.3.bias"] = torch.randn(512) / 20
    state["seq_gem.p"] = torch.tensor([2.7])
    return state


def test_jist_checkpoint_with_the_upstream_keys_converts_exactly(tmp_path):
    state = upstream_jist_state()
    assert len(state) == 124
    torch.save(state, tmp_path / "JIST_r18_512_seqgem.pth")
    model = load_trained_model(import_checkpoint(tmp_path / "JIST_r18_512_seqgem.pth", tmp_path / "jist").folder)
    assert (model.kind, model.length, model.image_size) == ("jist", 5, (640, 480))
    ours = model.module.state_dict()
    assert torch.equal(ours["encoder.backbone.layer4.1.conv2.weight"], state["model.backbone.7.1.conv2.weight"])
    assert torch.equal(ours["encoder.backbone.bn1.running_var"], state["model.backbone.1.running_var"])
    assert torch.equal(ours["encoder.fc.weight"], state["model.aggregation.3.weight"])
    assert float(ours["encoder.gem.p"]) == pytest.approx(3.2) and float(ours["sequence_pool.p"]) == pytest.approx(2.7)
    frames = torch.rand(3, 5, 512, generator=torch.Generator().manual_seed(4))
    plain = frames.clamp(min=1e-6).pow(2.7).mean(dim=1).pow(1 / 2.7)  # upstream SeqGeM: no final L2
    with torch.no_grad():
        torch.testing.assert_close(model.module.pool(frames), plain, atol=1e-5, rtol=1e-5)
        images = torch.rand(2, 3, 64, 96, generator=torch.Generator().manual_seed(5))
        local = model.module.encoder.backbone.features((images - model.module.encoder.mean) / model.module.encoder.std)
        gem = torch.nn.functional.normalize(local, dim=1).clamp(min=1e-6).pow(3.2).mean((2, 3)).pow(1 / 3.2)
        head = torch.nn.functional.normalize(gem @ state["model.aggregation.3.weight"].T
                                             + state["model.aggregation.3.bias"], dim=1)
        torch.testing.assert_close(model.module.frames(images), head, atol=1e-5, rtol=1e-5)


def test_jist_checkpoint_missing_or_extra_key_is_named(tmp_path):
    state = upstream_jist_state()
    less = dict(state)
    del less["model.backbone.4.0.bn1.weight"]
    torch.save(less, tmp_path / "less.pth")
    raises_one_line("missing key 'model.backbone.4.0.bn1.weight'", import_checkpoint, tmp_path / "less.pth",
                    tmp_path / "a")
    torch.save({**state, "model.aggregation.4.weight": torch.ones(3)}, tmp_path / "more.pth")
    raises_one_line("unexpected key 'model.aggregation.4.weight'", import_checkpoint, tmp_path / "more.pth",
                    tmp_path / "b")
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()
