"""A map's frame names memory-mapped: the names written are the names read (any text without a line separator),
slices stay lazy, an old map without the offsets file still opens, and a table that does not fit is one line."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from seqvpr.maps.names import OFFSETS_FILE, FrameNames, FramePaths, open_names, write_names
from tests.helpers import raises_one_line

SEPARATORS = "\n\r\x0b\x0c\x1c\x1d\x1e\x85\u2028\u2029"  # what str.splitlines splits at
NAME = st.text(st.characters(blacklist_categories=("Cs",), blacklist_characters=SEPARATORS), min_size=1, max_size=20)


@settings(max_examples=30, deadline=None)
@given(st.lists(NAME, min_size=1, max_size=40), st.integers(-45, 45), st.integers(-45, 45))
def test_names_read_back_whole_and_in_slices(tmp_path_factory, names, start, stop):
    folder = tmp_path_factory.mktemp("names")
    write_names(names, lambda name: open(folder / name, "wb"))
    opened = open_names(folder, len(names))
    assert list(opened) == names and len(opened) == len(names)
    assert list(opened[start:stop]) == names[start:stop]
    assert isinstance(opened[start:stop], FrameNames)  # a slice reads nothing
    assert opened[-1] == names[-1] and list(opened[::2]) == names[::2]
    assert list(FramePaths(opened)[start:stop]) == [Path(n) for n in names[start:stop]]


def test_a_map_without_the_offsets_file_finds_its_lines(tmp_path):
    (tmp_path / "names.txt").write_text("a\nbé\nc/d.png\n")
    assert list(open_names(tmp_path, 3)) == ["a", "bé", "c/d.png"]
    assert open_names(tmp_path / "nowhere", 3) is None


def test_names_that_do_not_fit_are_one_line(tmp_path):
    write_names(["a", "b"], lambda name: open(tmp_path / name, "wb"))
    raises_one_line("2 names for 3 frames", open_names, tmp_path, 3)
    np.save(tmp_path / OFFSETS_FILE, np.array([0, 1, 9], np.int64))
    raises_one_line("does not fit", open_names, tmp_path, 2)
    with pytest.raises(IndexError):
        FrameNames(np.frombuffer(b"a\n", np.uint8), np.array([0, 2]))[1]


def test_an_opened_maps_names_are_mapped_not_read(tmp_path):
    from seqvpr.data.traversal import Traversal
    from seqvpr.maps.files import MapInfo, MapSource, open_map, write_map

    rows = np.eye(4, dtype=np.float32)
    frames = Traversal("t", np.arange(4), np.zeros(4, np.int64), rows, tuple(Path(f"img/{i}.png") for i in range(4)))
    write_map(tmp_path / "m", frames, MapInfo(4, 4, "float32", True, {"descriptor": "file"},
                                              (MapSource("s", "t", 0, 4),)))
    saved = open_map(tmp_path / "m")
    assert isinstance(saved.frames.names, FrameNames) and isinstance(saved.frames.names.data, np.memmap)
    assert list(saved.frames.image_paths) == [Path(f"img/{i}.png") for i in range(4)]
    assert isinstance(saved.frames.segment_ids, np.memmap)
