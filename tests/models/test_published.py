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
