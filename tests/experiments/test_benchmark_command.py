"""`seqvpr benchmark CONFIG`: config checks, one table per run, failed methods reported in their rows."""

import csv

import pytest

from seqvpr.experiments.benchmark import read_config
from seqvpr.synthetic.routes import write_demo_route
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
[seqnet]
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


def benchmark_csv(monkeypatch, capsys, config, out) -> tuple[str, list[dict[str, str]]]:
    """Run ``seqvpr benchmark CONFIG --out OUT``; its stdout and results.csv rows."""
    code, stdout, stderr = run_cli(monkeypatch, capsys, "benchmark", config, "--out", out)
    assert code == 0, stderr
    with open(out / "results.csv", newline="") as handle:
        return stdout, list(csv.DictReader(handle))


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
    from seqvpr.viewer import view_page
    from seqvpr.viewer.runs import read_views

    view = read_views([tmp_path / "b"])  # seqvpr view BENCHMARK: the dataset's runs at the main L, side by side
    assert sorted(m.name.split(" ")[0] for m in view.methods) == sorted(f"{m}-L5" for m in main)
    assert view.query is not None and len(view.query.names) == 100 and view.positives is not None
    assert view_page([tmp_path / "b"], tmp_path / "page").is_file()


def test_robotics_figures_and_frame_precision_reach_the_csv_and_the_detail_table(monkeypatch, capsys, route, tmp_path):
    from seqvpr.data.ground_truth import ground_truth_within_radius
    from seqvpr.experiments.benchmark import load_splits
    from tests.helpers import match_method
    from seqvpr.evaluation.scoring import evaluate_match
    from seqvpr.sequences.match_settings import MatchSettings
    from seqvpr.sequences.windows import SequenceSpec

    config = route / "bench_matchers.toml"
    config.write_text(config_text('["single", "adaptive", "graph"]', lengths="[5, 7]"))
    stdout, found = benchmark_csv(monkeypatch, capsys, config, tmp_path / "b")
    rows = {(r["method"], r["L"]): r for r in found}
    splits = load_splits(read_config(config).datasets[0])
    gt = ground_truth_within_radius(splits.test[1], splits.test[0], splits.radius)
    result = match_method("adaptive", *splits.test, MatchSettings(SequenceSpec(7), k=20))
    expected = evaluate_match(result, gt, (1, 5))  # oracle: the library's own evaluation of the same run
    row = rows[("adaptive", "7")]
    assert float(row["frame_precision"]) == pytest.approx(expected.frame_precision, abs=1e-4)
    assert float(row["recall_at_100_precision"]) == pytest.approx(expected.pr.recall_at_100_precision, abs=1e-4)
    assert 0 < float(row["frame_precision"]) <= 1
    single = next(r for (method, _), r in rows.items() if method == "single")
    assert single["frame_precision"] != ""  # one frame a query: its own correspondence
    markdown = (tmp_path / "b" / "results.md").read_text()
    assert "demo: R@1 / R@5 / R@100P / frames" in markdown
    assert "| graph | " in stdout and "| graph | 1 | " in markdown  # a whole-path method has no window length
    detail = next(line for line in markdown.splitlines() if line.startswith("| adaptive | 7 |"))
    assert detail.split("|")[3].strip().endswith(f"{expected.frame_precision:.3f}")


def test_seqnet_row_and_hvpr_shortlist_and_jist_not_applicable_on_descriptors(monkeypatch, capsys, route, tmp_path):
    from seqvpr.matchers.retrieval import RetrievalMatcher
    from seqvpr.evaluation.scoring import evaluate_match
    from seqvpr.sequences.match_settings import MatchSettings
    from seqvpr.sequences.windows import SequenceSpec
    from seqvpr.models.seqnet import load_seqnet

    config = route / "bench_seqnet.toml"
    config.write_text(config_text('["seqnet", "jist", "hvpr"]', lengths="[5]"))
    stdout, found = benchmark_csv(monkeypatch, capsys, config, tmp_path / "b")
    rows = {r["method"]: r for r in found}
    assert rows["jist"]["error"].startswith("needs images") and rows["jist"]["R@1"] == ""
    assert "| jist (L=5) | n/a | n/a |" in stdout
    assert rows["seqnet"]["error"] == "" and rows["hvpr"]["error"] == ""
    # oracle: the trained SeqNet, reloaded, scored through the library on the test split
    from seqvpr.experiments.benchmark import load_splits, read_config
    from seqvpr.data.ground_truth import ground_truth_within_radius

    splits = load_splits(read_config(config).datasets[0])
    model, _ = load_seqnet(tmp_path / "b" / "demo" / "seqnet")
    result = RetrievalMatcher(MatchSettings(SequenceSpec(5), k=20), "seqnet", model).topk(*splits.test)
    expected = evaluate_match(result, ground_truth_within_radius(splits.test[1], splits.test[0], splits.radius), (1, 5))
    assert float(rows["seqnet"]["R@1"]) == pytest.approx(expected.recall[1], abs=1e-4)
    assert float(rows["seqnet"]["R@5"]) == pytest.approx(expected.recall[5], abs=1e-4)


