"""Loop closures within a drive: the best earlier frame of each frame outside the exclusion equals a plain loop
over eligible earlier windows (random drives of one or several sessions); the score, the acceptance and the PR
curve over it follow their definitions."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from seqvpr.data.traversal import Traversal
from seqvpr.localization.loops import LoopSettings, find_loops, make_drive, score_loops
from tests.helpers import raises_one_line
from tests.oracles import loops_by_plain_loop


def drive_of(rows: np.ndarray, segments: np.ndarray, name: str = "run", stamps=None) -> Traversal:
    return Traversal(name, np.arange(len(rows)), np.asarray(segments, np.int64), rows.astype(np.float32),
                     timestamps=stamps, source=name)


def assert_plain_loop(loops, length: int) -> None:
    rows = np.asarray(loops.drive.frames.descriptors[:])
    match, distance = loops_by_plain_loop(rows, loops.drive.frames.segment_ids, loops.limits, length)
    np.testing.assert_array_equal(loops.match, match)
    found = match >= 0
    np.testing.assert_allclose(loops.distance[found], distance[found], rtol=1e-5, atol=1e-6)


@settings(max_examples=40, deadline=None)
@given(st.integers(2, 40), st.integers(1, 3), st.integers(1, 5), st.integers(0, 8), st.integers(0, 2**31 - 1))
def test_each_frames_loop_is_the_plain_loops_best_eligible_window(n, n_sessions, length, exclude, seed):
    rng = np.random.default_rng(seed)
    parts = [drive_of(rng.normal(size=(n, 6)), np.sort(rng.integers(0, 2, n)), f"s{s}") for s in range(n_sessions)]
    drive = make_drive(parts)
    settings_ = LoopSettings(seq_len=length, exclude=f"{exclude}f")
    try:
        loops = find_loops(drive, settings_)
    except Exception as error:  # L longer than every segment: the kernel's one line
        assert "longer than every" in str(error)
        return
    assert_plain_loop(loops, length)
    assert (loops.match < loops.limits).all()
    assert ((loops.score >= 0) & (loops.score <= 1)).all()
    np.testing.assert_array_equal(loops.accepted, (loops.match >= 0) & (loops.score >= settings_.accept))


def test_a_drive_with_a_revisit_finds_it_and_scores_it_against_positions():
    rng = np.random.default_rng(3)
    places, where = rng.normal(size=(60, 16)), np.cumsum(np.ones((60, 2)), axis=0)
    rows = np.concatenate([places, places[10:40] + 0.05 * rng.normal(size=(30, 16))])
    frames = Traversal("run", np.arange(90), np.zeros(90, np.int64), rows.astype(np.float32),
                       positions=np.concatenate([where, where[10:40]]), source="run")
    loops = find_loops(make_drive([frames]), LoopSettings(seq_len=5, exclude="20f", threshold=0.2))
    revisit = np.arange(64, 90)  # frames 60..89 revisit 10..39; from the 5th on the whole window does
    np.testing.assert_array_equal(loops.match[revisit], revisit - 50)
    assert loops.accepted[revisit].all() and not loops.accepted[:60].any()
    scored = score_loops(loops, "0.5m")
    np.testing.assert_array_equal(scored.revisit, np.arange(90) >= 60)
    assert scored.correct[revisit].all() and not scored.correct[:60].any()
    assert scored.pr.recall_at_100_precision >= 26 / 30 and scored.pr.auc >= 26 / 30


def test_sessions_come_in_time_order_and_earlier_sessions_are_eligible_whole():
    rng = np.random.default_rng(0)
    late = drive_of(rng.normal(size=(10, 4)), np.zeros(10), "late", stamps=np.arange(10) + 100.0)
    early = drive_of(rng.normal(size=(10, 4)), np.zeros(10), "early", stamps=np.arange(10) + 0.0)
    drive = make_drive([late, early])
    assert drive.session_names == ("early", "late")
    loops = find_loops(drive, LoopSettings(seq_len=1, exclude="100s"))
    np.testing.assert_array_equal(loops.limits, [0] * 10 + [10] * 10)


def test_loop_settings_refuse_a_method_that_does_not_step_and_a_bad_exclusion():
    raises_one_line("loop closure runs", LoopSettings, method="hmm")
    raises_one_line("exclude", LoopSettings, exclude="-3f")
    raises_one_line("exclude", LoopSettings, exclude="3 parsecs")


@settings(max_examples=30, deadline=None)
@given(st.integers(2, 30), st.integers(1, 3), st.integers(1, 4), st.sampled_from(["0f", "3f", "2s", "1.5m"]),
       st.booleans(), st.integers(0, 2**31 - 1))
def test_the_streaming_detector_gives_what_find_loops_gives(n, n_sessions, length, exclude, shortlisted, seed):
    """Exhaustive, and through a flat shortlist as wide as the drive (searched a block at a time offline, a frame
    at a time streaming)."""
    from seqvpr.localization.loop_detector import replay_loops

    rng = np.random.default_rng(seed)
    parts = []
    for s in range(n_sessions):
        part = drive_of(rng.normal(size=(n, 6)), np.sort(rng.integers(0, 2, n)), f"s{s}",
                        stamps=np.cumsum(rng.uniform(0, 1, n)) + 100 * s)
        parts.append(Traversal(part.name, part.frame_index, part.segment_ids, part.descriptors,
                               positions=np.cumsum(rng.normal(size=(n, 2)), axis=0), timestamps=part.timestamps,
                               source=part.name))
    drive = make_drive(parts)
    settings_ = LoopSettings(seq_len=length, exclude=exclude, shortlist=n * n_sessions if shortlisted else 0,
                             shortlist_index="flat")
    try:
        offline = find_loops(drive, settings_)
    except Exception as error:
        assert "longer than every" in str(error)
        return
    streamed = replay_loops(drive, settings_, memory_budget=256)  # past a tiny budget: memory-mapped rows
    np.testing.assert_array_equal(streamed.limits, offline.limits)
    np.testing.assert_array_equal(streamed.match, offline.match)
    found = offline.match >= 0
    np.testing.assert_allclose(streamed.distance[found], offline.distance[found], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(streamed.score, offline.score, rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(streamed.accepted, offline.accepted)


@pytest.mark.parametrize("shortlist", [0, 6])
def test_a_detector_saved_and_restored_mid_drive_goes_on_as_if_never_stopped(tmp_path, shortlist):
    from seqvpr.localization.loop_detector import LoopDetector

    rng = np.random.default_rng(1)
    rows, stamps = rng.normal(size=(80, 8)).astype(np.float32), np.cumsum(rng.uniform(0.5, 1.5, 80))
    settings_ = LoopSettings(seq_len=4, exclude="10s", shortlist=shortlist)  # an HNSW shortlist's graph is saved
    whole = LoopDetector(settings_)
    expected = [whole.update(row, stamp) for row, stamp in zip(rows, stamps)]
    first = LoopDetector(settings_, memory_budget=512, folder=tmp_path)
    got = [first.update(row, stamp) for row, stamp in zip(rows[:37], stamps[:37])]
    first.save_state(tmp_path / "state.npz")
    second = LoopDetector(settings_)
    second.restore(tmp_path / "state.npz")
    got += [second.update(row, stamp) for row, stamp in zip(rows[37:], stamps[37:])]
    assert [(g.match, g.accepted) for g in got] == [(e.match, e.accepted) for e in expected]
    np.testing.assert_allclose([g.score for g in got], [e.score for e in expected], rtol=1e-6)
    assert sum(g.match >= 0 for g in got) > 40
    other = LoopDetector(LoopSettings(seq_len=5, exclude="10s", shortlist=shortlist))
    raises_one_line("other settings", other.restore, tmp_path / "state.npz")
    (tmp_path / "junk.npz").write_bytes(b"junk")
    raises_one_line("junk.npz", second.restore, tmp_path / "junk.npz")


def test_a_frame_that_is_not_a_finite_descriptor_is_one_line_and_changes_nothing():
    from seqvpr.localization.loop_detector import LoopDetector

    detector = LoopDetector(LoopSettings(seq_len=2, exclude="1f"))
    detector.update(np.ones(4, np.float32))
    raises_one_line("NaN or infinity", detector.update, np.array([1.0, np.nan, 0.0, 0.0]))
    raises_one_line("a frame of 5 values", detector.update, np.ones(5))
    assert len(detector.sessions) == 1 and detector.update(np.ones(4)).frame == 1

