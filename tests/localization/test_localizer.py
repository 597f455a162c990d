"""The online localiser against offline matching: frame-by-frame estimates equal ``sequence_topk`` with causal
windows (random traversals, segment breaks, resets), the filter equals the offline ``hmm`` method, shortlists as
wide as the map are exact, states resume exactly, camera frames are described as the map's, and bad frames are
one line that leaves the localiser usable."""

import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from PIL import Image

from seqvpr.data.sources import load_traversal, save_traversal_npz
from seqvpr.data.traversal import Traversal
from seqvpr.localization import Localizer
from seqvpr.localization.replay import replay
from seqvpr.maps import build_map, open_map
from seqvpr.maps.index import IndexSpec, add_index
from tests.helpers import match_method
from seqvpr.matchers.sequence import SequenceMatcher
from seqvpr.features.describe import describe
from seqvpr.sequences.match_settings import MatchSettings
from seqvpr.sequences.windows import SequenceSpec
from tests.helpers import examples, raises_one_line, write_route_files


@pytest.fixture(scope="module")
def route(tmp_path_factory):
    folder = write_route_files(tmp_path_factory.mktemp("route"), 150, 16, 9)
    build_map([str(folder / "ref.npz")], folder / "map")
    return folder


def traversal(rows: np.ndarray, segments: np.ndarray, name: str) -> Traversal:
    return Traversal(name, np.arange(len(rows)), np.asarray(segments, np.int64), rows.astype(np.float32))


def assert_same_as_offline(run, offline, k: int) -> None:
    scored = run.scored
    np.testing.assert_array_equal(scored, offline.topk.has_window)
    np.testing.assert_array_equal(run.indices[scored, :k], offline.topk.indices[scored, :k])
    finite = np.isfinite(offline.topk.distances[scored, :k])
    np.testing.assert_allclose(run.distances[scored, :k][finite], offline.topk.distances[scored, :k][finite],
                               rtol=1e-5, atol=1e-6)


@settings(max_examples=examples(25), deadline=None)
@given(st.integers(1, 30), st.integers(2, 30), st.integers(1, 6), st.integers(0, 2**31 - 1))
def test_streaming_equals_offline_causal_matching(n_query, n_map, length, seed):
    rng = np.random.default_rng(seed)
    map_rows, query_rows = rng.normal(size=(n_map, 6)), rng.normal(size=(n_query, 6))
    map_segments, query_segments = np.sort(rng.integers(0, 3, n_map)), np.sort(rng.integers(0, 3, n_query))
    with tempfile.TemporaryDirectory() as tmp:
        save_traversal_npz(Path(tmp) / "ref.npz", traversal(map_rows, map_segments, "ref"))
        saved = build_map([str(Path(tmp) / "ref.npz")], Path(tmp) / "m")
        query = traversal(query_rows, query_segments, "qry")
        if length > np.unique(map_segments, return_counts=True)[1].max():  # a window that is never complete
            raises_one_line(f"seq_len {length} is longer than every segment", Localizer.open, saved, seq_len=length)
            return
        run = replay(Localizer.open(saved, seq_len=length, k=4), query)
        if not (run.scored.any()):
            return  # no window anywhere: the offline kernel refuses such a query (L longer than every segment)
        try:
            offline = SequenceMatcher(MatchSettings(SequenceSpec(length, "causal"), k=4)).topk(saved, query)
        except Exception:  # the map has no window of L frames: then no frame may be localised either
            assert (run.best[run.scored] == -1).all()
            return
        assert_same_as_offline(run, offline, min(4, n_map))


def test_the_filter_streams_what_the_offline_hmm_method_gives(route):
    saved = open_map(route / "map")
    query = load_traversal(route / "qry.npz", "query")
    run = replay(Localizer.open(saved, method="hmm", k=5), query)
    offline = match_method("hmm", saved.frames, query, MatchSettings(k=5))
    np.testing.assert_array_equal(run.indices, offline.topk.indices)
    np.testing.assert_allclose(run.distances, offline.topk.distances, atol=1e-6)  # one-row vs blocked GEMM rounding
    assert not (run.status == "warming up").any()


