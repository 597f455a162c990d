"""Published SeqNet, SeqMatchNet, CosPlace and JIST checkpoints, built here with the reference codes' exact keys
(random values): strict conversion, containers with numpy scalars, prefixes, and upstream's forward against a plain
re-computation."""

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
    raises_one_line("aggregation.3.weight has shape (2, 2); expected [dim, 512] (ResNet-18) or [dim, 2048]",
                    import_checkpoint, cosplace, tmp_path / "d")
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


def upstream_cosplace_state(seed: int = 0, out_dim: int = 512) -> dict[str, torch.Tensor]:
    """A ResNet-18 ``*_cosplace.pth`` with exactly upstream's keys and shapes, written out here (not taken from
    seqvpr): ``backbone.0`` conv1, ``backbone.1`` bn1, ``backbone.4..7`` layer1..4, ``aggregation.1.p`` (GeM),
    ``aggregation.3.*`` (Linear)."""
    generator = torch.Generator().manual_seed(seed)
    state: dict[str, torch.Tensor] = {}

    def conv(key: str, out: int, inp: int, size: int) -> None:
        state[key] = torch.randn(out, inp, size, size, generator=generator) * (2 / (inp * size * size)) ** 0.5

    def norm(key: str, channels: int) -> None:
        state[f"{key}.weight"] = 1 + 0.1 * torch.randn(channels, generator=generator)
        state[f"{key}.bias"] = 0.1 * torch.randn(channels, generator=generator)
        state[f"{key}.running_mean"] = 0.1 * torch.randn(channels, generator=generator)
        state[f"{key}.running_var"] = 0.5 + torch.rand(channels, generator=generator)
        state[f"{key}.num_batches_tracked"] = torch.tensor(1000)

    conv("backbone.0.weight", 64, 3, 7)
    norm("backbone.1", 64)
    channels = 64
    for layer, width in zip(range(4, 8), (64, 128, 256, 512)):
        for block in range(2):
            prefix = f"backbone.{layer}.{block}"
            conv(f"{prefix}.conv1.weight", width, channels, 3)
            norm(f"{prefix}.bn1", width)
            conv(f"{prefix}.conv2.weight", width, width, 3)
            norm(f"{prefix}.bn2", width)
            if block == 0 and layer > 4:
                conv(f"{prefix}.downsample.0.weight", width, channels, 1)
                norm(f"{prefix}.downsample.1", width)
            channels = width
    state["aggregation.1.p"] = torch.tensor([3.2])
    state["aggregation.3.weight"] = torch.randn(out_dim, 512, generator=generator) / 20
    state["aggregation.3.bias"] = torch.randn(out_dim, generator=generator) / 20
    return state


def plain_cosplace(state: dict[str, torch.Tensor], images: torch.Tensor) -> torch.Tensor:
    """Upstream CosPlace's forward on a ResNet-18 state dict, in torch.nn.functional only: ImageNet normalisation,
    the ResNet, channel L2, GeM (avg_pool2d of clamp^p, ^1/p), Linear, L2."""
    F = torch.nn.functional

    def norm(x, key):
        return F.batch_norm(x, state[f"{key}.running_mean"], state[f"{key}.running_var"], state[f"{key}.weight"],
                            state[f"{key}.bias"], False, 0.0, 1e-5)

    mean, std = torch.tensor([0.485, 0.456, 0.406]), torch.tensor([0.229, 0.224, 0.225])
    x = (images - mean.view(1, 3, 1, 1)) / std.view(1, 3, 1, 1)
    x = F.max_pool2d(F.relu(norm(F.conv2d(x, state["backbone.0.weight"], stride=2, padding=3), "backbone.1")), 3, 2, 1)
    for layer in range(4, 8):
        for block in range(2):
            prefix, stride = f"backbone.{layer}.{block}", 2 if layer > 4 and block == 0 else 1
            out = F.relu(norm(F.conv2d(x, state[f"{prefix}.conv1.weight"], stride=stride, padding=1), f"{prefix}.bn1"))
            out = norm(F.conv2d(out, state[f"{prefix}.conv2.weight"], padding=1), f"{prefix}.bn2")
            if f"{prefix}.downsample.0.weight" in state:
                x = norm(F.conv2d(x, state[f"{prefix}.downsample.0.weight"], stride=stride), f"{prefix}.downsample.1")
            x = F.relu(out + x)
    x, p = F.normalize(x, dim=1), state["aggregation.1.p"]
    x = F.avg_pool2d(x.clamp(min=1e-6).pow(p), (x.size(-2), x.size(-1))).pow(1.0 / p).flatten(1)
    return F.normalize(F.linear(x, state["aggregation.3.weight"], state["aggregation.3.bias"]), dim=1)