JIST_TABLE = """[jist]
backbone = "efficientnet-lite0"
weights = "imagenet"
trainable_stages = ["stage7", "head"]
width = 64
height = 48
epochs = 1
refreshes = 1
max_iterations = 2
queries_per_refresh = 8
negative_pool = 16
batch_size = 2
negatives = 2
images_per_batch = 8
cell_m = 10
min_images = 2
"""


@pytest.mark.slow
def test_jist_trains_on_an_image_dataset_and_a_rerun_reuses_it(monkeypatch, capsys, tmp_path):
    from seqvpr.data.ground_truth import Radius, ground_truth_within_radius
    from seqvpr.experiments.benchmark import load_splits, read_config
    from seqvpr.models.jist import describe_with_jist, load_jist
    from seqvpr.matchers.retrieval import RetrievalMatcher
    from seqvpr.evaluation.scoring import evaluate_match
    from seqvpr.sequences.match_settings import MatchSettings
    from seqvpr.sequences.windows import SequenceSpec
    from seqvpr.synthetic.world import write_demo_world
    from seqvpr.training.jist import jist_setup

    paths = write_demo_world(tmp_path / "world", frames=150, width=64, height=48, seed=0, query_condition="dusk")
    config = tmp_path / "bench.toml"
    text = config_text('["single", "jist"]', lengths="[5, 7]", extra=JIST_TABLE)
    text = text.replace('"reference.npz"', f'"{paths["test_reference"]}"').replace('"query.npz"', f'"{paths["test_query"]}"')
    config.write_text(text.replace('"0:150"', '"0:90"').replace('"150:200"', '"90:115"').replace('"200:300"', '"115:150"'))
    code, stdout, stderr = run_cli(monkeypatch, capsys, "benchmark", config, "--out", tmp_path / "b")
    assert code == 0, stderr
    with open(tmp_path / "b" / "results.csv", newline="") as handle:
        rows = {(r["method"], r["L"]): r for r in csv.DictReader(handle)}
    assert rows[("jist", "5")]["error"] == "" and rows[("jist", "7")]["error"] == ""
    parsed = read_config(config)
    splits, (_, settings) = load_splits(parsed.datasets[0]), jist_setup(parsed.jist, parsed.seq_len)
    model = load_jist(tmp_path / "b" / "demo" / "jist")
    reference, query = (describe_with_jist(model, t, settings.width, settings.height) for t in splits.test)
    gt = ground_truth_within_radius(query, reference, Radius(10.0, "m"))
    for length in (5, 7):  # oracle: the saved model's frames pooled by its SeqGeM on the test split
        found = RetrievalMatcher(MatchSettings(SequenceSpec(length), k=5), "seqgem", model.sequence_pool).topk(
            reference, query)
        expected = evaluate_match(found, gt, (1, 5))
        assert float(rows[("jist", str(length))]["R@1"]) == pytest.approx(expected.recall[1], abs=1e-4)
    history = tmp_path / "b" / "demo" / "jist" / "history.csv"
    stamp = history.stat().st_mtime_ns
    code, again, _ = run_cli(monkeypatch, capsys, "benchmark", config, "--out", tmp_path / "b")
    assert code == 0 and again == stdout and history.stat().st_mtime_ns == stamp  # reused, not retrained


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
    bad.write_text(config_text('["single"]', extra="[jist]\nbackbon = 'resnet18'\n"))
    raises_one_line("[jist] has unknown keys backbon", read_config, bad)
    bad.write_text(config_text('["single"]').replace("[seqnet]\nepochs = 2", "[seqnet]\nepoch = 2"))
    raises_one_line("[seqnet] has unknown keys epoch", read_config, bad)
    bad.write_text(config_text('["single"]').replace("ks = [1, 5]", "ks = [1, 5]\nhvpr_shortlist = 'netvlad'"))
    raises_one_line("hvpr_shortlist 'netvlad' is not one of seqnet, seqgem", read_config, bad)
    for table, message in [("[match]\nvelocity = '1'", "[match] has unknown keys velocity"),
                           ("[match]\nvelocities = '1:0.5:0.1'", "[match] velocities '1:0.5:0.1': expected"),
                           ("[match]\nvelocities = '-1'", "velocities must be in (0, 100]"),
                           ("[match.adaptive]\nsteps = '2:1'", "[match.adaptive] steps '2:1': expected"),
                           ("[match]\ncontrast_window = 1", "contrast_window must be a whole number of at least 2"),
                           ("[match.graph]\nsteps = '0:2'", "[match] has tables for graph, which [benchmark] methods")]:
        bad.write_text(config_text('["single", "adaptive"]', extra=table + "\n"))
        raises_one_line(message, read_config, bad)


