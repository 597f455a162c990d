"""Saved maps, shards and indexes tampered with as a hostile or unlucky user would: each is one line naming the
file with exit 2 (never exit 0 with a wrong result), or, where the tampering is harmless, the correct result. One
row a case: how the saved map is spoiled, and a fragment of the one error line (None: harmless)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from seqvpr.data.sources import save_traversal_npz
from seqvpr.synthetic.routes import generate_route
from tests.helpers import QuietCapsys, raises_one_line, run_cli, write_route_files


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """Two routes of one shape (ours and another), each built as a map of every storage, indexed, and sharded."""
    w = tmp_path_factory.mktemp("maps")
    write_route_files(w, 300, 16, 2)
    other, _ = generate_route(n_frames=300, dim=16, seed=9)
    save_traversal_npz(w / "other.npz", other)
    mp, cp = pytest.MonkeyPatch(), QuietCapsys()
    for name, source in (("good", "ref.npz"), ("other", "other.npz")):
        for suffix, extra in (("", ()), ("_sq8", ("--dtype", "sq8")), ("_pq", ("--dtype", "pq:4")),
                              ("_idx", ("--index", "flat")), ("_sh", ("--shards", "2", "--overlap", "4"))):
            args = ("map", "build", w / source, "--out", w / f"{name}{suffix}", *extra)
            assert run_cli(mp, cp, *args)[0] == 0
    return w



def _resave(path, change) -> None:
    """Load an array file, change it, and save it back in place (same shape and dtype)."""
    array = np.load(path)
    change(array)
    np.save(path, array)


def _set_json(path, change) -> None:
    values = json.loads(path.read_text())
    change(values)
    path.write_text(json.dumps(values))


def _nan_row(a):
    a[5] = np.nan


def _swap_shards(m, w):
    os.rename(m / "shard-000", m / "tmp")
    os.rename(m / "shard-001", m / "shard-000")
    os.rename(m / "tmp", m / "shard-001")


def _foreign_shard(m, w):
    shutil.rmtree(m / "shard-001")
    shutil.copytree(w / "other_sh" / "shard-001", m / "shard-001")


def _shift_first(values):
    values["shards"][1]["first"] += 1


#: case -> (the map it starts from, how it is spoiled (map folder, world) -> None, fragment or None if harmless)
CASES = {
    "map: a row set to NaN": ("good", lambda m, w: _resave(m / "descriptors.npy", _nan_row), "descriptors.npy: its content is not what"),
    "map: an inf row": ("good", lambda m, w: _resave(m / "descriptors.npy", lambda a: a.__setitem__(3, np.inf)), "descriptors.npy: its content"),
    "map: rows scaled in a normalised map": ("good", lambda m, w: _resave(m / "descriptors.npy", lambda a: a.__imul__(3)), "descriptors.npy: its content"),
    "map: descriptors copied from another map of the same shape": ("good", lambda m, w: shutil.copyfile(w / "other" / "descriptors.npy", m / "descriptors.npy"), "descriptors.npy: its content"),
    "map: descriptors symlinked from another map": ("good", lambda m, w: (os.unlink(m / "descriptors.npy"), os.symlink(w / "other" / "descriptors.npy", m / "descriptors.npy")), "descriptors.npy: its content"),
    "map: segments rewritten": ("good", lambda m, w: _resave(m / "segments.npy", lambda a: a.__setitem__(slice(40, None), 7)), "segments.npy: its content"),
    "map: positions shifted": ("good", lambda m, w: _resave(m / "positions.npy", lambda a: a.__iadd__(50)), "positions.npy: its content"),
    "map: a file removed": ("good", lambda m, w: os.unlink(m / "frame_index.npy"), "frame_index.npy: missing"),
    "map: map.json's digests edited": ("good", lambda m, w: _set_json(m / "map.json", lambda v: v["files"].update({"segments.npy": "sha256:00"})), "do not agree"),
    "map: map.json names a file outside the folder": ("good", lambda m, w: _set_json(m / "map.json", lambda v: v["files"].update({"../x.npy": "sha256:00"})), "do not agree"),
    "sq8: quantizer with NaN": ("good_sq8", lambda m, w: _resave(m / "quantizer.npy", lambda a: a.__setitem__((1, 3), np.nan)), "quantizer.npy: its content"),
    "sq8: quantizer copied from another map": ("good_sq8", lambda m, w: shutil.copyfile(w / "other_sq8" / "quantizer.npy", m / "quantizer.npy"), "quantizer.npy: its content"),
    "pq: centroids with NaN": ("good_pq", lambda m, w: _resave(m / "pq_centroids.npy", lambda a: a.__setitem__(0, np.nan)), "pq_centroids.npy: its content"),
    "index: copied from another map of the same shape": ("good_idx", lambda m, w: shutil.copyfile(w / "other_idx" / "index.faiss", m / "index.faiss"), "index.faiss: its content"),
    "index: symlinked from another map": ("good_idx", lambda m, w: (os.unlink(m / "index.faiss"), os.symlink(w / "other_idx" / "index.faiss", m / "index.faiss")), "index.faiss: its content"),
    "index: map.json's index path leaves the folder": ("good_idx", lambda m, w: _set_json(m / "map.json", lambda v: v["index"].update(file="../other_idx/index.faiss")), "not inside the map folder"),
    "index: map.json's index names another map's rows": ("good_idx", lambda m, w: _set_json(m / "map.json", lambda v: v["index"].update(map="sha256:00")), "built over other rows"),
    "shards: two shard folders swapped": ("good_sh", _swap_shards, "not the shard"),
    "shards: a shard copied from another map": ("good_sh", _foreign_shard, "not the shard"),
    "shards: a shard's first row shifted": ("good_sh", lambda m, w: _set_json(m / "shards.json", _shift_first), "not the shard"),
    "shards: a shard folder outside the map": ("good_sh", lambda m, w: _set_json(m / "shards.json", lambda v: v["shards"][0].update(folder="../good")), "not inside the sharded map"),
    "shards: a shard's rows tampered": ("good_sh", lambda m, w: _resave(m / "shard-001" / "descriptors.npy", _nan_row), "descriptors.npy: its content"),
    # harmless: the same bytes, so the same result
    "harmless: descriptors touched": ("good", lambda m, w: os.utime(m / "descriptors.npy", (1, 1)), None),
    "harmless: descriptors rewritten with the same bytes": ("good", lambda m, w: (m / "descriptors.npy").write_bytes((m / "descriptors.npy").read_bytes()), None),
    "harmless: an index symlinked to its own bytes elsewhere": ("good_idx", lambda m, w: (shutil.copyfile(m / "index.faiss", w.parent / f"idx-{time.time_ns()}"), os.unlink(m / "index.faiss"), os.symlink(sorted(w.parent.glob("idx-*"))[-1], m / "index.faiss")), None),
}


def _match(monkeypatch, capsys, folder, out, *extra):
    return run_cli(monkeypatch, capsys, "match", "--map", folder, "-q", folder.parent.parent / "qry.npz", "--radius",
                   "10m", "-L", "3", "--out", out, *extra)


@pytest.mark.parametrize("case", list(CASES))
def test_a_tampered_map_is_one_line_or_the_right_result(world, tmp_path, monkeypatch, capsys, case):
    start, spoil, fragment = CASES[case]
    folder = tmp_path / "maps" / start
    folder.parent.mkdir()
    shutil.copytree(world / start, folder, symlinks=True)
    monkeypatch.chdir(world)
    shutil.copy(world / "qry.npz", tmp_path / "qry.npz")
    extra = ("--shortlist", "20") if start.endswith("_idx") else ()
    assert _match(monkeypatch, capsys, folder, tmp_path / "before", *extra)[0] == 0
    spoil(folder, world)
    code, _, err = _match(monkeypatch, capsys, folder, tmp_path / "after", *extra)
    if fragment is None:
        assert code == 0, err
        before, after = ((tmp_path / d / "predictions.csv").read_text() for d in ("before", "after"))
        assert before == after
        return
    lines = [line for line in err.strip().splitlines() if line.startswith("seqvpr: error")]
    assert code == 2 and len(lines) == 1 and fragment in lines[0], err
    code, _, err = run_cli(monkeypatch, capsys, "map", "check", folder)
    assert code == 2 and "seqvpr: error" in err, err


def test_map_check_passes_every_good_map_and_reads_every_file(world, monkeypatch, capsys):
    for name in ("good", "good_sq8", "good_pq", "good_idx", "good_sh"):
        code, out, err = run_cli(monkeypatch, capsys, "map", "check", world / name)
        assert code == 0 and out.strip().endswith("ok"), err
    assert "index: flat over frames, 300 vectors" in run_cli(monkeypatch, capsys, "map", "check", world / "good_idx")[1]


def test_a_map_copied_elsewhere_opens_and_matches_alike(world, tmp_path):
    from seqvpr.maps import open_map

    shutil.copytree(world / "good", tmp_path / "copy")
    np.testing.assert_array_equal(open_map(tmp_path / "copy").descriptors[:], open_map(world / "good").descriptors[:])


def test_an_older_map_without_identity_opens_with_a_warning(world, tmp_path):
    from seqvpr.errors import SeqvprWarning
    from seqvpr.maps import open_map

    shutil.copytree(world / "good", tmp_path / "old")
    _set_json(tmp_path / "old" / "map.json", lambda v: v.update(version=1, files=None, identity=None))
    with pytest.warns(SeqvprWarning, match="records no content identity"):
        assert open_map(tmp_path / "old").info.count == 300


def test_rows_are_checked_before_a_map_is_written(world, tmp_path):
    from seqvpr.data.traversal import Traversal
    from seqvpr.maps.build import map_sources
    from seqvpr.maps.files import MapInfo, write_map

    rows = np.eye(6, 4, dtype=np.float32)
    frames = Traversal.from_descriptors(rows, "t")
    info = lambda normal: MapInfo(6, 4, "float32", normal, {"descriptor": "file"}, map_sources([frames], ["t"]))  # noqa: E731
    rows[2, 1] = np.nan
    raises_one_line("row 2 is not finite", write_map, tmp_path / "m", frames, info(False))
    rows[2, 1] = 3.0
    raises_one_line("row 2 has length 3", write_map, tmp_path / "m", frames, info(True))
    assert not (tmp_path / "m").exists()


def test_a_name_with_a_line_separator_leaves_the_old_map(world, tmp_path):
    from seqvpr.data.traversal import Traversal
    from seqvpr.maps import open_map
    from seqvpr.maps.build import map_sources
    from seqvpr.maps.files import MapInfo, write_map

    shutil.copytree(world / "good", tmp_path / "m")
    frames = Traversal.from_descriptors(np.eye(3, 4, dtype=np.float32), "t")
    frames = Traversal(frames.name, frames.frame_index, frames.segment_ids, frames.descriptors,
                       tuple(Path(n) for n in ("a.png", "b\u2028c.png", "d.png")))
    info = MapInfo(3, 4, "float32", True, {"descriptor": "file"}, map_sources([frames], ["t"]))
    raises_one_line("frame 1's name", write_map, tmp_path / "m", frames, info)
    assert open_map(tmp_path / "m").info.count == 300


def test_a_failed_index_leaves_the_previous_map(world, tmp_path, monkeypatch, capsys):
    import seqvpr.maps.index as index_module
    from seqvpr.errors import SeqvprError
    from seqvpr.maps import open_map

    shutil.copytree(world / "good_idx", tmp_path / "m")
    before = (tmp_path / "m" / "map.json").read_text()

    def broken(*args, **kwargs):
        raise SeqvprError("the index could not be built (injected)")

    monkeypatch.setattr(index_module, "build_frame_index", broken)
    code, _, err = run_cli(monkeypatch, capsys, "map", "build", world / "other.npz", "--out", tmp_path / "m",
                           "--index", "flat")
    assert code == 2 and "injected" in err
    assert (tmp_path / "m" / "map.json").read_text() == before and open_map(tmp_path / "m").info.index
    assert not [p for p in tmp_path.iterdir() if ".seqvpr-" in p.name]


def test_an_index_is_never_paired_with_rows_rebuilt_since(world, tmp_path, monkeypatch, capsys):
    from seqvpr.maps import build_map, open_map
    from seqvpr.maps.index import IndexSpec, add_index

    shutil.copytree(world / "good", tmp_path / "m")
    opened = open_map(tmp_path / "m")
    build_map([str(world / "other.npz")], tmp_path / "m")  # rebuilt between the index's open and its build
    raises_one_line("the map was rebuilt since it was opened", add_index, opened, IndexSpec("flat"))
    assert open_map(tmp_path / "m").info.index is None


@pytest.mark.slow
def test_map_index_waits_for_no_one_while_a_build_holds_the_map(world, tmp_path, monkeypatch, capsys):
    """A concurrent ``map build`` holds the map's lock: ``map index`` is one line naming that process."""
    shutil.copytree(world / "good", tmp_path / "m")
    holder = subprocess.Popen([sys.executable, "-c", "import sys, time; from seqvpr.io import output_lock\n"
                               "with output_lock(sys.argv[1]):\n print('held', flush=True); time.sleep(60)",
                               str(tmp_path / "m")], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        code, _, err = run_cli(monkeypatch, capsys, "map", "index", tmp_path / "m", "--index", "flat")
        assert code == 2 and f"process {holder.pid}" in err, err
    finally:
        holder.kill()
        holder.wait()
    assert run_cli(monkeypatch, capsys, "map", "index", tmp_path / "m", "--index", "flat")[0] == 0