def test_a_flat_shortlist_as_wide_as_the_map_is_exact(route, tmp_path):
    saved = build_map([str(route / "ref.npz")], tmp_path / "m")
    add_index(saved, IndexSpec("flat"))
    saved = open_map(tmp_path / "m")
    query = load_traversal(route / "qry.npz", "query")
    exact = replay(Localizer.open(saved, k=5), query)
    wide = replay(Localizer.open(saved, k=5, shortlist=150), query)
    np.testing.assert_array_equal(wide.indices, exact.indices)
    np.testing.assert_allclose(wide.distances, exact.distances, rtol=1e-5)
    narrow = replay(Localizer.open(saved, k=5, shortlist=2, history=8), query)
    assert (narrow.best[narrow.scored] >= 0).all()


def test_a_saved_state_resumes_exactly(route, tmp_path):
    saved = open_map(route / "map")
    frames = load_traversal(route / "qry.npz", "query").descriptors
    for options in ({}, {"method": "hmm"}):
        whole = Localizer.open(saved, **options)
        first = Localizer.open(saved, **options)
        for row in frames[:40]:
            whole.update(row), first.update(row)
        first.save_state(tmp_path / "state.npz")
        resumed = Localizer.open(saved, **options)
        resumed.restore(tmp_path / "state.npz")
        for row in frames[40:60]:
            a, b = whole.update(row), resumed.update(row)
            assert (a.index, a.status, a.frame) == (b.index, b.status, b.frame) and abs(a.score - b.score) < 1e-12
    raises_one_line("saved with other settings", Localizer.open(saved, seq_len=3).restore, tmp_path / "state.npz")
    (tmp_path / "junk.npz").write_bytes(b"junk")
    raises_one_line("not readable as a localiser state", Localizer.open(saved).restore, tmp_path / "junk.npz")


def test_lost_is_a_state_and_the_route_is_found_again(route):
    saved = open_map(route / "map")
    query = load_traversal(route / "qry.npz", "query").descriptors
    rng = np.random.default_rng(0)
    off_map = rng.normal(size=(15, 16)).astype(np.float32) * 3  # kidnapped somewhere the map never saw
    localizer = Localizer.open(saved, threshold=0.05, lost_after=3)
    statuses = [localizer.update(row).status for row in query[:40]]
    assert statuses[:4] == ["warming up"] * 4 and "localised" in statuses
    lost = [localizer.update(row) for row in off_map]
    assert lost[-1].status == "lost" and lost[-1].index is None and lost[-1].best >= 0
    back = [localizer.update(row) for row in query[60:100]]
    assert any(e.status == "localised" for e in back[10:])


def test_bad_frames_are_one_line_and_the_localizer_goes_on(route):
    localizer = Localizer.open(open_map(route / "map"))
    query = load_traversal(route / "qry.npz", "query").descriptors
    for row in query[:6]:
        localizer.update(row)
    raises_one_line("holds 16-D frames", localizer.update, np.zeros(8, np.float32))
    raises_one_line("NaN or infinite", localizer.update, np.full(16, np.nan, np.float32))
    raises_one_line("takes a descriptor [D]", localizer.update, np.zeros((4, 4, 3), np.uint8))
    for kind in (np.int64, bool, np.complex64):
        raises_one_line("must be floating point", localizer.update, query[6].astype(kind))
    assert localizer.update(query[6].tolist()).frame == 6  # numbers as a list: the frame it is; the bad ones left
    raises_one_line("threshold must be a finite number", Localizer.open, route / "map", threshold=float("nan"))
    raises_one_line("takes no shortlist", Localizer.open, route / "map", method="hmm", shortlist=5)
    raises_one_line("needs an index over", Localizer.open, route / "map", shortlist=5)
    raises_one_line("not method delta", Localizer.open, route / "map", method="delta")


