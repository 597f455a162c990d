"""MSLS as downloaded: a fixture with the published CSV headers (pandas' unnamed index column included), two
sequences a side; sequences become segments in frame-number order, positions come from postprocessed.csv,
panoramas are left out, subtasks select, and ``seqvpr match`` runs on it end to end."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
from PIL import Image

from seqvpr.data.loaders.msls import load_msls_side
from seqvpr.data.sources import load_traversal
from tests.helpers import raises_one_line, run_cli


def write_side(folder, sequences, rng, pano_key=None):
    """``sequences``: {sequence key: [(frame number, easting)...]} written as MSLS writes them (rows shuffled)."""
    (folder / "images").mkdir(parents=True)
    rows = [(f"{seq}_{n}", seq, n, east) for seq, frames in sequences.items() for n, east in frames]
    order = rng.permutation(len(rows))
    rows = [rows[i] for i in order]
    with open(folder / "seq_info.csv", "w", newline="") as h:
        out = csv.writer(h)
        out.writerow(["", "key", "frame_number", "sequence_key"])
        out.writerows([i, key, n, seq] for i, (key, seq, n, _) in enumerate(rows))
    with open(folder / "postprocessed.csv", "w", newline="") as h:
        out = csv.writer(h)
        out.writerow(["", "key", "easting", "northing", "night", "control_panel", "view_direction", "unique_cluster"])
        out.writerows([i, key, 760000.0 + east, 3540000.0, False, False, "Forward", i] for i, (key, _, _, east) in enumerate(rows))
    with open(folder / "raw.csv", "w", newline="") as h:
        out = csv.writer(h)
        out.writerow(["", "key", "lon", "lat", "ca", "captured_at", "pano"])
        out.writerows([i, key, 35.9, 31.9, 90.0, 1500000000000 + i, key == pano_key] for i, (key, *_) in enumerate(rows))
    with open(folder / "subtask_index.csv", "w", newline="") as h:
        out = csv.writer(h)
        out.writerow(["", "key", "all", "s2w", "w2s", "o2n", "n2o", "d2n", "n2d"])
        out.writerows([i, key, True, False, False, False, False, seq == "qB", False] for i, (key, seq, _, _) in enumerate(rows))
    for key, *_ in rows:
        shade = int(40 + 2 * (int(key.split("_")[1]) % 50))
        Image.fromarray(np.full((24, 32, 3), shade, np.uint8) + rng.integers(0, 20, (24, 32, 3), dtype=np.uint8)).save(
            folder / "images" / f"{key}.jpg")
    return folder


@pytest.fixture(scope="module")
def city(tmp_path_factory):
    root = tmp_path_factory.mktemp("msls") / "train_val" / "amman"
    rng = np.random.default_rng(0)
    write_side(root / "database", {"dA": [(n, 3.0 * n) for n in range(12)], "dB": [(n, 100 + 3.0 * n) for n in range(10)]}, rng)
    write_side(root / "query", {"qA": [(n, 3.0 * n + 1) for n in range(2, 9)], "qB": [(n, 101 + 3.0 * n) for n in range(8)]},
               rng, pano_key="qA_5")
    return root


def test_sequences_are_segments_in_frame_order_with_positions(city):
    database = load_traversal(city / "database", "reference")
    assert len(database) == 22 and len(np.unique(database.segment_ids)) == 2
    first = [p.name for p in database.image_paths[:3]]
    assert first == ["dA_0.jpg", "dA_1.jpg", "dA_2.jpg"]
    np.testing.assert_allclose(database.positions[:3, 0], 760000.0 + np.array([0.0, 3.0, 6.0]))
    query = load_traversal(city / "query", "query")
    assert "qA_5.jpg" not in [p.name for p in query.image_paths]  # the panorama is left out
    assert len(np.unique(query.segment_ids)) == 3  # qA is cut where the panorama was (frame numbers 4 -> 6)


def test_a_subtask_keeps_its_frames(city):
    night = load_msls_side(city / "query", "d2n")
    assert {p.name.split("_")[0] for p in night.image_paths} == {"qB"}
    raises_one_line("subtask 'x2y' is not known", load_msls_side, city / "query", "x2y")


def test_match_runs_on_msls_end_to_end(city, tmp_path, monkeypatch, capsys):
    code, out, err = run_cli(monkeypatch, capsys, "match", "-r", city / "database", "-q", city / "query", "-L", "3",
                             "--json", "--out", tmp_path / "o")
    assert code == 0, err
    result = json.loads(out)
    assert "25" in result["settings"]["ground_truth_rule"] and result["queries_evaluated"] > 0


def test_missing_columns_are_one_line(tmp_path):
    side = tmp_path / "query"
    (side / "images").mkdir(parents=True)
    (side / "seq_info.csv").write_text(",key,frame_number\n0,a,0\n")
    raises_one_line("no column sequence_key or sequence_id", load_msls_side, side)


def test_the_subtask_option_of_match(city, tmp_path, monkeypatch, capsys):
    code, out, err = run_cli(monkeypatch, capsys, "match", "-r", city / "database", "-q", city / "query", "-L", "3",
                             "--msls-subtask", "d2n", "--json", "--out", tmp_path / "o")
    assert code == 0, err
    assert json.loads(out)["queries_evaluated"] <= 8 - 2


@pytest.mark.parametrize("name", ["raw.csv", "seq_info.csv", "postprocessed.csv", "subtask_index.csv"])
def test_a_csv_cut_mid_line_is_one_line_naming_it(city, tmp_path, name):
    """An interrupted download leaves a CSV whose last line lacks fields: one line naming the file and the line, for
    every file the loader reads (was an AttributeError for raw.csv)."""
    import shutil

    side = tmp_path / "query"
    shutil.copytree(city / "query", side)
    text = (side / name).read_text()
    (side / name).write_text(text.rstrip("\n")[: text.rstrip("\n").rfind(",")])  # the last field cut off
    raises_one_line(f"{side / name}: line", load_msls_side, side, "d2n")
