"""A matcher added as one class (``ToyMatcher``: one window distance) and one method record runs in every mode that
``matchers.assemble`` stacks, offline and a frame at a time: alone, shortlisted, sharded (one process, two torchrun
ranks) and shortlisted-sharded, each equal to a plain loop over the windows; nothing else in seqvpr knows of it."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import torch

from seqvpr.data.traversal import Traversal
from seqvpr.maps.files import ShardRecord
from seqvpr.sequences.match_settings import MatchSettings
from seqvpr.matchers import Shortlist, assemble
from seqvpr.matchers.shortlisted import ExactNeighbors
from seqvpr.matchers.window_matcher import WindowMatcher
from seqvpr.methods import METHODS, Method, build_matcher
from seqvpr.sequences.windows import SequenceSpec
from seqvpr.synthetic.routes import generate_route

ROOT = Path(__file__).resolve().parents[2]


class ToyMatcher(WindowMatcher):
    """Mean L1 distance of order-aligned frames: a distance no method of seqvpr uses."""

    def distances(self, reference_windows: torch.Tensor, query_window: torch.Tensor) -> torch.Tensor:
        return (reference_windows - query_window[None]).abs().sum(-1).mean(-1)


TOY = Method("toy", "matching", "mean L1 distance of aligned frames", matcher=f"{__name__}:ToyMatcher")


@dataclass(frozen=True)
class ToyShards:
    """A traversal cut into overlapping shards, in memory (what a sharded map is on disk)."""

    reference: Traversal
    count: int
    overlap: int
    shards: tuple[ShardRecord, ...]
    folder: str = "toy-shards"

    @classmethod
    def cut(cls, reference: Traversal, shards: int, overlap: int) -> ToyShards:
        bounds = [len(reference) * i // shards for i in range(shards + 1)]
        ranges = tuple(ShardRecord(f"shard-{i}", max(0, a - overlap), a, b)
                       for i, (a, b) in enumerate(zip(bounds, bounds[1:])))
        return cls(reference, len(reference), overlap, ranges)

    def __len__(self) -> int:
        return self.count

    def open_shard(self, number: int) -> Traversal:
        record = self.shards[number]
        return self.reference.select(np.arange(record.first, min(self.count, record.own_last + self.overlap)))

    @property
    def frames(self) -> Traversal:
        return self.reference

    def as_map(self) -> Traversal:
        return self.reference


def route(seed: int = 3) -> tuple[Traversal, Traversal]:
    reference, query = generate_route(n_frames=70, dim=6, seed=seed)
    return reference.select(np.r_[0:33, 36:70]), query  # a segment break in the reference


def settings(length: int, k: int = 6) -> MatchSettings:
    return MatchSettings(SequenceSpec(length, "causal"), k=k, normalize=False)


def window_exists(segments: np.ndarray, anchor: int, length: int) -> bool:
    start = anchor - length + 1
    return start >= 0 and segments[start] == segments[anchor]


def oracle(reference: Traversal, query: Traversal, length: int, k: int, candidates=None, segments=None):
    """Per query frame, the best K reference windows ending at a row (or among ``candidates[i]``), by the mean L1
    distance of aligned frames, ties to the lower row: a plain loop."""
    ref, qry = reference.descriptors.astype(np.float64), query.descriptors.astype(np.float64)
    q_seg = query.segment_ids if segments is None else segments
    out = []
    for i in range(len(query)):
        if not window_exists(q_seg, i, length):
            out.append(([], []))
            continue
        rows = range(len(reference)) if candidates is None else sorted(candidates[i])
        scored = []
        for r in rows:
            if window_exists(reference.segment_ids, r, length):
                d = np.mean([np.abs(ref[r - length + 1 + j] - qry[i - length + 1 + j]).sum() for j in range(length)])
                scored.append((d, r))
        scored.sort()
        out.append(([r for _, r in scored[:k]], [d for d, _ in scored[:k]]))
    return out


def assert_rows_equal(indices: np.ndarray, distances: np.ndarray, expected) -> None:
    for row, (rows, values) in enumerate(expected):
        np.testing.assert_array_equal(indices[row][: len(rows)], rows, err_msg=f"query {row}")
        assert (indices[row][len(rows):] == -1).all()
        np.testing.assert_allclose(distances[row][: len(rows)], values, rtol=1e-5)


def nearest(reference: Traversal, frame: np.ndarray, width: int) -> list[int]:
    distances = np.linalg.norm(reference.descriptors.astype(np.float64) - frame, axis=1)
    return [int(r) for r in np.lexsort((np.arange(len(distances)), distances))[:width]]


def shortlist_oracle(reference: Traversal, query: Traversal, length: int, width: int, history: int, stream: bool):
    """The candidate windows of each query frame: each frame of its window, and the ``history`` before it, places
    its ``width`` nearest reference frames' windows (slope 1)."""
    found = [nearest(reference, frame, width) for frame in query.descriptors.astype(np.float64)]
    candidates = []
    for i in range(len(query)):
        chosen = set()
        for lag in range(length + history):
            f = i - lag
            if f < 0 or (not stream and query.segment_ids[f] != query.segment_ids[i]):
                continue
            chosen.update(r + lag for r in found[f] if r + lag < len(reference))
        candidates.append(chosen)
    return candidates


