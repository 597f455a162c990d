"""CosPlace's augmentation of classification images: shapes, range, seeding, switches, and each step against its
formula."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from seqvpr.errors import SeqvprError
from seqvpr.training.augment import LUMA, augment_images, color_jitter, crop_boxes, random_resized_crop, turn_hue
from seqvpr.training.settings import JistTrainSettings
from tests.helpers import examples


def images(count: int = 4, height: int = 12, width: int = 16, seed: int = 0) -> torch.Tensor:
    return torch.rand(count, 3, height, width, generator=torch.Generator().manual_seed(seed))


@settings(max_examples=examples(25), deadline=None)
@given(st.integers(1, 5), st.integers(2, 20), st.integers(2, 20), st.floats(0, 1), st.floats(0, 0.5),
       st.floats(0.05, 1), st.integers(0, 1000))
def test_shape_range_and_seed(count, height, width, jitter, hue, scale, seed):
    batch = images(count, height, width, seed)
    first = augment_images(batch, np.random.default_rng(seed), jitter, hue, scale)
    again = augment_images(batch, np.random.default_rng(seed), jitter, hue, scale)
    assert first.shape == batch.shape and torch.equal(first, again)
    assert float(first.min()) >= 0.0 and float(first.max()) <= 1.0


@settings(max_examples=examples(25), deadline=None)
@given(st.integers(1, 5), st.integers(1, 40), st.integers(1, 40), st.floats(0.01, 1), st.integers(0, 1000))
def test_crop_boxes_lie_inside_the_image(count, height, width, scale, seed):
    boxes = crop_boxes(np.random.default_rng(seed), count, height, width, scale)
    top, left, h, w = boxes.T
    assert (h >= 1).all() and (w >= 1).all() and (top >= 0).all() and (left >= 0).all()
    assert (top + h <= height).all() and (left + w <= width).all()


def test_switched_off_is_the_identity():
    batch = images()
    assert torch.equal(augment_images(batch, np.random.default_rng(0), 0.0, 0.0, 1.0), batch)


def test_hue_turn_of_zero_and_of_a_full_turn_keep_the_image():
    batch = images()
    for turns in (0.0, 1.0):
        np.testing.assert_allclose(turn_hue(batch, torch.full((4,), turns)), batch, atol=1e-5)


def test_hue_turn_keeps_gray_and_luma():
    gray_batch = images()[:, :1].expand(-1, 3, -1, -1).clone() * 0.5 + 0.25
    np.testing.assert_allclose(turn_hue(gray_batch, torch.full((4,), 0.3)), gray_batch, atol=1e-5)
    color = images() * 0.4 + 0.3  # away from the clamp
    turned = turn_hue(color, torch.full((4,), 0.1))
    luma = torch.tensor(LUMA).view(1, 3, 1, 1)
    np.testing.assert_allclose((turned * luma).sum(1), (color * luma).sum(1), atol=1e-4)
    assert not torch.allclose(turned, color, atol=1e-3)


def test_jitter_follows_torchvision_formulas():
    """Brightness, contrast and saturation with the factors the generator draws, by a plain re-computation."""
    batch = images(2)
    rng = np.random.default_rng(3)
    factors = [rng.uniform(0.5, 1.5, size=2) for _ in range(3)]
    out = color_jitter(batch, np.random.default_rng(3), 0.5, 0.0)
    for i in range(2):
        x = (batch[i] * factors[0][i]).clamp(0, 1)
        gray_mean = (x * torch.tensor(LUMA).view(3, 1, 1)).sum(0).mean()
        x = (factors[1][i] * x + (1 - factors[1][i]) * gray_mean).clamp(0, 1)
        gray = (x * torch.tensor(LUMA).view(3, 1, 1)).sum(0, keepdim=True)
        x = (factors[2][i] * x + (1 - factors[2][i]) * gray).clamp(0, 1)
        np.testing.assert_allclose(out[i], x, atol=1e-6)


def test_a_whole_image_crop_is_the_identity_and_smaller_crops_zoom():
    batch = images(1, 8, 8)
    assert torch.equal(random_resized_crop(batch, np.random.default_rng(0), 1.0), batch)
    zoomed = random_resized_crop(batch, np.random.default_rng(0), 0.1)
    assert zoomed.shape == batch.shape and not torch.allclose(zoomed, batch)


@pytest.mark.parametrize("field,value,needle", [("jitter", 1.5, "jitter"), ("hue", 0.6, "hue"),
                                                ("crop_scale", 0.0, "crop_scale")])
def test_bad_strengths_are_one_line_errors(field, value, needle):
    with pytest.raises(SeqvprError, match=needle):
        JistTrainSettings(**{field: value})
