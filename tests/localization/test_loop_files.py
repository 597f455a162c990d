"""What ``seqvpr loops`` writes: a loops.csv row per frame, the accepted loops as stamp pairs, run.json with the
figures, and with ``report`` a page whose trajectory draws each accepted loop."""

from __future__ import annotations

import csv
import json

import numpy as np

from seqvpr.data.traversal import Traversal
from seqvpr.localization.loop_files import COLUMNS, write_loops
from seqvpr.localization.loops import LoopSettings, find_loops, make_drive, score_loops


def revisiting_drive(stamps: bool = True):
    """60 places driven, then places 10..39 again: frames 64..89 find their place (the whole window revisits)."""
    rng = np.random.default_rng(3)
    places, where = rng.normal(size=(60, 16)), np.cumsum(np.ones((60, 2)), axis=0)
    rows = np.concatenate([places, places[10:40] + 0.05 * rng.normal(size=(30, 16))])
    frames = Traversal("run", np.arange(90), np.zeros(90, np.int64), rows.astype(np.float32),
                       positions=np.concatenate([where, where[10:40]]), source="run",
                       timestamps=np.arange(90) * 0.5 if stamps else None)
    return make_drive([frames])


def test_the_folder_holds_a_row_per_frame_the_accepted_edges_and_the_figures(tmp_path):
    loops = find_loops(revisiting_drive(), LoopSettings(seq_len=5, exclude="20f", threshold=0.2))
    scored = score_loops(loops, "0.5m")
    write_loops(tmp_path / "run", loops, scored, {"sources": ["run"]})
    rows = list(csv.DictReader(open(tmp_path / "run" / "loops.csv")))
    assert tuple(rows[0]) == COLUMNS and len(rows) == 90
    assert [int(r["match"]) if r["match"] else -1 for r in rows] == loops.match.tolist()
    assert [r["correct"] for r in rows[64:]] == ["1"] * 26
    edges = [line.split() for line in open(tmp_path / "run" / "loops_tum.txt") if not line.startswith("#")]
    accepted = np.flatnonzero(loops.accepted)
    assert [(float(a), float(b)) for a, b, _ in edges] == [(i * 0.5, loops.match[i] * 0.5) for i in accepted]
    record = json.loads((tmp_path / "run" / "run.json").read_text())
    assert record["accepted"] == len(accepted) and record["pr_auc"] == round(scored.pr.auc, 6)
    assert not (tmp_path / "run" / "report").exists()


def test_a_drive_without_timestamps_names_frame_rows_in_its_edge_file(tmp_path):
    loops = find_loops(revisiting_drive(stamps=False), LoopSettings(seq_len=5, exclude="20f", threshold=0.2))
    write_loops(tmp_path / "run", loops, None, {})
    lines = open(tmp_path / "run" / "loops_tum.txt").read().splitlines()
    assert "frame rows" in lines[0]
    assert [tuple(map(int, line.split()[:2])) for line in lines[1:]] == \
        [(i, int(loops.match[i])) for i in np.flatnonzero(loops.accepted)]


def test_the_report_draws_the_accepted_loops_and_the_pr_curve(tmp_path):
    loops = find_loops(revisiting_drive(), LoopSettings(seq_len=5, exclude="20f", threshold=0.2))
    write_loops(tmp_path / "run", loops, score_loops(loops, "0.5m"), {}, report=True)
    page = (tmp_path / "run" / "report" / "index.html").read_text()
    assert 'src="loops.png"' in page and 'src="pr.png"' in page
    assert "accepted correct" in page and "recall at 100 precision" in page
    for image in ("loops.png", "pr.png"):
        assert (tmp_path / "run" / "report" / image).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_a_report_without_ground_truth_has_no_pr_curve(tmp_path):
    loops = find_loops(revisiting_drive(), LoopSettings(seq_len=5, exclude="20f", threshold=0.2))
    write_loops(tmp_path / "run", loops, None, {}, report=True)
    page = (tmp_path / "run" / "report" / "index.html").read_text()
    assert 'src="loops.png"' in page and "pr.png" not in page
    assert not (tmp_path / "run" / "report" / "pr.png").exists()


def test_over_several_sessions_each_edge_names_the_two_sessions(tmp_path):
    one = revisiting_drive().frames
    first, second = one.select(np.arange(60)), one.select(np.arange(60, 90))
    drive = make_drive([first, second], ["day drive", "night"])  # stamps 0..29.5 then 30..44.5: time order kept
    loops = find_loops(drive, LoopSettings(seq_len=5, exclude="10s", threshold=0.2))
    write_loops(tmp_path / "run", loops, None, {})
    lines = open(tmp_path / "run" / "loops_tum.txt").read().splitlines()
    assert "session" in lines[0] and len(lines) > 10
    assert all(line.split()[3:] == ["night", "day_drive"] for line in lines[1:])