def test_keyframe_gating_skips_a_stopped_robot(route):
    localizer = Localizer.open(open_map(route / "map"), keyframe_distance=0.05)
    query = load_traversal(route / "qry.npz", "query").descriptors
    estimates = [localizer.update(row) for row in [*query[:8], *[query[8]] * 5, *query[9:12]]]
    assert [e.kept for e in estimates[8:13]] == [True, False, False, False, False]
    assert estimates[12].index == estimates[8].index and estimates[12].frame == 12


def test_an_estimate_keeps_its_values_while_later_frames_reuse_the_buffers(route):
    """Each frame goes into a reused row and ring: what an earlier estimate holds never changes, and the row
    keyframe gating compares against is the last kept frame's."""
    query = load_traversal(route / "qry.npz", "query").descriptors
    localizer = Localizer.open(open_map(route / "map"), keyframe_distance=0.05)
    estimates, copies = [], []
    for row in [*query[:10], query[9], query[9], *query[10:20]]:
        estimates.append(localizer.update(row))
        copies.append((estimates[-1].indices.copy(), estimates[-1].distances.copy()))
    for estimate, (indices, distances) in zip(estimates, copies):
        np.testing.assert_array_equal(estimate.indices, indices)
        np.testing.assert_array_equal(estimate.distances, distances)
    assert [e.kept for e in estimates[9:13]] == [True, False, False, True]
    np.testing.assert_array_equal(localizer.last_kept.numbers, localizer.matcher.prepare_frame(query[19]).numbers)
    fresh = Localizer.open(open_map(route / "map"))
    ungated = [fresh.update(row) for row in query[:20]]
    np.testing.assert_array_equal(ungated[-1].indices, estimates[-1].indices)


def test_camera_frames_are_described_as_the_map_was(tmp_path):
    rng = np.random.default_rng(3)
    for side in ("ref", "qry"):
        (tmp_path / side).mkdir()
        for i in range(12):
            pixels = rng.integers(0, 255, (48, 80, 3), dtype=np.uint8)
            Image.fromarray(pixels).save(tmp_path / side / f"{i:03d}.png")
    saved = build_map([str(tmp_path / "ref")], tmp_path / "m")
    query = load_traversal(tmp_path / "qry", "query")
    from_images = replay(Localizer.open(saved, seq_len=3), query)
    from_descriptors = replay(Localizer.open(saved, seq_len=3), describe(query))
    np.testing.assert_array_equal(from_images.indices, from_descriptors.indices)
    np.testing.assert_allclose(from_images.score, from_descriptors.score, atol=1e-6)
    array = np.asarray(Image.open(tmp_path / "qry" / "000.png"))
    localizer = Localizer.open(saved, seq_len=1)
    assert localizer.update(array).best == localizer.update(tmp_path / "qry" / "000.png").best


def test_only_a_localized_estimate_names_a_map_frame_a_position_and_a_name(tmp_path):
    rng = np.random.default_rng(3)
    folder = tmp_path / "map_images"
    folder.mkdir()
    images = [rng.integers(0, 255, (24, 32, 3), dtype=np.uint8) for _ in range(30)]
    for i, image in enumerate(images):
        Image.fromarray(image).save(folder / f"{i:03d}.png")
    (folder / "positions.csv").write_text("name,easting,northing\n" + "".join(f"{i:03d}.png,{5.0 * i},1.0\n"
                                                                             for i in range(30)))
    saved = build_map([str(folder)], tmp_path / "map")
    localizer = Localizer.open(saved, seq_len=3, threshold=0.3, lost_after=3)
    noise = [rng.integers(0, 255, (24, 32, 3), dtype=np.uint8) for _ in range(8)]
    estimates = [localizer.update(image) for image in images[:12] + noise]
    statuses = {e.status for e in estimates}
    assert statuses == {"warming up", "localised", "uncertain", "lost"}
    for e in estimates:
        if e.status == "localised":
            assert e.localized and e.index == e.best and e.position == (5.0 * e.index, 1.0)
            assert e.name.endswith(f"{e.index:03d}.png")
        else:
            assert not e.localized and (e.index, e.position, e.name, e.latlon) == (None, None, None, None)
    assert all(e.best is None and np.isnan(e.score) for e in estimates if e.status == "warming up")
    assert all(e.best is not None for e in estimates if e.status in ("uncertain", "lost"))


