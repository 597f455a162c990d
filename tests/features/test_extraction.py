"""Extraction: batching, the on-disk cache (reuse and invalidation), resume after an interruption, bad images."""

import json
import os

import numpy as np
import pytest
import torch
from PIL import Image
from torch import nn

from seqvpr.features.extraction import (
    Extractor,
    ExtractorConfig,
    build_extractor,
    extract_descriptors,
    init_netvlad,
    load_image,
)
from seqvpr.features.pooling import GeM, NetVLAD
from seqvpr.errors import SeqvprWarning
from tests.helpers import raises_one_line


class TinyBackbone(nn.Module):
    """A small convolution standing in for a real backbone; counts the images it sees."""

    def __init__(self) -> None:
        super().__init__()
        torch.manual_seed(0)
        self.conv = nn.Conv2d(3, 8, 3, stride=2)
        self.images_seen = 0

    def features(self, x):
        self.images_seen += len(x)
        return torch.relu(self.conv(x))


def tiny() -> Extractor:
    return Extractor(TinyBackbone(), GeM(), (0.5, 0.5, 0.5), (0.5, 0.5, 0.5)).eval()


@pytest.fixture
def images(tmp_path):
    rng = np.random.default_rng(0)
    folder = tmp_path / "images"
    folder.mkdir()
    paths = []
    for i in range(10):
        path = folder / f"{i:03d}.png"
        Image.fromarray(rng.integers(0, 255, size=(30, 40, 3), dtype=np.uint8)).save(path)
        paths.append(path)
    return paths


CONFIG = ExtractorConfig(width=32, height=24, batch_size=3)


def test_batched_equals_one_at_a_time_with_the_real_backbone(images):
    config = ExtractorConfig(width=64, height=48, batch_size=4)
    model = build_extractor(config)
    batched = extract_descriptors(images[:5], config, extractor=model, engine="torch").descriptors
    single = extract_descriptors(images[:5], ExtractorConfig(width=64, height=48, batch_size=1), extractor=model, engine="torch")
    assert batched.shape == (5, 1280)
    assert np.allclose(batched, single.descriptors, atol=1e-5)
    assert np.allclose(np.linalg.norm(batched, axis=1), 1.0, atol=1e-5)


def test_cache_is_reused_and_invalidated_by_config_or_images(tmp_path, images):
    cache = tmp_path / "cache"
    model = tiny()
    first = extract_descriptors(images, CONFIG, cache_dir=cache, extractor=model, engine="torch")
    assert model.backbone.images_seen == 10
    again = extract_descriptors(images, CONFIG, cache_dir=cache, extractor=model, engine="torch")
    assert model.backbone.images_seen == 10 and np.array_equal(first.descriptors, again.descriptors)
    extract_descriptors(images, ExtractorConfig(width=40, height=24, batch_size=3), cache_dir=cache, extractor=model, engine="torch")
    assert model.backbone.images_seen == 20  # another input size: recomputed
    extract_descriptors(images[:9], CONFIG, cache_dir=cache, extractor=model, engine="torch")
    assert model.backbone.images_seen == 29  # another image list: recomputed
    Image.fromarray(np.zeros((30, 40, 3), np.uint8)).save(images[4])
    os.utime(images[4], ns=(1, 1))
    changed = extract_descriptors(images, CONFIG, cache_dir=cache, extractor=model, engine="torch")
    assert model.backbone.images_seen == 39  # an image changed: recomputed
    assert not np.allclose(changed.descriptors[4], first.descriptors[4])


def test_an_image_rewritten_with_its_old_size_and_mtime_is_not_served_stale(tmp_path, images):
    cache = tmp_path / "cache"
    model = tiny()
    first = extract_descriptors(images, CONFIG, cache_dir=cache, extractor=model, engine="torch")
    stat = images[2].stat()
    data = bytearray(images[2].read_bytes())
    other = images[3].read_bytes()
    images[2].write_bytes(other[: len(data)] + bytes(max(0, len(data) - len(other))))  # cp -p / rsync -t
    os.utime(images[2], ns=(stat.st_atime_ns, stat.st_mtime_ns))
    assert images[2].stat().st_size == stat.st_size and images[2].stat().st_mtime_ns == stat.st_mtime_ns
    again = extract_descriptors(images, CONFIG, cache_dir=cache, extractor=model, skip_bad=True, engine="torch")
    assert model.backbone.images_seen == 20 and again.cache_file != first.cache_file


