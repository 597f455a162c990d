"""The inference engines (``seqvpr.features.engines``): ONNX Runtime's descriptors equal torch's within the
tolerance for every built-in encoder, the export is made once per encoder identity and reused, ``auto`` falls back
to torch where an encoder does not export, ONNX Runtime's pool follows the thread policy, and a missing runtime is
one line saying how to install it."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from seqvpr.errors import SeqvprError
from seqvpr.features import engines
from seqvpr.features.engines import OnnxEncoder, TOLERANCE, cached_export, check_engine, probe_difference, with_engine
from seqvpr.features.extraction import ExtractorConfig, build_extractor
from tests.helpers import raises_one_line

SIZE = (96, 64)


@pytest.mark.parametrize("backbone, weights", [("efficientnet-lite0", "imagenet"), ("resnet18", None),
                                               ("resnet50", None)])
def test_onnx_gives_torchs_descriptors_for_every_built_in_encoder(tmp_path, backbone, weights):
    module = build_extractor(ExtractorConfig(backbone, weights, width=SIZE[0], height=SIZE[1]))
    engine = with_engine(module, *SIZE, "onnx")
    assert isinstance(engine, OnnxEncoder)
    images = torch.rand(3, 3, SIZE[1], SIZE[0], generator=torch.Generator().manual_seed(5))
    with torch.no_grad():
        assert float((module(images) - engine(images)).abs().max()) <= TOLERANCE


def test_lite_padding_is_folded_by_onnx_runtime_into_its_convolutions(tmp_path):
    """TensorFlow "same" padding exports as constant Pads with no omitted inputs, which ONNX Runtime's graph
    optimisation folds into the convolutions after them: no Pad is left to run (a third of Lite0's time)."""
    import onnx
    import onnxruntime

    module = build_extractor(ExtractorConfig("efficientnet-lite0", "imagenet", width=SIZE[0], height=SIZE[1]))
    exported = engines.export_onnx(module, *SIZE, tmp_path / "lite.onnx")
    assert sum(node.op_type == "Pad" for node in onnx.load(exported).graph.node) == 17
    options = onnxruntime.SessionOptions()
    options.graph_optimization_level = onnxruntime.GraphOptimizationLevel.ORT_ENABLE_BASIC
    options.optimized_model_filepath = str(tmp_path / "optimised.onnx")
    onnxruntime.InferenceSession(str(exported), options, providers=["CPUExecutionProvider"])
    assert not [node for node in onnx.load(tmp_path / "optimised.onnx").graph.node if node.op_type == "Pad"]


def test_the_thumbnail_cnn_exports_too():
    from seqvpr.features.backbones import thumbnail_cnn

    module = nn.Sequential(thumbnail_cnn(None), nn.AdaptiveAvgPool2d(1), nn.Flatten()).eval()
    assert probe_difference(module, with_engine(module, 64, 32, "onnx"), 64, 32) <= TOLERANCE


def test_an_export_is_made_once_per_encoder_identity(tmp_path):
    module = build_extractor(ExtractorConfig("resnet18", None, width=64, height=48))
    first = cached_export(module, 64, 48, tmp_path)
    stamp = first.stat().st_mtime_ns
    assert cached_export(module, 64, 48, tmp_path) == first and first.stat().st_mtime_ns == stamp
    assert cached_export(module, 64, 32, tmp_path) != first  # another input size, another export
    with torch.no_grad():
        module.pooling.p.add_(0.5)  # other weights, another identity
    assert cached_export(module, 64, 48, tmp_path) != first
    assert sorted(p.suffix for p in tmp_path.iterdir()) == [".onnx"] * 3  # no unchecked leftovers


class Branchy(nn.Module):
    """An encoder whose output depends on its batch through Python control flow: the trace (one image) bakes one
    branch in, so its export differs from torch on the probe batch (two images)."""

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        pooled = images.mean(dim=(2, 3))
        return pooled * 2 if len(images) > 1 else pooled


def test_auto_keeps_torch_where_the_export_differs_and_onnx_says_why(tmp_path, monkeypatch):
    monkeypatch.setenv("SEQVPR_CACHE", str(tmp_path))
    module = Branchy()
    assert with_engine(module, 32, 24, "auto") is module
    raises_one_line("engine onnx: the encoder does not export to ONNX", with_engine, module, 32, 24, "onnx")
    assert not list((tmp_path / "encoders").glob("*.onnx"))


def test_torch_and_gpu_devices_keep_the_module():
    module = build_extractor(ExtractorConfig("resnet18", None, width=32, height=32))
    assert with_engine(module, 32, 32, "torch") is module
    assert with_engine(module, 32, 32, "auto", device="cuda") is module
    raises_one_line("engine onnx runs on the CPU", with_engine, module, 32, 32, "onnx", "cuda")


def test_onnx_runtime_threads_follow_the_policy(tmp_path):
    module = build_extractor(ExtractorConfig("resnet18", None, width=32, height=32))
    path = cached_export(module, 32, 32, tmp_path)
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        options = OnnxEncoder(path).session.get_session_options()
        assert (options.intra_op_num_threads, options.inter_op_num_threads) == (1, 1)
    finally:
        torch.set_num_threads(before)


def test_a_missing_runtime_and_a_bad_engine_are_one_line(monkeypatch):
    raises_one_line("engine must be one of 'auto', 'torch', 'onnx', got 'tensorrt'", check_engine, "tensorrt")
    monkeypatch.setattr(engines, "onnx_runtime_installed", lambda: False)
    raises_one_line("engine onnx needs ONNX Runtime: pip install onnxruntime onnx", check_engine, "onnx")
    module = build_extractor(ExtractorConfig("resnet18", None, width=32, height=32))
    assert with_engine(module, 32, 32, "auto") is module


def test_a_damaged_onnx_file_is_one_line(tmp_path):
    (tmp_path / "bad.onnx").write_bytes(b"not a model")
    with pytest.raises(SeqvprError, match="bad.onnx: not an ONNX model ONNX Runtime can run"):
        OnnxEncoder(tmp_path / "bad.onnx")


def test_a_batch_through_onnx_runtime_gives_torchs_rows_and_keeps_skipping_bad_images(tmp_path):
    import numpy as np
    from PIL import Image

    from seqvpr.features.extraction import extract_descriptors

    rng = np.random.default_rng(2)
    paths = []
    for i in range(7):
        paths.append(tmp_path / f"{i}.png")
        Image.fromarray(rng.integers(0, 255, (40, 50, 3), dtype=np.uint8)).save(paths[-1])
    config = ExtractorConfig("resnet18", None, width=48, height=32, batch_size=3)
    torch.manual_seed(0)
    module = build_extractor(config)
    rows = {engine: extract_descriptors(paths, config, extractor=module, engine=engine) for engine in ("torch", "onnx")}
    assert np.abs(rows["torch"].descriptors - rows["onnx"].descriptors).max() <= TOLERANCE
    paths[4].write_bytes(b"not an image")
    raises_one_line("4.png", extract_descriptors, paths, config, extractor=module, engine="onnx")
    kept = extract_descriptors(paths, config, extractor=module, engine="onnx", skip_bad=True)
    assert kept.rows.tolist() == [0, 1, 2, 3, 5, 6] and [p.name for p in kept.skipped] == ["4.png"]
    assert np.abs(kept.descriptors - np.delete(rows["torch"].descriptors, 4, axis=0)).max() <= TOLERANCE


def test_the_engines_agree_on_real_images_to_the_recall(shared_data):
    """Gardens Point Walking, day left against night right, Lite0 at 160x120 (half the default, to stay quick):
    descriptors within the tolerance and Recall@1/5 of sequence matching identical."""
    import numpy as np

    import seqvpr
    from seqvpr.features.describe import describe

    walking = shared_data / "gardenspoint_walking"
    found = {}
    for engine in ("torch", "onnx"):
        sides = [describe(seqvpr.load_traversal(str(walking / side), role), "efficientnet-lite0",
                          extractor=ExtractorConfig(width=160, height=120), engine=engine)
                 for side, role in (("day_left", "reference"), ("night_right", "query"))]
        found[engine] = sides, seqvpr.evaluate(seqvpr.match(*sides, seq_len=5), radius="2f", ks=(1, 5)).recall
    for torch_side, onnx_side in zip(found["torch"][0], found["onnx"][0]):
        assert np.abs(torch_side.descriptors - onnx_side.descriptors).max() <= TOLERANCE
    assert found["torch"][1] == found["onnx"][1] and found["torch"][1][1] > 0.3, found["torch"][1]


def test_the_command_lines_engines_are_the_librarys():
    from seqvpr import checks
    from seqvpr.cli.options import ENGINES

    assert ENGINES == checks.ENGINES == engines.ENGINES
