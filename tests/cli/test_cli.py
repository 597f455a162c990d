"""The command line as a user meets it: results, JSON, predictions, and one-line errors without partial files."""

import json

import numpy as np
import pytest

from tests.helpers import run_cli



run = run_cli


@pytest.fixture
def pair(tmp_path):
    rng = np.random.default_rng(0)
    base = rng.normal(size=(40, 16))
    ref, qry = tmp_path / "ref.npy", tmp_path / "qry.npy"
    np.save(ref, base)
    np.save(qry, base + 0.8 * rng.normal(size=base.shape))
    return ref, qry


def test_match_json_and_predictions(monkeypatch, capsys, tmp_path, pair):
    ref, qry = pair
    out = tmp_path / "out"
    code, stdout, _ = run(monkeypatch, capsys, "match", "-r", ref, "-q", qry, "--radius", "1f", "-L", "3", "--json", "--out", out)
    assert code == 0
    result = json.loads(stdout)
    assert set(result["recall"]) == {"1", "5", "10", "20"}
    assert result["queries_evaluated"] == 38 and result["queries_excluded"] == 2
    assert result["settings"]["sequence"]["length"] == 3
    lines = (out / "predictions.csv").read_text().splitlines()
    assert lines[0] == "query,query_name,references,distances,correct" and len(lines) == 39
    code, stdout, _ = run(monkeypatch, capsys, "eval", out / "predictions.csv", "-r", ref, "-q", qry, "--radius", "1f", "--json")
    assert code == 0 and json.loads(stdout)["recall"] == result["recall"]


@pytest.mark.parametrize("method, velocities", [("matching", "1"), ("adaptive", "1"), ("matching", "0.6,1.4"),
                                              ("seqslam-cone", "0.6,1.4")])
def test_match_writes_the_top1_correspondences_with_their_frame_precision(monkeypatch, capsys, tmp_path, pair,
                                                                          method, velocities):
    import csv

    ref, qry = pair
    out = tmp_path / "out"
    (out).mkdir()
    (out / "correspondences.csv").write_text("stale\n")  # a previous run's pairs
    (out / "run.json").write_text("{}")  # (its manifest: the folder is a run's output, replaced whole)
    code, stdout, stderr = run(monkeypatch, capsys, "match", "-r", ref, "-q", qry, "--radius", "1f", "-L", "5",
                               "--method", method, "--velocities", velocities, "--json", "--out", out)
    assert code == 0, stderr
    result = json.loads(stdout)
    if method == "seqslam-cone":  # votes over several trajectories: no pairs, no file, no figure
        assert not (out / "correspondences.csv").exists() and result["frame_precision"] is None
        return
    with open(out / "correspondences.csv", newline="") as handle:
        rows = list(csv.DictReader(handle))
    by_query = {}
    for row in rows:
        by_query.setdefault(int(row["query"]), []).append(row)
    assert len(by_query) == 36 and all(len(pairs) == 5 for pairs in by_query.values())  # 40 frames, L = 5
    for query, pairs in by_query.items():
        assert [int(p["query_frame"]) for p in pairs] == list(range(query - 2, query + 3))
        frames = [int(p["reference_frame"]) for p in pairs]
        if velocities == "1":
            assert set(np.diff(frames)) <= ({1} if method == "matching" else {1, 2})
        else:  # the winning slope's straight trajectory (np.rint of k * v from the window's start)
            assert [f - frames[0] for f in frames] in ([0, 1, 1, 2, 2], [0, 1, 3, 4, 6])
    predictions = {int(r["query"]): r for r in csv.DictReader(open(out / "predictions.csv", newline=""))}
    for query, pairs in by_query.items():  # the window's own frame is paired with the top-1 reference
        assert int(pairs[2]["reference_frame"]) == int(predictions[query]["references"].split()[0])
    correct = [int(row["correct"]) for row in rows]
    assert result["frame_precision"] == pytest.approx(np.mean(correct))


def test_help_has_examples(monkeypatch, capsys):
    code, stdout, _ = run(monkeypatch, capsys, "match", "--help")
    assert code == 0 and "Examples:" in stdout and "--seq-len" in stdout


def bad_inputs(tmp_path, pair):
    ref, qry = pair
    nan = tmp_path / "nan.npy"
    values = np.ones((40, 16))
    values[7, 3] = np.nan
    np.save(nan, values)
    wide = tmp_path / "wide.npy"
    np.save(wide, np.ones((40, 17)))
    empty = tmp_path / "empty.npy"
    np.save(empty, np.ones((0, 16)))
    short = tmp_path / "short.npy"
    np.save(short, np.ones((3, 16)))
    images = tmp_path / "imgs"
    images.mkdir()
    (images / "positions.csv").write_text("name,easting\n")
    return {
        "nan": (["-r", ref, "-q", nan, "--radius", "1f"], "nan.npy"),
        "dimension": (["-r", ref, "-q", wide, "--radius", "1f"], "dimension"),
        "empty": (["-r", ref, "-q", empty, "--radius", "1f"], "empty.npy"),
        "too long": (["-r", ref, "-q", short, "--radius", "1f", "-L", "5"], "longer than every segment"),
        "missing": (["-r", ref, "-q", tmp_path / "nope.npy", "--radius", "1f"], "nope.npy"),
        "malformed csv": (["-r", images, "-q", qry, "--radius", "1f"], "positions.csv"),
        "bad radius": (["-r", ref, "-q", qry, "--radius", "2 parsecs"], "radius"),
        "no radius": (["-r", ref, "-q", qry], "radius"),
    }


