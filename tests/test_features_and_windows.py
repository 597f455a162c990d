"""Patch normalisation against its plain formula; windows and segments against the oracle."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from PIL import Image

from seqvpr.data.traversal import Traversal, segments_from_gaps
from seqvpr.features.patchnorm import PatchNormConfig, patch_normalize, patchnorm_descriptors
from seqvpr.sequences.windows import window_starts
from tests import oracles


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


@settings(max_examples=200, deadline=None)
@given(st.lists(st.booleans(), max_size=30), st.integers(1, 8), st.integers(0, 7), st.sampled_from(["drop", "shift"]))
def test_window_starts_match_oracle(breaks, span, offset, boundary):
    offset = min(offset, span - 1)
    segments = np.cumsum([0] + breaks)
    fast = window_starts(segments, span, offset, boundary)
    for i in range(len(segments)):
        expected = oracles.window_start(list(segments), i, span, offset, boundary)
        assert fast[i] == (-1 if expected is None else expected)


def test_select_starts_new_segment_at_removed_frames():
    t = Traversal.from_descriptors(np.zeros((10, 2)))
    kept = t.select(np.array([0, 1, 2, 5, 6, 9]))
    assert list(kept.segment_ids) == [0, 0, 0, 1, 1, 2]
    assert list(kept.frame_index) == [0, 1, 2, 5, 6, 9]


def test_segments_from_gaps():
    ids = segments_from_gaps(frame_numbers=np.array([10, 20, 30, 50, 60]), max_frame_step=10)
    assert list(ids) == [0, 0, 0, 1, 1]
    ids = segments_from_gaps(timestamps=np.array([0, 1, 2, 10, 11.0]), max_time_gap=3)
    assert list(ids) == [0, 0, 0, 1, 1]
