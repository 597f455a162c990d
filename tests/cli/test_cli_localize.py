"""``seqvpr localize`` as a user runs it: calibrate on one traversal, replay another, read what it wrote."""

from __future__ import annotations

import csv
import json

import pytest

from tests.helpers import run_cli, write_route_files


@pytest.fixture(scope="module")
def route(tmp_path_factory):
    return write_route_files(tmp_path_factory.mktemp("route"), 120, 16, 7)


def test_calibrate_then_localize_reports_the_precision_reached(route, tmp_path, monkeypatch, capsys):
    assert run_cli(monkeypatch, capsys, "map", "build", route / "ref.npz", "--out", tmp_path / "m")[0] == 0
    common = ("--map", tmp_path / "m", "-q", route / "qry.npz", "--radius", "10m")
    code, out, err = run_cli(monkeypatch, capsys, "localize", *common, "--frames", "0:100", "--calibrate",
                             "--target-precision", "0.9", "--out", tmp_path / "c")
    assert code == 0, err
    assert "for precision >= 0.9: reached" in err and "localizer.json" in err and "R@1 " in out
    stored = json.loads((tmp_path / "m" / "localizer.json").read_text())["calibrations"][0]
    assert stored["settings"]["method"] == "matching" and stored["precision"] >= 0.9
    assert stored["query_frames"] == "0:100" and stored["ground_truth"] == "radius 10m"
    calibration_run = json.loads((tmp_path / "c" / "run.json").read_text())  # --calibrate writes its run as any
    assert calibration_run["threshold"] == stored["threshold"] and calibration_run["query_frames"] == "0:100"
    assert calibration_run["threshold_source"].startswith(f"calibrated on {route / 'qry.npz'} frames 0:100")
    assert calibration_run["precision_of_localised"] == stored["precision"]  # reported at the threshold it chose
    assert (tmp_path / "c" / "stream.csv").exists() and (tmp_path / "c" / "report" / "index.html").exists()

    code, out, err = run_cli(monkeypatch, capsys, "localize", *common, "--out", tmp_path / "o", "--json")
    assert code == 0 and "warning" not in err, err
    summary = json.loads(out)
    assert summary["threshold"] == stored["threshold"] and summary["target_precision"] == 0.9
    assert summary["threshold_source"] == calibration_run["threshold_source"]
    assert summary["ground_truth"] == "radius 10m" and summary["query_frames"] is None
    localized = summary["status"]["localised"]
    assert summary["localised_correct"] + summary["localised_wrong"] == localized > 0
    assert summary["precision_of_localised"] == pytest.approx(summary["localised_correct"] / localized)
    assert set(summary["latency_ms"]) == {"describe", "distance", "sequence", "total"}
    rows = list(csv.DictReader(open(tmp_path / "o" / "stream.csv")))
    assert len(rows) == 120 and rows[0]["status"] == "warming up" and rows[-1]["correct"] in ("0", "1")
    warming, trusted = rows[0], [r for r in rows if r["status"] == "localised"]
    assert (warming["score"], warming["best_row"], warming["localised_row"], warming["x"]) == ("", "", "", "")
    assert len(trusted) == localized and all(r["localised_row"] == r["best_row"] != "" and r["x"] for r in trusted)
    assert all(r["localised_row"] == r["x"] == r["y"] == "" and r["best_row"] != "" for r in rows
               if r["status"] in ("uncertain", "lost"))
    assert trusted[0]["best_frame"] == trusted[0]["best_row"]  # one source, numbered from 0
    report = tmp_path / "o" / "report"
    assert (report / "index.html").exists() and (report / "localisation.png").exists() and (report / "map.png").exists()
    assert "calibrated on " in (report / "index.html").read_text()


def test_an_uncalibrated_threshold_says_so(route, tmp_path, monkeypatch, capsys):
    assert run_cli(monkeypatch, capsys, "map", "build", route / "ref.npz", "--out", tmp_path / "m")[0] == 0
    code, out, err = run_cli(monkeypatch, capsys, "localize", "--map", tmp_path / "m", "-q", route / "qry.npz",
                             "--method", "hmm", "--out", tmp_path / "o")
    assert code == 0 and "threshold 0.5 is the default for hmm, not calibrated on this map" in err
    assert "threshold 0.5000: the default for hmm" in out
    assert json.loads((tmp_path / "o" / "run.json").read_text())["threshold_source"].startswith("the default for hmm")


def test_the_filter_and_a_saved_state_from_the_command_line(route, tmp_path, monkeypatch, capsys):
    assert run_cli(monkeypatch, capsys, "map", "build", route / "ref.npz", "--out", tmp_path / "m")[0] == 0
    common = ("--map", tmp_path / "m", "-q", route / "qry.npz", "--method", "hmm", "--out", tmp_path / "o")
    code, out, err = run_cli(monkeypatch, capsys, "localize", *common, "--save-state", tmp_path / "s.npz")
    assert code == 0 and "120 frames" in out and (tmp_path / "s.npz").exists(), err
    code, _, err = run_cli(monkeypatch, capsys, "localize", *common, "--resume-state", tmp_path / "s.npz")
    assert code == 0, err


