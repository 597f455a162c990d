"""`seqvpr benchmark` reuses a trained model only when it was trained on the same data and split; the run records
the data identities, the splits and the models its results rest on."""

import json

import pytest

from seqvpr.synthetic.routes import write_demo_route
from tests.experiments.test_benchmark_command import config_text
from tests.helpers import run_cli


@pytest.fixture(scope="module")
def route(tmp_path_factory):
    folder = tmp_path_factory.mktemp("route")
    write_demo_route(folder, n_frames=300, seed=2)
    return folder


def run(monkeypatch, capsys, config, out):
    code, stdout, stderr = run_cli(monkeypatch, capsys, "benchmark", config, "--out", out)
    assert code == 0, stderr
    return stdout, stderr, json.loads((out / "run.json").read_text())["datasets"]["demo"]


def test_a_model_trained_on_another_split_is_retrained_not_reused(monkeypatch, capsys, route, tmp_path):
    config = route / "bench_reuse.toml"
    config.write_text(config_text('["seqmatchnet"]', lengths="[5]"))
    out = tmp_path / "b"
    first, stderr, record = run(monkeypatch, capsys, config, out)
    assert "warning" not in stderr
    assert record["splits"]["train"]["reference"]["frames"] == "0:150"
    assert record["splits"]["test"]["query"]["file"].startswith("sha256:")
    weights = record["models"]["seqmatchnet"]["weights"]
    assert weights.startswith("sha256:")
    again, stderr, same = run(monkeypatch, capsys, config, out)  # same data and split: reused
    assert again == first and "warning" not in stderr and same["models"]["seqmatchnet"]["weights"] == weights
    config.write_text(config_text('["seqmatchnet"]', lengths="[5]").replace('"0:150"', '"0:140"'))
    _, stderr, moved = run(monkeypatch, capsys, config, out)
    assert "seqvpr: warning:" in stderr and "trained on other data" in stderr and "training it again" in stderr
    assert moved["splits"]["train"]["reference"]["frames"] == "0:140"
    assert moved["models"]["seqmatchnet"]["weights"] != weights
    state = json.loads((out / "demo" / "seqmatchnet" / "train_state.json").read_text())
    assert state["data"]["reference"]["frames"] == "0:140"