@pytest.mark.parametrize("case", ["nan", "dimension", "empty", "too long", "missing", "malformed csv", "bad radius", "no radius"])
def test_bad_input_is_one_line_without_output(monkeypatch, capsys, tmp_path, pair, case):
    args, needle = bad_inputs(tmp_path, pair)[case]
    out = tmp_path / "out"
    code, stdout, stderr = run(monkeypatch, capsys, "match", *args, "--out", out)
    assert code == 2
    message = stderr.strip()
    assert "\n" not in message and message.startswith("seqvpr: error:") and needle in message
    assert "Traceback" not in stderr
    assert not out.exists() or not any(out.iterdir())


def test_malformed_predictions_file(monkeypatch, capsys, tmp_path, pair):
    ref, qry = pair
    bad = tmp_path / "p.csv"
    bad.write_text("query,references\n1,2 x\n")
    code, _, stderr = run(monkeypatch, capsys, "eval", bad, "-r", ref, "-q", qry, "--radius", "1f")
    assert code == 2 and "p.csv: line 2" in stderr and "\n" not in stderr.strip()


@pytest.mark.slow
def test_demo_quick_renders_matches_trains_and_writes_an_offline_report(monkeypatch, capsys, tmp_path):
    import re

    out = tmp_path / "demo"
    code, stdout, stderr = run(monkeypatch, capsys, "demo", "--quick", "--frames", "100", "--epochs", "3", "--out", out)
    assert code == 0, stderr
    lines = stdout.splitlines()
    table = lines[next(i for i, line in enumerate(lines) if "PR-AUC" in line) + 1:]
    cells = [re.split(r"\s{2,}", line.strip()) for line in table[:next(i for i, t in enumerate(table)
                                                                         if t.startswith("loop closures"))]]
    loop_row = next(line for line in lines if line.startswith("loop closures"))
    found = re.search(r"(\d+) of (\d+) frames revisit, (\d+) loops? accepted, (\d+) right.* PR-AUC ([\d.]+)", loop_row)
    assert found and int(found[2]) == 200 and int(found[4]) <= int(found[3]) and float(found[5]) > 0.2, loop_row
    rows = {name: [float(v) if v != "–" else None for v in values] for name, *values in cells}
    assert set(rows) == {"single image", "sequence matching L=5", "adaptive matching L=5", "SeqSLAM L=5",
                         "SeqSLAM cone L=5", "SeqSLAM hybrid L=5", "CaseVPR L=5", "graph matching", "SeqMatchNet L=5"}
    assert all(0 <= value <= 1 for values in rows.values() for value in values[:4])
    assert rows["SeqSLAM cone L=5"][4] is None and rows["SeqSLAM L=5"][4] is not None  # the cone pairs no frames
    assert rows["sequence matching L=5"][0] > rows["single image"][0]  # sequences beat single frames here
    page = out / "report" / "index.html"
    html = page.read_text()
    assert "SeqMatchNet L=5" in html and f"{rows['single image'][0]:.3f}" in html
    links = re.findall(r'(?:src|href)="([^"]+)"', html)
    assert links and all((page.parent / link).is_file() for link in links)
    assert not any(link.startswith(("http:", "https:", "//", "/")) for link in links)
    assert sorted(p.name for p in (out / "world").iterdir()) == ["test_query", "test_reference", "train_query",
                                                                  "train_reference"]


def test_description_file_with_ground_truth_table(monkeypatch, capsys, tmp_path, pair):
    ref, qry = pair
    description = tmp_path / "dataset.toml"
    description.write_text(
        f'[reference]\ndescriptors = "{ref.name}"\nname = "day"\n'
        f'[query]\ndescriptors = "{qry.name}"\n[ground_truth]\nradius = "1f"\n'
    )
    code, stdout, _ = run(monkeypatch, capsys, "match", "-r", description, "-q", description, "-L", "3", "--json", "--out", tmp_path / "o")
    direct = run(monkeypatch, capsys, "match", "-r", ref, "-q", qry, "--radius", "1f", "-L", "3", "--json", "--out", tmp_path / "p")[1]
    assert code == 0 and json.loads(stdout)["recall"] == json.loads(direct)["recall"]


def test_traversal_npz_keeps_positions_for_metric_radius(monkeypatch, capsys, tmp_path):
    from seqvpr.synthetic.routes import write_demo_route

    ref, qry = write_demo_route(tmp_path, n_frames=200, seed=3)
    code, stdout, _ = run(monkeypatch, capsys, "match", "-r", ref, "-q", qry, "--radius", "10m", "-L", "5", "--json", "--out", tmp_path / "o")
    assert code == 0 and json.loads(stdout)["settings"]["ground_truth_rule"] == "within 10 m"


def test_demo_bad_options_are_one_line_errors_without_output(monkeypatch, capsys, tmp_path):
    afile = tmp_path / "afile"
    afile.write_text("x")
    for args, message in ((["--out", afile], "afile is not a folder, and a folder goes there"),
                          (["--frames", "10", "--out", tmp_path / "d"], "--frames must be at least 50"),
                          (["--epochs", "0", "--out", tmp_path / "d"], "--epochs must be at least 1")):
        code, _, stderr = run(monkeypatch, capsys, "demo", *args)
        assert code == 2 and message in stderr and stderr.count("\n") == 1
    assert not (tmp_path / "d").exists()
