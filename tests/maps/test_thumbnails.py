"""Thumbnails kept in a map (``map build --thumbnails``): each frame's are its image's thumbnail, byte for byte;
they are map files (sealed, checked, kept when an index is added); what cannot keep them is one line."""

from __future__ import annotations

import pytest

from seqvpr.data.thumbnails import cached_thumbnail, thumbnail_cache
from seqvpr.maps import build_map
from seqvpr.maps.files import open_map
from seqvpr.maps.grow import add_to_map
from seqvpr.maps.thumbnails import THUMBNAILS_FILE, map_thumbnail
from tests.helpers import raises_one_line, write_image_folder, write_route_files


@pytest.fixture
def images(tmp_path):
    return write_image_folder(tmp_path / "frames", 12, (24, 32), (64, 48))


def test_each_frame_keeps_its_images_thumbnail(images, tmp_path):
    saved = build_map([str(images)], tmp_path / "map", thumbnails=True)
    assert THUMBNAILS_FILE in saved.info.files
    for row in range(12):
        expected = cached_thumbnail(saved.frames.image_paths[row], thumbnail_cache()).read_bytes()
        assert map_thumbnail(tmp_path / "map", row) == expected and expected[:2] == b"\xff\xd8"
    plain = build_map([str(images)], tmp_path / "plain")
    assert map_thumbnail(tmp_path / "plain", 0) is None and plain.info.identity != saved.info.identity


def test_thumbnails_stay_when_an_index_is_added_and_are_checked(images, tmp_path, monkeypatch, capsys):
    from seqvpr.maps.index import IndexSpec, add_index
    from tests.helpers import run_cli

    saved = build_map([str(images)], tmp_path / "map", thumbnails=True)
    first = map_thumbnail(tmp_path / "map", 3)
    add_index(saved, IndexSpec("flat"))
    assert map_thumbnail(tmp_path / "map", 3) == first
    assert run_cli(monkeypatch, capsys, "map", "check", tmp_path / "map")[0] == 0
    with open(tmp_path / "map" / THUMBNAILS_FILE, "r+b") as handle:  # a flipped byte is found
        handle.seek(10)
        byte = handle.read(1)
        handle.seek(10)
        handle.write(bytes([byte[0] ^ 0xFF]))
    code, _, err = run_cli(monkeypatch, capsys, "map", "check", tmp_path / "map")
    assert code != 0 and THUMBNAILS_FILE in err


def test_what_cannot_keep_thumbnails_is_one_line(images, tmp_path):
    build_map([str(images)], tmp_path / "map", thumbnails=True)
    raises_one_line("keeps thumbnails", add_to_map, tmp_path / "map", [str(images)])
    write_route_files(tmp_path, 20, 8, 1)
    raises_one_line("hold descriptors, not images", build_map, [str(tmp_path / "ref.npz")], tmp_path / "m2",
                    thumbnails=True)
    assert open_map(tmp_path / "map").info.count == 12
