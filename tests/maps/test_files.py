"""The map folder: written atomically, opened memory-mapped, every missing or broken file one line."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from seqvpr.data.sources import load_traversal
from seqvpr.data.traversal import Traversal
from seqvpr.maps import build_map, open_map
from seqvpr.maps.build import concatenate_traversals
from tests.helpers import raises_one_line, write_route_files


@pytest.fixture(scope="module")
def sources(tmp_path_factory):
    folder = write_route_files(tmp_path_factory.mktemp("sources"), 80, 12, 2)
    return folder / "ref.npz", folder / "qry.npz", load_traversal(folder / "ref.npz", "reference")


def test_a_map_holds_the_normalized_frames_memory_mapped_with_their_table(sources, tmp_path):
    ref, _, reference = sources
    saved = build_map([str(ref)], tmp_path / "m")
    assert isinstance(saved.descriptors, np.memmap) and saved.descriptors.dtype == np.float32
    expected = reference.descriptors / np.linalg.norm(reference.descriptors, axis=1, keepdims=True)
    np.testing.assert_allclose(saved.descriptors, expected, rtol=1e-6)
    np.testing.assert_array_equal(saved.frames.positions, reference.positions)
    np.testing.assert_array_equal(saved.frames.frame_index, reference.frame_index)
    info = json.loads((tmp_path / "m" / "map.json").read_text())
    assert (info["format"], info["version"], info["count"], info["dim"], info["normalized"]) == ("seqvpr-map", 2, 80, 12, True)
    assert info["sources"] == [{"source": str(ref), "name": "ref", "first": 0, "frames": 80}]
    assert info["columns"] == ["positions", "timestamps"] and info["library_version"] and info["created"]


def test_float16_halves_the_descriptor_file(sources, tmp_path):
    ref = sources[0]
    wide, half = build_map([str(ref)], tmp_path / "f32"), build_map([str(ref)], tmp_path / "f16", dtype="float16")
    assert half.descriptors.dtype == np.float16 and half.descriptors.nbytes * 2 == wide.descriptors.nbytes
    np.testing.assert_allclose(half.descriptors.astype(np.float32), wide.descriptors, atol=1e-3)


def test_several_sources_keep_their_own_segments(sources, tmp_path):
    ref, qry, _ = sources
    saved = build_map([str(ref), str(qry)], tmp_path / "two")
    segments = np.asarray(saved.frames.segment_ids)
    assert set(segments[:80]).isdisjoint(segments[80:])
    assert [(s.first, s.frames) for s in saved.info.sources] == [(0, 80), (80, 80)]
    assert np.load(tmp_path / "two" / "sources.npy").tolist() == [0] * 80 + [1] * 80


def test_concatenation_renumbers_segments_and_drops_columns_one_source_lacks():
    a = Traversal.from_descriptors(np.ones((4, 3)), positions=np.zeros((4, 2)), segment_ids=np.array([5, 5, 7, 7]))
    b = Traversal.from_descriptors(np.ones((3, 3)), segment_ids=np.array([5, 5, 5]))
    both = concatenate_traversals([a, b])
    assert both.segment_ids.tolist() == [0, 0, 1, 1, 2, 2, 2] and both.positions is None


def test_a_failed_build_leaves_no_map(sources, tmp_path):
    raises_one_line("no such file", build_map, [str(sources[0]), str(tmp_path / "missing.npy")], tmp_path / "m")
    assert not (tmp_path / "m").exists() and list(tmp_path.iterdir()) == []


def test_broken_maps_are_one_line_errors(sources, tmp_path):
    folder = tmp_path / "m"
    build_map([str(sources[0])], folder)
    info = folder / "map.json"
    good = info.read_text()
    info.write_text(good.replace('"version": 2', '"version": 9'))
    message = raises_one_line("version 9 is not known", open_map, folder)
    assert "malformed" not in message
    info.write_text(good.replace('"sources"', '"origins"'))
    raises_one_line("malformed map description (KeyError", open_map, folder)
    info.write_text(good.replace('"seqvpr-map"', '"other"'))
    raises_one_line("not a seqvpr map", open_map, folder)
    info.write_text("{")
    raises_one_line("malformed map description", open_map, folder)
    info.unlink()
    raises_one_line("not a seqvpr map (no map.json", open_map, folder)
    raises_one_line("no such map folder", open_map, tmp_path / "nothing")
    info.write_text(good)
    data = (folder / "descriptors.npy").read_bytes()
    (folder / "descriptors.npy").write_bytes(data[: len(data) // 2])
    raises_one_line("descriptors.npy: its content is not what", open_map, folder)
    (folder / "descriptors.npy").write_bytes(data)
    np.save(folder / "segments.npy", np.zeros(3, np.int64))
    raises_one_line("segments.npy: its content is not what", open_map, folder)
    (folder / "segments.npy").unlink()
    raises_one_line("segments.npy: missing", open_map, folder)


def test_sq8_stores_a_quarter_and_decodes_within_half_a_step(sources, tmp_path):
    ref = sources[0]
    wide, coded = build_map([str(ref)], tmp_path / "f32"), build_map([str(ref)], tmp_path / "sq8", dtype="sq8")
    assert np.load(tmp_path / "sq8" / "descriptors.npy", mmap_mode="r").dtype == np.uint8
    assert coded.descriptors.nbytes * 4 == wide.descriptors.nbytes
    offset, step = np.load(tmp_path / "sq8" / "quantizer.npy")
    decoded = coded.descriptors[:]
    assert decoded.dtype == np.float32 and decoded.shape == (80, 12)
    assert np.abs(decoded - wide.descriptors).max() <= step.max() / 2 + 1e-6
    np.testing.assert_array_equal(coded.descriptors[np.array([3, 70])], decoded[[3, 70]])
    (tmp_path / "sq8" / "quantizer.npy").unlink()
    raises_one_line("quantizer.npy: missing", open_map, tmp_path / "sq8")


def test_map_files_take_the_umask_mode_not_a_private_one(sources, tmp_path):
    import os

    from seqvpr.maps.index import IndexSpec, add_index

    old = os.umask(0o022)
    try:
        saved = build_map([str(sources[0])], tmp_path / "m")
        add_index(saved, IndexSpec("flat"))
    finally:
        os.umask(old)
    assert (tmp_path / "m").stat().st_mode & 0o777 == 0o755
    for name in ("map.json", "descriptors.npy", "index.faiss"):
        assert (tmp_path / "m" / name).stat().st_mode & 0o777 == 0o644, name


def test_pq_stores_m_bytes_a_frame_and_still_ranks_like_float32(tmp_path):
    from seqvpr.maps import match_map
    from seqvpr.sequences.match_settings import MatchSettings
    from seqvpr.sequences.windows import SequenceSpec

    folder = write_route_files(tmp_path, 600, 16, 9)
    wide = build_map([str(folder / "ref.npz")], tmp_path / "f32")
    coded = build_map([str(folder / "ref.npz")], tmp_path / "pq", dtype="pq:8")
    assert np.load(tmp_path / "pq" / "descriptors.npy", mmap_mode="r").shape == (600, 8)
    assert np.load(tmp_path / "pq" / "pq_centroids.npy").shape == (8, 256, 2)
    assert coded.descriptors.nbytes == 600 * 8 and coded.descriptors.shape == (600, 16)
    decoded = coded.descriptors[:]
    assert np.linalg.norm(decoded - wide.descriptors, axis=1).mean() < 0.1
    np.testing.assert_array_equal(coded.descriptors[np.array([4, 500])], decoded[[4, 500]])
    query = load_traversal(folder / "qry.npz", "query")
    settings = MatchSettings(SequenceSpec(5), k=5)
    a, b = (match_map(m, query, "matching", settings).topk.indices[:, 0] for m in (wide, coded))
    assert (np.abs(a - b) <= 2)[a >= 0].mean() > 0.8


def test_unknown_or_untrainable_storages_are_one_line(sources, tmp_path):
    raises_one_line("map storage 'int4' is not known", build_map, [str(sources[0])], tmp_path / "a", dtype="int4")
    raises_one_line("M = 5 must divide the dimension 12", build_map, [str(sources[0])], tmp_path / "b", dtype="pq:5")
    raises_one_line("needs at least 256 frames", build_map, [str(sources[0])], tmp_path / "c", dtype="pq:4")
    assert not any(tmp_path.iterdir())


def test_a_map_records_its_coordinate_system_and_an_older_map_reads_local(sources, tmp_path):
    from dataclasses import replace

    from seqvpr.data.sources import save_traversal_npz

    ref, _, reference = sources
    assert build_map([str(ref)], tmp_path / "local").info.crs == "local"  # a file's positions without a zone
    save_traversal_npz(tmp_path / "utm.npz", replace(reference, crs="utm:32N"))
    saved = build_map([str(tmp_path / "utm.npz")], tmp_path / "utm")
    assert saved.info.crs == saved.frames.crs == "utm:32N"
    assert json.loads((tmp_path / "utm" / "map.json").read_text())["crs"] == "utm:32N"
    values = json.loads((tmp_path / "utm" / "map.json").read_text())
    del values["crs"]  # a map written before maps recorded their coordinate system
    (tmp_path / "utm" / "map.json").write_text(json.dumps(values))
    assert open_map(tmp_path / "utm").info.crs == open_map(tmp_path / "utm").frames.crs == "local"
    save_traversal_npz(tmp_path / "none.npz", replace(reference, positions=None))
    assert build_map([str(tmp_path / "none.npz")], tmp_path / "none").info.crs is None


def test_sources_in_two_utm_zones_are_laid_in_the_first_ones_and_a_local_frame_is_one_line(sources, tmp_path):
    """A map of drives that start on either side of a zone line holds every position in the first source's zone;
    a local frame beside a UTM one cannot be placed: one line."""
    from dataclasses import replace

    from seqvpr.data.geo import latlon_to_utm

    lat, lon = np.full(4, 48.1), np.array([11.9990, 11.9995, 12.0005, 12.0010])  # across 12 degrees E
    in_32, crs_32 = latlon_to_utm(lat, lon, "a")
    in_33, crs_33 = latlon_to_utm(lat[::-1], lon[::-1], "b")
    a = Traversal.from_descriptors(np.ones((4, 3)), positions=in_32, source="a.npz")
    b = Traversal.from_descriptors(np.ones((4, 3)), positions=in_33, source="b.npz")
    whole = concatenate_traversals([replace(a, crs=crs_32), replace(b, crs=crs_33)])
    assert whole.crs == "utm:32N"
    np.testing.assert_allclose(whole.positions[4:][::-1], in_32, atol=1e-6)  # the same places, in zone 32
    raises_one_line("b.npz: positions in local cannot be compared with positions in utm:32N",
                    concatenate_traversals, [replace(a, crs=crs_32), b])
    raises_one_line("coordinate system 'utm:61N' is not", replace, a, crs="utm:61N")


def test_shards_carry_the_coordinate_system_and_the_frame_names(tmp_path):
    from pathlib import Path

    from seqvpr.maps.build import map_sources
    from seqvpr.maps.files import MapInfo, write_map
    from seqvpr.maps.sharding import shard_map

    names = tuple(f"run.bag:/camera/image_raw@{100 + i}.000000000" for i in range(10))
    frames = Traversal("run", np.arange(10), np.zeros(10, np.int64), np.eye(10, 4, dtype=np.float32) + 0.1,
                       tuple(Path(f"/cache/{i}.jpg") for i in range(10)), np.c_[np.arange(10.0), np.zeros(10)],
                       names=names, crs="utm:55S")
    write_map(tmp_path / "m", frames, MapInfo(10, 4, "float32", False, {"descriptor": "patchnorm"},
                                              map_sources([frames], ["run.bag"])))
    assert (tmp_path / "m" / "names.txt").read_text().splitlines() == list(names)
    shard_map(tmp_path / "m", tmp_path / "s", 3, overlap=1)
    whole = open_map(tmp_path / "s")
    assert whole.info.crs == whole.frames.crs == "utm:55S" and whole.frames.frame_names() == list(names)
    assert open_map(tmp_path / "s" / "shard-001").info.crs == "utm:55S"


def test_build_map_reads_frames_a_network_described_before_from_the_cache(tmp_path, monkeypatch):
    from PIL import Image

    from seqvpr.cache import cache_folder
    from seqvpr.features import extraction
    from seqvpr.features.extraction import ExtractorConfig
    from seqvpr.maps import FrameDescription, build_map

    monkeypatch.setenv("SEQVPR_CACHE", str(tmp_path / "cache"))
    images = tmp_path / "images"
    images.mkdir()
    rng = np.random.default_rng(0)
    for i in range(4):
        Image.fromarray(rng.integers(0, 255, (24, 32, 3), dtype=np.uint8)).save(images / f"{i}.png")
    description = FrameDescription("efficientnet-lite0", extractor=ExtractorConfig(width=32, height=24))
    first = build_map([str(images)], tmp_path / "a", description)
    assert len(list(cache_folder("descriptors").glob("*.npz"))) == 1

    def no_network(*args, **kwargs):
        raise AssertionError("described again")

    monkeypatch.setattr(extraction, "_prepare_model", no_network)
    second = build_map([str(images)], tmp_path / "b", description)
    np.testing.assert_array_equal(np.asarray(first.descriptors), np.asarray(second.descriptors))


def test_an_unwritable_default_cache_is_a_warning_and_the_map_is_built(tmp_path, monkeypatch):
    from PIL import Image

    from seqvpr.errors import SeqvprWarning
    from seqvpr.features.extraction import ExtractorConfig
    from seqvpr.maps import FrameDescription, build_map

    (tmp_path / "file").write_text("not a folder")
    monkeypatch.setenv("SEQVPR_CACHE", str(tmp_path / "file" / "cache"))
    images = tmp_path / "images"
    images.mkdir()
    for i in range(3):
        Image.fromarray(np.full((24, 32, 3), 40 * i, np.uint8)).save(images / f"{i}.png")
    with pytest.warns(SeqvprWarning, match="describing without a cache"):
        saved = build_map([str(images)], tmp_path / "m",
                          FrameDescription("efficientnet-lite0", extractor=ExtractorConfig(width=32, height=24)))
    assert saved.info.count == 3


@settings(max_examples=10, deadline=None)
@given(st.integers(1, 3), st.integers(300, 700), st.integers(2, 9), st.sampled_from(["float32", "float16", "sq8",
                                                                                     "pq:4"]), st.integers(0, 99))
def test_a_streamed_build_writes_what_a_whole_one_would(tmp_path_factory, n_sources, n, dim, storage, seed):
    """Sources memory-mapped and laid end to end, rows normalised, encoded and written a few at a time: the stored
    rows are those of the whole array normalised at once and encoded by the same rule (sq8: the exact range; the
    float storages: a cast; pq: codes that decode to within the rows' spread)."""
    import torch

    import seqvpr.maps.codes as codes
    from seqvpr.sequences.matching import unit_rows

    folder = tmp_path_factory.mktemp("stream")
    rng = np.random.default_rng(seed)
    parts = [rng.standard_normal((n + 7 * i, dim * 4)).astype(np.float32) * 3 for i in range(n_sources)]
    for i, part in enumerate(parts):
        np.save(folder / f"s{i}.npy", part)
    patch = pytest.MonkeyPatch()
    patch.setattr(codes, "CHUNK_ROWS", 97)  # many chunks, and chunk edges inside every source
    try:
        saved = build_map([str(folder / f"s{i}.npy") for i in range(n_sources)], folder / "map", dtype=storage)
    finally:
        patch.undo()
    whole = np.concatenate(parts)
    unit_rows(torch.from_numpy(whole), out=torch.from_numpy(whole))
    stored = np.load(folder / "map" / "descriptors.npy")
    if storage.startswith("float"):
        assert np.array_equal(stored, whole.astype(storage))
    elif storage == "sq8":
        low, high = whole.min(axis=0), whole.max(axis=0)
        step = np.maximum((high - low) / 255.0, np.finfo(np.float32).tiny).astype(np.float32)
        assert np.array_equal(stored, np.clip(np.rint((whole - low) / step), 0, 255).astype(np.uint8))
    else:
        assert stored.shape == (len(whole), 4) and np.abs(saved.descriptors[:] - whole).mean() < 0.5


def test_a_users_files_outlive_rebuilding_the_map_and_a_stale_calibration_is_left_out(tmp_path, caplog):
    """A map built again in its folder keeps what the map did not own (a user's files and folders); the calibration
    stays with the same map (same identity) and is left out, with a warning, for another one."""
    import logging

    from seqvpr.maps import build_map

    (tmp_path / "route").mkdir()
    route = write_route_files(tmp_path / "route", n_frames=80, dim=8, seed=1)
    build_map([str(route / "ref.npz")], tmp_path / "m")
    (tmp_path / "m" / "notes.txt").write_text("mine")
    (tmp_path / "m" / "drives").mkdir()
    (tmp_path / "m" / "drives" / "a.txt").write_text("also mine")
    (tmp_path / "m" / "localizer.json").write_text("{}")
    build_map([str(route / "ref.npz")], tmp_path / "m")  # the same map again
    assert (tmp_path / "m" / "localizer.json").exists() and (tmp_path / "m" / "notes.txt").read_text() == "mine"
    with caplog.at_level(logging.WARNING, logger="seqvpr"):
        build_map([str(route / "qry.npz")], tmp_path / "m")  # another map in its place
    assert not (tmp_path / "m" / "localizer.json").exists()
    assert "calibrated for the map this one replaces" in caplog.text
    assert (tmp_path / "m" / "notes.txt").read_text() == "mine"
    assert (tmp_path / "m" / "drives" / "a.txt").read_text() == "also mine"
