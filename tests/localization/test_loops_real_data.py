"""Loop closures on real revisiting drives from ``../shared/data``: Nordland summer frames 17-600 followed by winter
frames 17-600 as one traversal (the winter half revisits the summer half; ground truth by frame number), and Gardens
Point Walking day_left followed by night_right. ``seqvpr loops``' matches equal a plain loop over eligible earlier
windows, the streaming detector's equal both, and sequences beat single frames."""

from __future__ import annotations

import numpy as np
import pytest

from seqvpr.localization.loop_detector import replay_loops
from seqvpr.localization.loops import LoopSettings, find_loops, load_drive, make_drive, score_loops
from tests.helpers import run_cli
from tests.oracles import loops_from_distance_matrix


def one_traversal(sources):
    """The sources described (patch-normalised thumbnails) and laid end to end as one drive of one session (each
    source its own segments)."""
    drive = load_drive([str(s) for s in sources], frames="17:601" if "nordland" in str(sources[0]) else None)
    return make_drive([drive.frames])


@pytest.fixture(scope="module")
def drives(shared_data):
    nordland, gardens = shared_data / "nordland_64x32", shared_data / "gardenspoint_walking"
    return {"nordland": (one_traversal([nordland / "summer", nordland / "winter"]), "1f"),
            "gardens": (one_traversal([gardens / "day_left", gardens / "night_right"]), "2f")}


@pytest.mark.parametrize("name", ["nordland", "gardens"])
def test_loops_on_a_real_drive_are_the_plain_loop_and_the_stream(drives, name):
    drive, _ = drives[name]
    settings = LoopSettings(seq_len=5, exclude="100f")
    offline = find_loops(drive, settings)
    rows = np.asarray(drive.frames.descriptors[:], dtype=np.float64)
    rows /= np.linalg.norm(rows, axis=1, keepdims=True)
    squared = np.clip(2.0 - 2.0 * rows @ rows.T, 0.0, None)
    match, distance = loops_from_distance_matrix(np.sqrt(squared), drive.frames.segment_ids, offline.limits, 5)
    np.testing.assert_array_equal(offline.match, match)
    found = match >= 0
    np.testing.assert_allclose(offline.distance[found], distance[found], rtol=1e-4, atol=1e-5)
    streamed = replay_loops(drive, settings)
    np.testing.assert_array_equal(streamed.match, offline.match)
    np.testing.assert_array_equal(streamed.accepted, offline.accepted)


@pytest.mark.parametrize("name", ["nordland", "gardens"])
def test_sequences_find_more_loops_than_single_frames(drives, name):
    drive, radius = drives[name]
    figures = {length: score_loops(find_loops(drive, LoopSettings(seq_len=length, exclude="100f")), radius).pr
               for length in (1, 10)}
    assert figures[10].auc > figures[1].auc
    assert figures[10].recall_at_100_precision >= figures[1].recall_at_100_precision


def test_the_command_writes_what_the_library_finds(shared_data, tmp_path, monkeypatch, capsys):
    nordland = shared_data / "nordland_64x32"
    code, out, err = run_cli(monkeypatch, capsys, "loops", nordland / "summer", nordland / "winter", "--frames",
                             "17:601", "-L", "5", "--radius", "1f", "--out", tmp_path / "run")
    assert code == 0, err
    import csv
    import json

    rows = list(csv.DictReader(open(tmp_path / "run" / "loops.csv")))
    drive = load_drive([str(nordland / "summer"), str(nordland / "winter")], frames="17:601")
    library = find_loops(drive, LoopSettings(seq_len=5))
    assert [int(r["match"]) if r["match"] else -1 for r in rows] == library.match.tolist()
    record = json.loads((tmp_path / "run" / "run.json").read_text())
    scored = score_loops(library, "1f")
    assert record["pr_auc"] == round(scored.pr.auc, 6) and f"PR-AUC {scored.pr.auc:.3f}" in out
    accepted = [line for line in open(tmp_path / "run" / "loops_tum.txt") if not line.startswith("#")]
    assert len(accepted) == int(library.accepted.sum())


@pytest.mark.parametrize("name", ["nordland", "gardens"])
def test_a_shortlist_of_twenty_finds_what_the_exhaustive_pass_finds(drives, name):
    drive, radius = drives[name]
    exhaustive = find_loops(drive, LoopSettings(seq_len=10, exclude="100f"))
    shortlisted = find_loops(drive, LoopSettings(seq_len=10, exclude="100f", shortlist=20))
    assert (shortlisted.match == exhaustive.match).mean() >= 0.99
    assert score_loops(shortlisted, radius).pr.auc >= score_loops(exhaustive, radius).pr.auc - 0.01