def test_match_tables_set_each_methods_settings(tmp_path):
    config = tmp_path / "match.toml"
    extra = "[match]\nsteps = '0:2'\n[match.seqslam-hybrid]\nvelocities = '0.8:1.2:0.1'\ncontrast_window = 40\n"
    config.write_text(config_text('["adaptive", "seqslam-hybrid"]', extra=extra))
    parsed = read_config(config)
    hybrid, hybrid_search = parsed.match_settings("seqslam-hybrid", 10, 20)
    assert hybrid.sequence.velocities == (0.8, 0.9, 1.0, 1.1, 1.2) and hybrid.sequence.length == 10
    assert hybrid_search == {"contrast_window": 40, "steps": (0, 2)} and hybrid.k == 20
    adaptive, adaptive_search = parsed.match_settings("adaptive", 5, 20)
    assert adaptive.sequence.velocities == (1.0,) and adaptive_search == {"steps": (0, 2)}


class Captured(Exception):
    """Raised by a stand-in ``train_jist`` to stop once it has seen its arguments."""


def test_jist_defaults_are_the_same_in_train_jist_and_the_benchmark(monkeypatch, capsys, tmp_path):
    """``seqvpr train jist`` with its defaults and the benchmark with an empty [jist] table hand ``train_jist`` the
    same model config, run settings and radii (negatives at 2.5x the positive radius, the recipe for the frames)."""
    import seqvpr.training.jist as jist
    from seqvpr.experiments.benchmark import Splits, train_kind
    from seqvpr.data.ground_truth import parse_radius
    from seqvpr.data.sources import load_pair
    from seqvpr.synthetic.world import write_demo_world

    seen = []

    def capture(data, config, settings, out_dir, **kwargs):
        seen.append((config, settings, data.positive_radius, data.negative_radius, data.val_radius))
        raise Captured

    monkeypatch.setattr(jist, "train_jist", capture)
    paths = write_demo_world(tmp_path / "world", frames=40, width=64, height=48, seed=0)
    ref, qry = str(paths["train_reference"]), str(paths["train_query"])
    with pytest.raises(Captured):
        run_cli(monkeypatch, capsys, "train", "jist", "-r", ref, "-q", qry, "--train-frames", "0:30",
                "--val-frames", "30:40", "--radius", "10m", "--out", tmp_path / "run")
    config = tmp_path / "b.toml"
    config.write_text(config_text('["jist"]').replace('"reference.npz"', f'"{ref}"').replace('"query.npz"', f'"{qry}"'))
    reference, query = load_pair(ref, qry)
    splits = Splits((reference.slice_frames(0, 30), query.slice_frames(0, 30)),
                    (reference.slice_frames(30, 40), query.slice_frames(30, 40)), None, parse_radius("10m"))
    with pytest.raises(Captured):
        train_kind("jist", splits, read_config(config), tmp_path / "bench")
    assert seen[0] == seen[1]  # 64x48 frames: both took the thumbnail recipe
    assert seen[0][0].backbone == "thumbnail-cnn" and seen[0][1].width == 64 and seen[0][3].value == 25.0
