"""Reading an image file: a decompression bomb (more pixels than PIL's limit) and a FIFO are one line each, never a
warning, a traceback or a hang."""

from __future__ import annotations

import os
import warnings

import numpy as np
import pytest
from PIL import Image

from seqvpr.data.images import read_image
from seqvpr.errors import SeqvprError
from tests.helpers import raises_one_line
from tests.test_arrays import finishes


@pytest.mark.parametrize("size", [(15, 10), (40, 40)])  # PIL warns above the limit, refuses above twice it
def test_an_image_over_the_pixel_limit_is_one_line_with_its_size(tmp_path, monkeypatch, size):
    Image.fromarray(np.zeros(size[::-1], np.uint8)).save(tmp_path / "big.png")
    monkeypatch.setattr(Image, "MAX_IMAGE_PIXELS", 100)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no warning escapes
        message = raises_one_line("too large to decode safely", read_image, tmp_path / "big.png")
    assert f"{size[0] * size[1]} pixels" in message and str(tmp_path / "big.png") in message
    monkeypatch.undo()
    assert read_image(tmp_path / "big.png").size == size


def test_a_fifo_named_as_an_image_is_refused_without_hanging(tmp_path):
    os.mkfifo(tmp_path / "frame.png")
    error = finishes(read_image, tmp_path / "frame.png")
    assert isinstance(error, SeqvprError) and "named pipe (FIFO)" in str(error)