def image_folder(folder, count: int, width: int, height: int, seed: int):
    """An image folder traversal (PNGs of exactly width x height, positions 2 m apart)."""
    from PIL import Image

    folder.mkdir()
    rng = np.random.default_rng(seed)
    rows = ["name,easting,northing"]
    for i in range(count):
        Image.fromarray(rng.integers(0, 255, (height, width, 3), dtype=np.uint8)).save(folder / f"{i:03d}.png")
        rows.append(f"{i:03d}.png,{2.0 * i},0")
    (folder / "positions.csv").write_text("\n".join(rows) + "\n")
    return folder


def plain_descriptors(state: dict[str, torch.Tensor], folder) -> torch.Tensor:
    """The plain forward on the folder's PNGs as they are (read with PIL, scaled to [0, 1])."""
    from PIL import Image

    paths = sorted(folder.glob("*.png"))
    images = [np.asarray(Image.open(path).convert("RGB"), dtype=np.float32) / 255 for path in paths]
    with torch.no_grad():
        return plain_cosplace(state, torch.from_numpy(np.stack(images)).permute(0, 3, 1, 2))


@pytest.mark.slow
def test_cosplace_raw_state_dict_describes_images_as_upstream(tmp_path):
    from seqvpr.data.sources import load_traversal
    from seqvpr.methods import describe_for_models

    state = upstream_cosplace_state()
    assert len(state) == 123
    torch.save(state, tmp_path / "resnet18_512_cosplace.pth")
    imported = import_checkpoint(tmp_path / "resnet18_512_cosplace.pth", tmp_path / "cosplace")
    config = json.loads((imported.folder / "config.json").read_text())
    assert imported.kind == "cosplace" and config["source"]["sha256"] == imported.sha256
    assert config["source"]["file"].endswith("resnet18_512_cosplace.pth") and config["config"]["backbone"] == "resnet18"
    model = load_trained_model(imported.folder)
    assert (model.kind, model.length, model.image_size) == ("cosplace", 1, (512, 384))
    images = load_traversal(image_folder(tmp_path / "images", 3, 512, 384, seed=1), "reference")
    described, _ = describe_for_models(images, images, {"cosplace": model}, None)  # at the folder's 512 x 384
    plain = plain_descriptors(state, tmp_path / "images")
    np.testing.assert_allclose(described.descriptors, plain.numpy(), atol=1e-5, rtol=0)
    np.testing.assert_allclose(np.linalg.norm(described.descriptors, axis=1), 1, atol=1e-6)


def test_cosplace_training_checkpoint_and_dataparallel_prefix_load(tmp_path):
    state = upstream_cosplace_state(seed=3, out_dim=64)
    checkpoint = {"epoch_num": 4, "model_state_dict": {f"module.{k}": v for k, v in state.items()},
                  "optimizer_state_dict": {"state": {}, "param_groups": [{"lr": 1e-5, "params": [0, 1]}]},
                  "classifiers_state_dict": [{"weight": torch.randn(10, 64)}],
                  "optimizers_classifiers_state_dict": [{"state": {}, "param_groups": []}], "best_val_recall1": 55.5}
    torch.save(checkpoint, tmp_path / "last_checkpoint.pth")
    model = load_trained_model(import_checkpoint(tmp_path / "last_checkpoint.pth", tmp_path / "out").folder)
    assert model.kind == "cosplace" and model.module.out_dim == 64
    images = torch.rand(2, 3, 64, 96, generator=torch.Generator().manual_seed(2))
    with torch.no_grad():
        torch.testing.assert_close(model.module(images), plain_cosplace(state, images), atol=1e-5, rtol=1e-5)


@pytest.mark.slow
def test_cosplace_missing_extra_or_misshapen_key_is_named(tmp_path):
    state = upstream_cosplace_state()
    cases = {
        "less": ({k: v for k, v in state.items() if k != "backbone.5.0.downsample.1.running_var"},
                 "missing key 'backbone.5.0.downsample.1.running_var'"),
        "no_p": ({k: v for k, v in state.items() if k != "aggregation.1.p"}, "missing key 'aggregation.1.p'"),
        "more": ({**state, "aggregation.5.weight": torch.ones(3)}, "unexpected key 'aggregation.5.weight'"),
        "fc": ({**state, "backbone.8.weight": torch.ones(3)}, "unexpected key 'backbone.8.weight'"),
        "bias": ({**state, "aggregation.3.bias": torch.ones(256)},
                 "aggregation.3.bias has shape (256,), the model needs (512,)"),
        "head": ({**state, "aggregation.3.weight": torch.ones(512, 300)}, "aggregation.3.weight has shape (512, 300)"),
        "r50": ({**state, "aggregation.3.weight": torch.ones(128, 2048), "aggregation.3.bias": torch.ones(128)},
                "backbone.4.0.conv1.weight has shape (64, 64, 3, 3), the model needs (64, 64, 1, 1)"),
    }
    for name, (content, needle) in cases.items():
        torch.save(content, tmp_path / f"{name}.pth")
        message = raises_one_line(needle, import_checkpoint, tmp_path / f"{name}.pth", tmp_path / f"out-{name}")
        assert message.startswith(f"{tmp_path / name}.pth: ")
        assert not (tmp_path / f"out-{name}").exists()