@pytest.mark.parametrize("gate", [0.0, 0.05])
def test_restatus_gives_what_a_run_at_that_threshold_gives(route, gate):
    from seqvpr.localization.replay import at_threshold

    saved = open_map(route / "map")
    query = load_traversal(route / "qry.npz", "query")
    query = query.select(np.r_[0:50, 70:120])  # a segment break: the localiser restarts there
    run = replay(Localizer.open(saved, threshold=0.02, lost_after=3, keyframe_distance=gate), query)
    again = replay(Localizer.open(saved, threshold=0.2, lost_after=3, keyframe_distance=gate), query)
    moved = at_threshold(run, 0.2, 3, "another")
    assert len(set(again.status)) >= 3 and moved.threshold == 0.2 and moved.threshold_source == "another"
    np.testing.assert_array_equal(moved.status, again.status)
    np.testing.assert_array_equal(moved.index, again.index)


@pytest.mark.slow
def test_a_localizer_over_a_descriptor_map_imports_only_what_it_runs(route):
    code = f"""
import sys
import numpy as np
from seqvpr.localization import Localizer
localizer = Localizer.open({str(route / "map")!r})
for row in np.load({str(route / "ref.npz")!r})["descriptors"][:8]:
    localizer.update(row.astype(np.float32))
loaded = sorted(m for m in sys.modules if m.split(".")[0] in ("matplotlib", "faiss", "PIL", "rosbags")
                or m.startswith(("scipy.io", "scipy.spatial", "scipy.sparse"))  # numba imports bare scipy
                or m.startswith(("seqvpr.models", "seqvpr.features",
                                 "seqvpr.training", "seqvpr.evaluation", "seqvpr.maps.build", "seqvpr.maps.match",
                                 "seqvpr.data.sources", "seqvpr.data.loaders")))
print(sorted({{m.split(".")[0] for m in loaded}} | {{m for m in loaded if m.startswith("seqvpr")}}))
"""
    import subprocess
    import sys

    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip().splitlines()[-1] == "[]"


def test_a_map_built_through_seqmatchnet_takes_untransformed_frames_and_streams_the_offline_match(route, tmp_path):
    """The localiser applies the map's SeqMatchNet transform itself, once, to the frames it is given (of the
    model's input size): its stream is the offline causal match of the same map."""
    import seqvpr
    from seqvpr.models.configs import TransformConfig
    from seqvpr.models.registry import load_trained_model
    from seqvpr.models.seqmatchnet import FrameTransform, save_seqmatchnet

    save_seqmatchnet(tmp_path / "smn", FrameTransform(TransformConfig(16, out_dim=8), seed=3),
                     {"sequence": {"length": 4}})
    build_map([str(route / "ref.npz")], tmp_path / "map", models={"seqmatchnet": load_trained_model(tmp_path / "smn")})
    query = load_traversal(route / "qry.npz", "query")
    run = replay(Localizer.open(tmp_path / "map", tmp_path / "smn", seq_len=4, k=5), query)
    offline = seqvpr.match(tmp_path / "map", query, "seqmatchnet", models=[tmp_path / "smn"], seq_len=4, k=5,
                           align="causal")
    assert_same_as_offline(run, offline, 5)
    localizer = Localizer.open(tmp_path / "map", tmp_path / "smn", seq_len=4)
    raises_one_line("holds frames of 16-D descriptors through its SeqMatchNet model", localizer.update,
                    np.ones(8, np.float32))