@pytest.mark.parametrize("damage", ["truncate", "flip"])
def test_a_damaged_cache_entry_is_recomputed_never_used(tmp_path, images, damage):
    cache = tmp_path / "cache"
    model = tiny()
    first = extract_descriptors(images, CONFIG, cache_dir=cache, extractor=model, engine="torch")
    data = bytearray(first.cache_file.read_bytes())
    if damage == "truncate":  # a full disk or a killed writer
        first.cache_file.write_bytes(bytes(data[: len(data) // 2]))
    else:  # flip one byte of the stored descriptors (np.savez stores them uncompressed)
        at = data.index(first.descriptors[0].tobytes()[:8]) + 4
        data[at] ^= 0xFF
        first.cache_file.write_bytes(bytes(data))
    with pytest.warns(SeqvprWarning, match="damaged cache entry"):
        again = extract_descriptors(images, CONFIG, cache_dir=cache, extractor=model, engine="torch")
    assert model.backbone.images_seen == 20  # recomputed
    np.testing.assert_array_equal(again.descriptors, first.descriptors)
    assert extract_descriptors(images, CONFIG, cache_dir=cache, extractor=model, engine="torch").cache_file == first.cache_file
    assert model.backbone.images_seen == 20  # and the new entry is sound


def test_interrupted_extraction_resumes_where_it_stopped(tmp_path, images):
    cache = tmp_path / "cache"
    whole = extract_descriptors(images, CONFIG, extractor=tiny()).descriptors
    seen = []

    def interrupt(n):
        seen.append(n)
        if len(seen) == 2:
            raise KeyboardInterrupt

    model = tiny()
    with pytest.raises(KeyboardInterrupt):
        extract_descriptors(images, CONFIG, cache_dir=cache, extractor=model, progress=interrupt, engine="torch")
    assert model.backbone.images_seen == 6
    resumed = extract_descriptors(images, CONFIG, cache_dir=cache, extractor=model, engine="torch")
    assert model.backbone.images_seen == 10  # only the 4 images not done before
    assert np.allclose(resumed.descriptors, whole, atol=1e-6)
    assert not any(p.name.endswith(".part") for p in cache.iterdir())


def test_bad_image_is_an_error_naming_it_or_skipped(tmp_path, images):
    images[3].write_bytes(b"not an image")
    raises_one_line(f"{images[3]}: not a readable image", extract_descriptors, images, CONFIG, extractor=tiny())
    result = extract_descriptors(images, CONFIG, extractor=tiny(), skip_bad=True)
    assert result.skipped == (images[3],)
    assert list(result.rows) == [0, 1, 2, 4, 5, 6, 7, 8, 9] and len(result.descriptors) == 9
    raises_one_line("no such image", extract_descriptors, [tmp_path / "gone.png"], CONFIG, extractor=tiny())


def test_unknown_backbone_is_one_line():
    raises_one_line("backbone 'vgg'", ExtractorConfig, backbone="vgg")


def test_cli_extract_then_match_keeps_source_frames_of_skipped_images(monkeypatch, capsys, tmp_path, images):
    from tests.helpers import run_cli

    images[2].write_bytes(b"broken")
    folder = images[0].parent
    out = tmp_path / "ref.npz"
    args = ["extract", folder, "--descriptor", "efficientnet-lite0", "--image-size", "64x48", "--out", out]
    code, _, err = run_cli(monkeypatch, capsys, *args)
    assert code == 2 and "002.png: not a readable image" in err and not out.exists()
    code, stdout, err = run_cli(monkeypatch, capsys, *args, "--skip-bad", "--cache-dir", tmp_path / "cache")
    assert code == 0, err
    assert "skipped 1 unreadable images: 002.png" in err and "9 frames, 1280-D" in stdout
    with np.load(out) as saved:
        assert list(saved["frame_index"]) == [0, 1, 3, 4, 5, 6, 7, 8, 9]
        assert list(saved["segments"]) == [0, 0, 1, 1, 1, 1, 1, 1, 1]  # the gap starts a new segment
    code, stdout, err = run_cli(monkeypatch, capsys, "match", "-r", out, "-q", out, "--radius", "0f", "--json",
                                "--out", tmp_path / "m")
    assert code == 0, err
    assert json.loads(stdout)["recall"]["1"] == 1.0  # every frame finds itself


def test_cli_extract_bad_options_name_the_option(monkeypatch, capsys, tmp_path, images):
    from tests.helpers import run_cli

    code, _, err = run_cli(monkeypatch, capsys, "extract", images[0].parent, "--descriptor", "efficientnet-lite0",
                           "--image-size", "10", "--out", tmp_path / "x.npz")
    assert code == 2 and "--image-size '10'" in err and not (tmp_path / "x.npz").exists()
    code, _, err = run_cli(monkeypatch, capsys, "extract", images[0].parent, "--descriptor", "resnet18",
                           "--out", tmp_path / "x.npz")
    assert code == 2 and "pass a checkpoint path" in err and err.count("\n") == 1


def tiny_netvlad(clusters: int = 4) -> Extractor:
    backbone = TinyBackbone()
    backbone.local_features = backbone.features
    return Extractor(backbone, NetVLAD(clusters, 8), (0.5, 0.5, 0.5), (0.5, 0.5, 0.5)).eval()


def test_netvlad_extraction_equals_pooling_the_local_features_and_its_head_keys_the_cache(tmp_path, images):
    config = ExtractorConfig(width=32, height=24, batch_size=3, pooling="netvlad", clusters=4)
    model = tiny_netvlad()
    init_netvlad(model, images, config, seed=1)
    with torch.no_grad():
        local = model.backbone.features((torch.stack([load_image(p, 32, 24) for p in images]) - 0.5) / 0.5)
        expected = model.pooling(local).numpy()
    cache = tmp_path / "cache"
    first = extract_descriptors(images, config, cache_dir=cache, extractor=model, engine="torch")
    assert first.descriptors.shape == (10, 32)
    assert np.allclose(first.descriptors, expected, atol=1e-5)
    assert extract_descriptors(images, config, cache_dir=cache, extractor=model, engine="torch").cache_file == first.cache_file
    init_netvlad(model, images[:5], config, seed=2)  # a re-fitted head must not reuse the cache
    again = extract_descriptors(images, config, cache_dir=cache, extractor=model, engine="torch")
    assert again.cache_file != first.cache_file and len(list(cache.glob("*.npz"))) == 2


def test_netvlad_init_is_seeded_and_needs_a_netvlad_extractor(images):
    config = ExtractorConfig(width=32, height=24, batch_size=4, pooling="netvlad", clusters=4)
    heads = []
    for _ in range(2):
        model = tiny_netvlad()
        init_netvlad(model, images, config, seed=3)
        heads.append(model.pooling.centroids.detach().clone())
    assert torch.equal(heads[0], heads[1])
    raises_one_line("NetVLAD head", init_netvlad, tiny(), images, CONFIG)
    raises_one_line("initialised extractor", extract_descriptors, images, config)


def test_cli_match_netvlad_pca_whitened_finds_each_frame_itself(monkeypatch, capsys, tmp_path, images):
    from tests.helpers import run_cli

    folder = images[0].parent
    code, stdout, err = run_cli(monkeypatch, capsys, "match", "-r", folder, "-q", folder, "--radius", "0f",
                                "--descriptor", "efficientnet-lite0", "--image-size", "64x48", "--pooling",
                                "netvlad", "--clusters", "8", "--pca-dim", "64", "--json", "--out", tmp_path / "m")
    assert code == 0, err
    result = json.loads(stdout)
    assert result["recall"]["1"] == 1.0
    assert result["settings"]["pooling"] == "netvlad"
    assert "PCA-whitening to 9 dimensions" in err  # 10 reference frames allow at most 9