def test_cosplace_resnet50_by_the_head_input(tmp_path):
    from seqvpr.features.backbones import COSPLACE_CHILDREN, ResNet

    children = {v: k for k, v in COSPLACE_CHILDREN.items()}
    state = {f"backbone.{children[k.split('.')[0]]}.{k.partition('.')[2]}": v
             for k, v in ResNet(50).state_dict().items()}
    state.update({"aggregation.1.p": torch.tensor([3.0]), "aggregation.3.weight": torch.randn(128, 2048),
                  "aggregation.3.bias": torch.randn(128)})
    torch.save(state, tmp_path / "resnet50_128_cosplace.pth")
    model = load_trained_model(import_checkpoint(tmp_path / "resnet50_128_cosplace.pth", tmp_path / "r50").folder)
    assert model.module.out_dim == 128 and model.module.backbone.out_channels == 2048
    assert torch.equal(model.module.state_dict()["backbone.layer3.5.conv3.weight"], state["backbone.6.5.conv3.weight"])


def upstream_jist_state(seed: int = 0) -> dict[str, torch.Tensor]:
    """A JIST ``best_model.pth`` with the exact upstream keys: CosPlace's under ``model.`` plus ``seq_gem.p``."""
    state = {f"model.{k}": v for k, v in upstream_cosplace_state(seed).items()}
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
        cosplace = {k.removeprefix("model."): v for k, v in state.items() if k.startswith("model.")}
        torch.testing.assert_close(model.module.frames(images), plain_cosplace(cosplace, images), atol=1e-5, rtol=1e-5)


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
    torch.save({k: v for k, v in state.items() if k != "seq_gem.p"}, tmp_path / "nopool.pth")
    raises_one_line("a JIST checkpoint with a missing key 'seq_gem.p'", import_checkpoint, tmp_path / "nopool.pth",
                    tmp_path / "c")
    assert not any((tmp_path / name).exists() for name in "abc")


@pytest.mark.slow
def test_command_line_import_then_match_with_a_cosplace_model(monkeypatch, capsys, tmp_path):
    from seqvpr.data.sources import load_pair
    from seqvpr.api import match
    from seqvpr.methods import describe_for_models
    from seqvpr.sequences.match_settings import MatchSettings
    from seqvpr.sequences.windows import SequenceSpec

    torch.save(upstream_cosplace_state(seed=5, out_dim=32), tmp_path / "r18_cosplace.pth")
    code, stdout, stderr = run_cli(monkeypatch, capsys, "import", tmp_path / "r18_cosplace.pth",
                                   "--out", tmp_path / "m")
    assert code == 0 and stdout.startswith("cosplace model:"), stderr
    ref, qry = image_folder(tmp_path / "ref", 10, 64, 48, seed=6), image_folder(tmp_path / "qry", 10, 64, 48, seed=7)
    common = ["-r", ref, "-q", qry, "--radius", "3m", "--model", tmp_path / "m", "--image-size", "64x48", "--json"]
    code, stdout, stderr = run_cli(monkeypatch, capsys, "match", *common, "--out", tmp_path / "o")
    assert code == 0, stderr
    settings = json.loads(stdout)["settings"]
    assert (settings["method"], settings["descriptor"], settings["model_kind"]) == ("single", "cosplace", "cosplace")
    assert settings["image_size"] == [64, 48] and settings["sequence"]["length"] == 1
    model = load_trained_model(tmp_path / "m")  # the library: the encoder's frames, single-image retrieval
    frames = describe_for_models(*load_pair(ref, qry), {"cosplace": model}, None, image_size=(64, 48))
    np.testing.assert_allclose(frames[1].descriptors, plain_descriptors(upstream_cosplace_state(5, 32), qry).numpy(),
                               atol=1e-5, rtol=0)
    expected = match(*frames, "single", models={"cosplace": model}, settings=MatchSettings(SequenceSpec(1), k=20))
    rows = (tmp_path / "o" / "predictions.csv").read_text().splitlines()[1:]
    assert [[int(i) for i in row.split(",")[2].split()] for row in rows] == expected.topk.indices.tolist()
    code, stdout, stderr = run_cli(monkeypatch, capsys, "match", *common, "--method", "matching", "-L", "3",
                                   "--out", tmp_path / "o3")
    assert code == 0 and json.loads(stdout)["settings"]["sequence"]["length"] == 3, stderr
    torch.save(upstream_jist_state(), tmp_path / "jist.pth")
    import_checkpoint(tmp_path / "jist.pth", tmp_path / "jist")
    code, _, stderr = run_cli(monkeypatch, capsys, "match", *common, "--model", tmp_path / "jist",
                              "--out", tmp_path / "x")
    assert code == 2 and "a JIST model and a CosPlace model (--model) both describe the images" in stderr
    assert stderr.count("\n") == 1 and not (tmp_path / "x").exists()
