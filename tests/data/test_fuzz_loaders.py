"""Every loader against damaged copies of a valid file: cut at every class of prefix length and with random bytes
flipped, each read gives a correct result or one ``SeqvprError`` line naming the file, never another exception
(200 damaged copies a format under the ci profile, fewer in development)."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import scipy.io

from seqvpr.errors import SeqvprError
from tests.helpers import examples

COPIES = examples(200)


def damaged(data: bytes, rng: np.random.Generator, count: int) -> list[bytes]:
    """``count`` damaged copies: prefixes of every length class (empty, a few bytes, half, all but one) and copies
    with 1 to 8 random bytes flipped, about half each."""
    cuts = sorted({0, 1, 7, 64, len(data) // 2, max(len(data) - 1, 0)} | set(rng.integers(0, len(data), count // 2)))
    copies = [data[:cut] for cut in cuts][: count // 2]
    while len(copies) < count:
        flipped = bytearray(data)
        for at in rng.integers(0, len(data), rng.integers(1, 9)):
            flipped[at] ^= int(rng.integers(1, 256))
        copies.append(bytes(flipped))
    return copies


def check_loader(tmp_path: Path, name: str, valid: bytes, load: Callable[[Path], object], seed: int = 0) -> None:
    """Each damaged copy of ``valid``, written as ``name``, gives a result or one line naming the file."""
    rng = np.random.default_rng(seed)
    path = tmp_path / name
    for number, data in enumerate(damaged(valid, rng, COPIES)):
        path.write_bytes(data)
        try:
            load(path)
        except SeqvprError as error:
            assert "\n" not in str(error), (number, str(error))
        except Exception as error:  # noqa: BLE001 - what the test looks for
            pytest.fail(f"copy {number} of {name} ({len(data)} bytes): {type(error).__name__}: {error}")


@pytest.fixture(scope="module")
def route():
    from seqvpr.synthetic.routes import generate_route

    return generate_route(n_frames=40, dim=6, seed=3)


def traversal_loader(role: str = "reference") -> Callable[[Path], object]:
    from seqvpr.data.sources import load_traversal

    return lambda path: load_traversal(str(path), role)


def test_descriptor_arrays(tmp_path, route):
    import io

    buffer = io.BytesIO()
    np.save(buffer, route[0].descriptors)
    check_loader(tmp_path, "x.npy", buffer.getvalue(), traversal_loader())
    buffer = io.BytesIO()
    np.savez(buffer, rows=route[0].descriptors)
    check_loader(tmp_path, "x.npz", buffer.getvalue(), traversal_loader(), seed=1)
    buffer = io.BytesIO()
    scipy.io.savemat(buffer, {"Y": route[0].descriptors})
    check_loader(tmp_path, "x.mat", buffer.getvalue(), traversal_loader(), seed=2)


def test_traversal_files(tmp_path, route):
    from seqvpr.data.sources import save_traversal_npz

    save_traversal_npz(tmp_path / "valid.npz", route[0])
    check_loader(tmp_path, "t.npz", (tmp_path / "valid.npz").read_bytes(), traversal_loader())


def test_image_folder_positions(tmp_path):
    from PIL import Image

    folder = tmp_path / "images"
    folder.mkdir()
    rows = ["name,easting,northing,timestamp"]
    for i in range(6):
        Image.new("RGB", (8, 6), (i * 30, 0, 0)).save(folder / f"{i:03d}.png")
        rows.append(f"{i:03d}.png,{100 + 2 * i},{50 + i},{i * 0.1}")
    valid = ("\n".join(rows) + "\n").encode()
    check_loader(folder, "positions.csv", valid, lambda path: traversal_loader()(path.parent))


def test_ground_truth_files(tmp_path, route):
    import io

    from seqvpr.evaluation.ground_truth import resolve_ground_truth

    reference = route[0].select(np.arange(10))
    query = route[1].select(np.arange(8))
    load = lambda path: resolve_ground_truth(reference, query, None, str(path))  # noqa: E731
    buffer = io.BytesIO()
    np.save(buffer, np.eye(10, 8, dtype=bool))
    check_loader(tmp_path, "gt.npy", buffer.getvalue(), load)
    buffer = io.BytesIO()
    scipy.io.savemat(buffer, {"GT": {"GThard": np.eye(10, 8, dtype=bool), "GTsoft": np.eye(10, 8, dtype=bool)}})
    check_loader(tmp_path, "gt.mat", buffer.getvalue(), load, seed=1)


def test_a_saved_maps_description_and_rows(tmp_path):
    from seqvpr.maps import build_map, open_map
    from tests.helpers import write_route_files

    (tmp_path / "route").mkdir()
    route = write_route_files(tmp_path / "route", n_frames=30, dim=6, seed=2)
    build_map([str(route / "ref.npz")], tmp_path / "map")
    for number, name in enumerate(("map.json", "descriptors.npy", "segments.npy")):
        valid = (tmp_path / "map" / name).read_bytes()
        check_loader(tmp_path / "map", name, valid, open_map_of, seed=number)
        (tmp_path / "map" / name).write_bytes(valid)


def open_map_of(path: Path):
    from seqvpr.maps import open_map

    return open_map(path.parent)


def test_a_model_folder(tmp_path):
    from seqvpr.models.configs import TransformConfig
    from seqvpr.models.registry import load_trained_model
    from seqvpr.models.seqmatchnet import FrameTransform, save_seqmatchnet

    save_seqmatchnet(tmp_path / "m", FrameTransform(TransformConfig(6), seed=0), {})
    for number, name in enumerate(("config.json", "model.safetensors")):
        valid = (tmp_path / "m" / name).read_bytes()
        check_loader(tmp_path / "m", name, valid, lambda path: load_trained_model(path.parent), seed=number)
        (tmp_path / "m" / name).write_bytes(valid)


def test_a_description_file(tmp_path, route):
    from seqvpr.data.sources import save_traversal_npz

    save_traversal_npz(tmp_path / "ref.npz", route[0])
    save_traversal_npz(tmp_path / "qry.npz", route[1])
    valid = ('[reference]\ndescriptors = "ref.npz"\n[query]\ndescriptors = "qry.npz"\n'
             '[ground_truth]\nradius = "5m"\n').encode()
    check_loader(tmp_path, "dataset.toml", valid, traversal_loader("query"))


def test_a_localizer_state_and_calibration(tmp_path):
    from seqvpr.localization import Localizer
    from seqvpr.maps import build_map
    from tests.helpers import write_route_files

    (tmp_path / "route").mkdir()
    route = write_route_files(tmp_path / "route", n_frames=30, dim=6, seed=4)
    saved = build_map([str(route / "ref.npz")], tmp_path / "map")
    localizer = Localizer.open(saved, seq_len=3)
    for row in np.load(route / "qry.npz")["descriptors"][:5]:
        localizer.update(row)
    localizer.save_state(tmp_path / "state.npz")
    check_loader(tmp_path, "state.npz", (tmp_path / "state.npz").read_bytes(),
                 lambda path: Localizer.open(saved, seq_len=3).restore(path))
    (tmp_path / "map" / "localizer.json").write_text(json.dumps(
        {"format": "seqvpr-localizer", "version": 1, "map": saved.info.identity, "calibrations": []}))
    valid = (tmp_path / "map" / "localizer.json").read_bytes()
    check_loader(tmp_path / "map", "localizer.json", valid, lambda path: Localizer.open(saved, seq_len=3), seed=1)


def test_a_dbstruct(tmp_path, route):
    from seqvpr.data.loaders.dbstruct import write_dbstruct

    reference, query = route[0].select(np.arange(10)), route[1].select(np.arange(8))
    write_dbstruct(tmp_path / "valid.db", reference, query, 5.0, "valid")
    valid = (tmp_path / "valid.db").read_bytes()
    check_loader(tmp_path, "x.db", valid, traversal_loader("query"))


def test_ros_bags(tmp_path, monkeypatch):
    from PIL import Image

    from tests.bags import fixes, write_bag

    monkeypatch.setenv("SEQVPR_BAG_FRAMES", str(tmp_path / "frames"))
    (tmp_path / "jpg").mkdir()
    images = []
    for i in range(4):
        images.append(tmp_path / "jpg" / f"{i}.jpg")
        Image.new("RGB", (8, 6), (40 * i, 0, 0)).save(images[-1])
    valid = write_bag(tmp_path / "valid.bag", images, *fixes(4), ros1=True).read_bytes()
    check_loader(tmp_path, "x.bag", valid, traversal_loader("query"))
    folder = write_bag(tmp_path / "valid2", images, *fixes(4), ros1=False)
    for number, member in enumerate(sorted(p.name for p in folder.iterdir())):
        data = (folder / member).read_bytes()
        check_loader(folder, member, data, lambda path: traversal_loader("query")(path.parent), seed=number)
        (folder / member).write_bytes(data)


def test_msls_tables(tmp_path):
    from tests.data.test_loader_msls import write_side

    side = write_side(tmp_path / "database", {"dA": [(n, 3.0 * n) for n in range(6)]}, np.random.default_rng(0))
    for number, name in enumerate(("seq_info.csv", "postprocessed.csv", "raw.csv", "subtask_index.csv")):
        valid = (side / name).read_bytes()
        check_loader(side, name, valid, lambda path: traversal_loader()(path.parent), seed=number)
        (side / name).write_bytes(valid)


def test_vprbench_rows(tmp_path):
    from seqvpr.data.loaders.ground_truth_files import load_ground_truth_file
    from tests.data.test_loader_vprbench import rows_file

    rows_file(tmp_path / "valid.npy", [[0, 1], [1], [], [2, 3]])
    check_loader(tmp_path, "gt.npy", (tmp_path / "valid.npy").read_bytes(),
                 lambda path: load_ground_truth_file(path, 4, 4))


def test_seq_bounds(tmp_path):
    from seqvpr.data.loaders.seq_bounds import load_seq_bounds

    valid = b"0 3\n0 3\n0 3\n3 5\n3 5\n"
    check_loader(tmp_path, "x_seqBounds.txt", valid, lambda path: load_seq_bounds(path, 5))


@pytest.mark.parametrize("suffix", ["png", "jpg"])
def test_image_files(tmp_path, suffix):
    from PIL import Image

    from seqvpr.data.images import read_image

    rng = np.random.default_rng(5)
    Image.fromarray(rng.integers(0, 255, (12, 16, 3), dtype=np.uint8)).save(tmp_path / f"valid.{suffix}")
    check_loader(tmp_path, f"x.{suffix}", (tmp_path / f"valid.{suffix}").read_bytes(),
                 lambda path: read_image(path).load())
