"""Maps that grow: a map built from A and grown by B (``map add``) holds what a map built from A and B at once holds
(rows, names, positions, segments, sources; a frame index extended, a window index rebuilt) and matches alike,
for float32, float16 and sq8; a failure while the
grown map is committed leaves the old map byte for byte; what does not fit the map is one line."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from seqvpr.data.sources import save_traversal_npz
from seqvpr.data.traversal import Traversal
from seqvpr.maps import build_map
from seqvpr.maps.files import open_map
from seqvpr.maps.grow import add_to_map
from seqvpr.maps.parts import sessions_of
from tests.helpers import raises_one_line


def drive(rng, n: int, name: str, dim: int = 16) -> Traversal:
    rows = rng.normal(size=(n, dim))
    return Traversal(name, np.arange(n), np.sort(rng.integers(0, 2, n)), rows.astype(np.float32),
                     positions=np.cumsum(rng.normal(size=(n, 2)), axis=0), timestamps=np.arange(n, dtype=float),
                     source=name)


@pytest.fixture
def files(tmp_path):
    rng = np.random.default_rng(0)
    a, b = drive(rng, 60, "a"), drive(rng, 30, "b")
    b = Traversal("b", b.frame_index, b.segment_ids, a.descriptors[rng.permutation(60)[:30]] * 2.0,
                  positions=b.positions, timestamps=b.timestamps, source="b")  # a's frames: inside its sq8 range
    c = drive(rng, 20, "c")
    spiked = c.descriptors.copy()
    spiked[:, 0] = 100.0  # one dimension far outside a's range
    save_traversal_npz(tmp_path / "a.npz", a)
    save_traversal_npz(tmp_path / "b.npz", b)
    save_traversal_npz(tmp_path / "c.npz", Traversal("c", c.frame_index, c.segment_ids, spiked, source="c"))
    save_traversal_npz(tmp_path / "d32.npz", drive(rng, 20, "d", dim=32))
    return tmp_path


def folder_bytes(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir()) if p.is_file()}


@pytest.mark.parametrize("dtype", ["float32", "float16", "sq8"])
def test_a_map_grown_by_b_is_the_map_of_a_and_b(files, dtype):
    grown = build_map([str(files / "a.npz")], files / "grown", dtype=dtype)
    grown = add_to_map(files / "grown", [str(files / "b.npz")], session="tuesday")
    whole = open_map(build_map([str(files / "a.npz"), str(files / "b.npz")], files / "whole", dtype=dtype).folder)
    np.testing.assert_array_equal(grown.descriptors[:], whole.descriptors[:])
    for column in ("segment_ids", "frame_index", "positions", "timestamps"):
        np.testing.assert_array_equal(getattr(grown.frames, column), getattr(whole.frames, column))
    assert [(s.first, s.frames) for s in grown.info.sources] == [(s.first, s.frames) for s in whole.info.sources]
    assert [s["name"] for s in sessions_of(grown.info)] == ["build", "tuesday"]
    assert grown.info.parts[0] == ("descriptors.npy", 60) and grown.info.parts[1][1] == 30
    import seqvpr

    query = files / "b.npz"
    ours = seqvpr.match(open_map(files / "grown"), str(query), "matching", seq_len=3, k=5)
    theirs = seqvpr.match(open_map(files / "whole"), str(query), "matching", seq_len=3, k=5)
    np.testing.assert_array_equal(ours.topk.indices, theirs.topk.indices)


def test_adding_writes_only_the_new_rows_and_links_the_old(files):
    build_map([str(files / "a.npz")], files / "m")
    before = (files / "m" / "descriptors.npy").stat().st_ino
    add_to_map(files / "m", [str(files / "b.npz")])
    assert (files / "m" / "descriptors.npy").stat().st_ino == before  # the same file, linked, not copied
    assert (files / "m" / "descriptors-001.npy").is_file()


def test_a_failed_commit_leaves_the_old_map_byte_for_byte(files, monkeypatch):
    import seqvpr.maps.grow as grow

    build_map([str(files / "a.npz")], files / "m")
    before = folder_bytes(files / "m")
    for step in ("commit_folder", "keep_users_files", "open_map_tmp"):
        def fail(*args, **kwargs):
            raise OSError(f"{step} failed")
        if step == "commit_folder":
            monkeypatch.setattr(grow, "commit_folder", fail)
        with pytest.raises(OSError):
            if step != "commit_folder":
                monkeypatch.setattr(grow, "_seal", fail)
            add_to_map(files / "m", [str(files / "b.npz")])
        monkeypatch.undo()
        assert folder_bytes(files / "m") == before
        assert not [p for p in files.iterdir() if p.name.endswith(".part")]


def test_what_does_not_fit_the_map_is_one_line(files):
    build_map([str(files / "a.npz")], files / "m", dtype="sq8")
    before = folder_bytes(files / "m")
    raises_one_line("-D", add_to_map, files / "m", [str(files / "d32.npz")])
    raises_one_line("already in the map", add_to_map, files / "m", [str(files / "a.npz")])
    raises_one_line("outside the sq8 map's value range", add_to_map, files / "m", [str(files / "c.npz")])
    assert folder_bytes(files / "m") == before


def test_a_frame_index_gains_the_new_rows_and_a_window_index_is_rebuilt(files):
    import seqvpr
    from seqvpr.maps.index import IndexSpec, add_index

    add_index(build_map([str(files / "a.npz")], files / "m"), IndexSpec("flat"))
    grown = add_to_map(files / "m", [str(files / "b.npz")])
    assert grown.info.index["ntotal"] == 90 and grown.info.index["map"] == grown.info.identity
    exact = seqvpr.match(grown, str(files / "b.npz"), "matching", seq_len=3, k=5)
    listed = seqvpr.match(open_map(files / "m"), str(files / "b.npz"), "matching", seq_len=3, k=5, shortlist=90)
    np.testing.assert_array_equal(listed.topk.indices[:, 0], exact.topk.indices[:, 0])
    add_index(build_map([str(files / "a.npz")], files / "w"), IndexSpec("flat"), windows=3)
    grown = add_to_map(files / "w", [str(files / "b.npz")])
    add_index(build_map([str(files / "a.npz"), str(files / "b.npz")], files / "ab"), IndexSpec("flat"), windows=3)
    whole = open_map(files / "ab")
    assert grown.info.index["ntotal"] == whole.info.index["ntotal"] and grown.info.index["map"] == grown.info.identity
    np.testing.assert_array_equal(np.load(files / "w" / "index_rows.npy"), np.load(files / "ab" / "index_rows.npy"))
    for saved in (grown, whole):  # the rebuilt index finds what the whole map's finds
        found = seqvpr.match(saved, str(files / "b.npz"), "smoothing", seq_len=3, k=5)  # through the index
        np.testing.assert_array_equal(found.topk.indices, seqvpr.match(
            whole, str(files / "b.npz"), "smoothing", seq_len=3, k=5).topk.indices)


def test_a_sharded_map_takes_no_map_add(files):
    from seqvpr.maps import build_sharded_map

    build_sharded_map([str(files / "a.npz")], files / "s", 2, overlap=4)
    raises_one_line("a sharded map takes no map add", add_to_map, files / "s", [str(files / "b.npz")])
