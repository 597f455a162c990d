"""`seqvpr benchmark CONFIG`: config checks, one table per run, failed methods reported in their rows."""

import csv

import pytest

from seqvpr.benchmark import read_config
from seqvpr.data.synthetic import write_demo_route
from tests.helpers import raises_one_line, run_cli


@pytest.fixture(scope="module")
def route(tmp_path_factory):
    folder = tmp_path_factory.mktemp("route")
    write_demo_route(folder, n_frames=300, seed=2)
    return folder


def config_text(methods, lengths="[5, 120]", extra=""):
    return f"""
[benchmark]
methods = {methods}
seq_len = 5
lengths = {lengths}
ks = [1, 5]
[training]
epochs = 2
lr = 0.01
{extra}
[[dataset]]
name = "demo"
reference = "reference.npz"
query = "query.npz"
radius = "10m"
train = "0:150"
select = "150:200"
test = "200:300"
"""


def test_benchmark_prints_both_tables_and_reports_a_failed_length_in_its_row(monkeypatch, capsys, route, tmp_path):
    config = route / "bench.toml"
    config.write_text(config_text('["single", "matching", "seqmatchnet", "smoothing", "hvpr"]'))
    code, stdout, stderr = run_cli(monkeypatch, capsys, "benchmark", config, "--out", tmp_path / "b")
    assert code == 0, stderr
    assert "| matching (L=5) |" in stdout and "demo L=120" in stdout
    with open(tmp_path / "b" / "results.csv", newline="") as handle:
        rows = list(csv.DictReader(handle))
    main = {r["method"]: r for r in rows if r["L"] == "5"}
    assert set(main) == {"single", "matching", "seqmatchnet", "smoothing", "hvpr"}
    assert all(r["error"] == "" and 0 <= float(r["R@1"]) <= 1 for r in main.values())
    long = [r for r in rows if r["L"] == "120"]  # 100 test frames: a window of 120 cannot exist
    assert long and all("longer than every segment" in r["error"] for r in long)
    assert float(main["matching"]["R@1"]) > float(main["single"]["R@1"])  # sequences help on this route
    assert (tmp_path / "b" / "results.md").read_text().count("failed") >= len(long)
    code, again, stderr = run_cli(monkeypatch, capsys, "benchmark", config, "--out", tmp_path / "b")
    assert code == 0 and again == stdout  # a re-run into the same folder reuses the trained model


def test_config_errors_are_one_line(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text(config_text('["single", "magic"]'))
    raises_one_line("unknown methods magic", read_config, bad)
    bad.write_text(config_text('["single"]').replace("[training]\nepochs = 2", "[training]\nepochz = 2"))
    raises_one_line("unknown keys epochz", read_config, bad)
    bad.write_text("[benchmark]\nmethods = [\n")
    raises_one_line("not valid TOML", read_config, bad)
    bad.write_text(config_text('["single"]').replace('radius = "10m"\n', ""))
    raises_one_line("dataset 1 lacks radius", read_config, bad)
    raises_one_line("no such benchmark config", read_config, tmp_path / "missing.toml")
