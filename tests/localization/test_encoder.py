"""Camera frames as the encoder takes them: an image of any kind it reads, and one line for what is no image."""

from __future__ import annotations

import numpy as np
from PIL import Image

from seqvpr.localization.encoder import rgb_image
from tests.helpers import raises_one_line


def test_frames_without_pixels_or_of_another_type_are_one_line():
    assert rgb_image(np.zeros((4, 6, 3), np.uint8)).size == (6, 4)
    assert rgb_image(np.zeros((4, 6), np.uint8)).mode == "RGB"
    raises_one_line("has no pixels", rgb_image, np.zeros((0, 0, 3), np.uint8))
    raises_one_line("has no pixels", rgb_image, np.zeros((0, 5, 3), np.uint8))
    raises_one_line("has no pixels", rgb_image, Image.new("RGB", (0, 3)))
    raises_one_line("must be an H x W x 3 uint8 array", rgb_image, np.full((4, 4, 3), np.nan))
    raises_one_line("must be an H x W x 3 uint8 array", rgb_image, np.zeros((4, 4, 4), np.uint8))