@pytest.fixture
def toy(monkeypatch):
    monkeypatch.setitem(METHODS, "toy", TOY)  # the one record


def streamed(stepper, matcher, query: Traversal, k: int):
    indices, distances = np.full((len(query), k), -1), np.full((len(query), k), np.inf)
    for row, frame in enumerate(query.descriptors):
        scored = stepper.push(matcher.prepare_frame(frame))
        if scored is not None:
            indices[row, : len(scored.indices)], distances[row, : len(scored.indices)] = scored.indices, scored.distances
    return indices, distances


@pytest.mark.parametrize("length", [1, 4])
def test_the_toy_matcher_offline_and_a_frame_at_a_time_is_the_plain_loop(toy, length):
    reference, query = route()
    matcher = build_matcher("toy", settings(length))
    assert isinstance(matcher, ToyMatcher)
    top = matcher.topk(reference, query).topk
    assert_rows_equal(top.indices, top.distances, oracle(reference, query, length, 6))
    indices, distances = streamed(matcher.stream(reference), matcher, query, 6)
    assert_rows_equal(indices, distances, oracle(reference, query, length, 6, segments=np.zeros(len(query), int)))


@pytest.mark.parametrize("length, width, history", [(3, 2, 0), (4, 3, 2)])
def test_the_toy_matcher_shortlisted_is_the_plain_loop_over_the_candidates(toy, length, width, history):
    reference, query = route(5)
    matcher = build_matcher("toy", settings(length))
    shortlisted = assemble(matcher, reference, Shortlist(lambda: ExactNeighbors(reference.descriptors), width, history))
    top = shortlisted.topk(reference, query).topk
    candidates = shortlist_oracle(reference, query, length, width, history, stream=False)
    assert_rows_equal(top.indices, top.distances, oracle(reference, query, length, 6, candidates))
    indices, distances = streamed(shortlisted.stream(reference), matcher, query, 6)
    candidates = shortlist_oracle(reference, query, length, width, history, stream=True)
    assert_rows_equal(indices, distances, oracle(reference, query, length, 6, candidates, np.zeros(len(query), int)))


@pytest.mark.parametrize("shards, overlap", [(3, 3), (4, 5)])
def test_the_toy_matcher_sharded_in_one_process_is_the_plain_loop(toy, shards, overlap):
    reference, query = route(7)
    matcher = build_matcher("toy", settings(4))
    cut = ToyShards.cut(reference, shards, overlap)
    top = assemble(matcher, cut).topk(cut, query).topk
    assert_rows_equal(top.indices, top.distances, oracle(reference, query, 4, 6))
    indices, distances = streamed(assemble(matcher, cut).stream(cut), matcher, query, 6)
    assert_rows_equal(indices, distances, oracle(reference, query, 4, 6, segments=np.zeros(len(query), int)))


@pytest.mark.parametrize("shards, overlap, width, history", [(3, 3, 2, 0), (4, 5, 3, 2)])
def test_the_toy_matcher_shortlisted_and_sharded_is_the_plain_loop_over_the_candidates(toy, shards, overlap, width,
                                                                                      history):
    reference, query = route(9)
    matcher = build_matcher("toy", settings(4))
    cut = ToyShards.cut(reference, shards, overlap)
    stack = assemble(matcher, cut, Shortlist(lambda: ExactNeighbors(reference.descriptors), width, history))
    top = stack.topk(cut, query).topk
    candidates = shortlist_oracle(reference, query, 4, width, history, stream=False)
    assert_rows_equal(top.indices, top.distances, oracle(reference, query, 4, 6, candidates))
    indices, distances = streamed(stack.stream(cut), matcher, query, 6)
    candidates = shortlist_oracle(reference, query, 4, width, history, stream=True)
    assert_rows_equal(indices, distances, oracle(reference, query, 4, 6, candidates, np.zeros(len(query), int)))


TORCHRUN_SCRIPT = """
import sys
sys.path.insert(0, {root!r})
import numpy as np
from seqvpr import distributed
from seqvpr.matchers import assemble
from seqvpr.methods import METHODS, build_matcher
from tests.matchers.test_toy_matcher import TOY, ToyShards, route, settings

METHODS["toy"] = TOY
reference, query = route(7)
with distributed.process_group("cpu") as world:
    shards = ToyShards.cut(reference, 3, 3)
    result = assemble(build_matcher("toy", settings(4)), shards, ranks=world).topk(shards, query)
    if world.is_root:
        np.savez({out!r}, indices=result.topk.indices, distances=result.topk.distances)
    else:
        assert result is None
"""


@pytest.mark.slow
def test_the_toy_matcher_sharded_over_two_torchrun_ranks_is_the_plain_loop(tmp_path):
    script = tmp_path / "toy.py"
    script.write_text(TORCHRUN_SCRIPT.format(root=str(ROOT), out=str(tmp_path / "top.npz")))
    bin_dir = Path(sys.executable).parent
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PATH": f"{bin_dir}{os.pathsep}{os.environ.get('PATH', '')}"}
    launcher = [shutil.which("torchrun", path=env["PATH"]), "--standalone", "--nproc-per-node", "2"]
    done = subprocess.run([*launcher, str(script)], cwd=tmp_path, env=env, capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    found = np.load(tmp_path / "top.npz")
    reference, query = route(7)
    assert_rows_equal(found["indices"], found["distances"], oracle(reference, query, 4, 6))