@pytest.mark.parametrize("args, message", [
    (("--calibrate",), "--calibrate needs ground truth"),
    (("--shortlist", "5"), "--shortlist needs an index over"),
    (("--shortlist-history", "3"), "--shortlist-history H needs a --shortlist"),
    (("--method", "hmm", "--shortlist", "4"), "takes no --shortlist"),
    (("--resume-state", "QRY"), "as a localiser state"),
    (("--radius", "10m", "--calibrate", "--target-precision", "2"), "'--target-precision': 2 is not in (0, 1]"),
])
def test_bad_localize_options_are_one_line(route, tmp_path, monkeypatch, capsys, args, message):
    assert run_cli(monkeypatch, capsys, "map", "build", route / "ref.npz", "--out", tmp_path / "m")[0] == 0
    args = [route / "qry.npz" if a == "QRY" else a for a in args]
    code, _, err = run_cli(monkeypatch, capsys, "localize", "--map", tmp_path / "m", "-q", route / "qry.npz", *args,
                           "--out", tmp_path / "o")
    assert code == 2 and message in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "o").exists()


def test_the_report_counts_each_status_as_the_summary_does(route, tmp_path, monkeypatch, capsys):
    import re

    from seqvpr.evaluation import localization_report
    from seqvpr.evaluation.localization_plots import legend_label

    drawn: dict[str, list[str]] = {}
    for name in ("plot_map_view", "plot_over_time"):
        original = getattr(localization_report, name)
        monkeypatch.setattr(localization_report, name,
                            lambda *a, _f=original, _n=name: drawn.setdefault(_n, _f(*a)))
    assert run_cli(monkeypatch, capsys, "map", "build", route / "ref.npz", "--out", tmp_path / "m")[0] == 0
    code, out, err = run_cli(monkeypatch, capsys, "localize", "--map", tmp_path / "m", "-q", route / "qry.npz",
                             "--radius", "10m", "--out", tmp_path / "o", "--json")
    assert code == 0, err
    summary = json.loads(out)
    status = summary["status"]
    page = (tmp_path / "o" / "report" / "index.html").read_text()
    table = page[page.index('class="recall status"'):]
    shown = {name: int(n) for name, n in re.findall(r"</span>([^<]+)</td><td>(\d+)</td>", table[:table.index("</table>")])}
    by_status = {s: sum(n for name, n in shown.items() if name.split(",")[0] == s) for s in status}
    assert by_status == status and sum(shown.values()) == 120
    assert shown.get("localised, correct", 0) == summary["localised_correct"]
    assert shown.get("localised, wrong", 0) + shown.get("localised, no true place (wrong)", 0) == \
        summary["localised_wrong"]
    assert drawn["plot_map_view"] == drawn["plot_over_time"] == [legend_label(k, v) for k, v in shown.items()]
    assert "the default for matching, not calibrated on this map" in page and "Recall@1" in page and "pr_auc" not in page
    assert "trusted" not in page


def test_a_calibration_and_a_users_files_outlive_indexing_the_map(route, tmp_path, monkeypatch, capsys):
    """``map index`` rebuilds the map folder: the calibration (an index leaves the map's identity as it is) and
    whatever else a user put there are carried over, so the next ``localize`` still uses the calibrated threshold."""
    assert run_cli(monkeypatch, capsys, "map", "build", route / "ref.npz", "--out", tmp_path / "m")[0] == 0
    common = ("--map", tmp_path / "m", "-q", route / "qry.npz", "--radius", "10m")
    assert run_cli(monkeypatch, capsys, "localize", *common, "--calibrate", "--target-precision", "0.9",
                   "--out", tmp_path / "c")[0] == 0
    (tmp_path / "m" / "notes.txt").write_text("mine")
    (tmp_path / "m" / "drives").mkdir()
    (tmp_path / "m" / "drives" / "a.txt").write_text("also mine")
    calibration = (tmp_path / "m" / "localizer.json").read_text()
    for spec in ("flat", "hnsw:8"):  # a first index, then another in its place
        code, _, err = run_cli(monkeypatch, capsys, "map", "index", tmp_path / "m", "--index", spec)
        assert code == 0, err
        assert (tmp_path / "m" / "localizer.json").read_text() == calibration
        assert (tmp_path / "m" / "notes.txt").read_text() == "mine"
        assert (tmp_path / "m" / "drives" / "a.txt").read_text() == "also mine"
    code, out, err = run_cli(monkeypatch, capsys, "localize", *common, "--out", tmp_path / "o", "--json")
    assert code == 0 and "warning" not in err, err
    assert json.loads(out)["threshold_source"].startswith("calibrated on ")
    code, out, err = run_cli(monkeypatch, capsys, "map", "check", tmp_path / "m")
    assert code == 0, err
