"""Patch normalisation against its plain formula."""

import numpy as np
from PIL import Image

from seqvpr.features.patchnorm import PatchNormConfig, patch_normalize, patchnorm_descriptors


def test_patch_normalize_plain_formula():
    rng = np.random.default_rng(1)
    image = rng.integers(0, 256, (32, 64)).astype(float)
    expected = []
    for by in range(0, 32, 8):
        for bx in range(0, 64, 8):
            block = image[by : by + 8, bx : bx + 8].ravel()
            expected.extend((block - block.mean()) / (block.std() + 1e-6))
    expected = np.array(expected) / np.linalg.norm(expected)
    np.testing.assert_allclose(patch_normalize(image, 8), expected, atol=1e-12)


def test_constant_patches_give_zeros_not_nan():
    vector = patch_normalize(np.full((16, 16), 7.0), 8)
    assert np.isfinite(vector).all() and not vector.any()


def test_patchnorm_resizes_and_reads_files(tmp_path):
    path = tmp_path / "a.png"
    Image.fromarray(np.random.default_rng(0).integers(0, 255, (60, 100, 3), dtype=np.uint8)).save(path)
    out = patchnorm_descriptors([path], PatchNormConfig(32, 16, 8))
    assert out.shape == (1, 512) and abs(np.linalg.norm(out[0]) - 1) < 1e-5
