"""Reading image files: one place that turns any file PIL opens (8-bit, 16-bit or 32-bit grayscale, palette,
RGBA...) into 8-bit RGB or grayscale, and any unreadable, truncated or non-image file into one line naming it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

from seqvpr.arrays import check_regular_file
from seqvpr.errors import SeqvprError

#: integer modes wider than 8 bits, with the largest value each can hold
WIDE_MODES = {"I;16": 65535, "I;16B": 65535, "I;16L": 65535, "I;16N": 65535, "I": None, "F": None}


def to_8bit(image: Image.Image, mode: str = "RGB") -> Image.Image:
    """``image`` as 8-bit ``mode`` ("RGB" or "L"): wide grayscale is scaled to 0-255 (16-bit by its full range,
    32-bit integer or float by the image's own maximum), never clipped, so a 16-bit frame is not a white one."""
    if image.mode in WIDE_MODES:
        values = np.asarray(image, dtype=np.float64)
        top = WIDE_MODES[image.mode] or max(float(values.max()), 1.0)
        image = Image.fromarray(np.clip(np.rint(values / top * 255.0), 0, 255).astype(np.uint8), "L")
    return image.convert(mode)


def read_image(path: str | Path, mode: str = "RGB") -> Image.Image:
    """The image file as 8-bit ``mode``, fully decoded (a truncated file fails here, not later); one with more pixels
    than PIL's ``Image.MAX_IMAGE_PIXELS`` (a decompression bomb) is one line with its size, never a warning."""
    if Path(path).exists():
        check_regular_file(path, "an image")
    try:
        return decode_image(path, str(path), mode)
    except FileNotFoundError:
        raise SeqvprError(f"{path}: no such image") from None


def decode_image(source, where: str, mode: str = "RGB", what: str = "image") -> Image.Image:
    """An image file or binary stream (a camera message's bytes) decoded whole as 8-bit ``mode``; a decompression
    bomb or anything unreadable is one line naming ``where`` (``what`` says what it should have been)."""
    import warnings

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", Image.DecompressionBombWarning)
            with Image.open(source) as image:
                image.load()
                return to_8bit(image, mode)
    except FileNotFoundError:
        raise
    except (Image.DecompressionBombError, Image.DecompressionBombWarning) as error:
        raise SeqvprError(f"{where}: too large to decode safely ({' '.join(str(error).split())})") from None
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError) as error:
        raise SeqvprError(f"{where}: not a readable {what} ({type(error).__name__}: {error})") from None


#: bytes per pixel of the raw encodings a ``sensor_msgs/Image`` may hold that seqvpr reads
RAW_CHANNELS = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "mono8": 1, "mono16": 2}


def raw_pixels(encoding: str, height: int, width: int, step: int, bigendian: bool, data, where: str) -> np.ndarray:
    """An RGB (or gray) uint8 array of the raw pixels a ``sensor_msgs/Image`` holds (rgb8, bgr8, rgba8, bgra8,
    mono8; mono16 by its high byte): one line naming ``where`` for an unknown encoding, an empty image, or a buffer
    whose size is not what its height, width and step say."""
    channels = RAW_CHANNELS.get(encoding)
    if channels is None:
        raise SeqvprError(f"{where}: image encoding {encoding!r} is not supported ({', '.join(RAW_CHANNELS)})")
    if height < 1 or width < 1:
        raise SeqvprError(f"{where}: an empty image ({width}x{height} {encoding})")
    if step < width * channels:
        raise SeqvprError(f"{where}: step {step} is shorter than a row of {width} {encoding} pixels "
                          f"({width * channels} bytes)")
    buffer = np.frombuffer(data, np.uint8) if not isinstance(data, np.ndarray) else data.view(np.uint8).ravel()
    if buffer.size != height * step:
        raise SeqvprError(f"{where}: {buffer.size} bytes of pixels, where a {width}x{height} {encoding} image with "
                          f"step {step} holds {height * step}")
    rows = buffer.reshape(height, step)[:, : width * channels]
    if encoding == "mono16":
        wide = rows.view(">u2" if bigendian else "<u2").reshape(height, width)
        return (wide >> 8).astype(np.uint8)
    pixels = rows.reshape(height, width, channels) if channels > 1 else rows.reshape(height, width)
    if encoding.startswith("bgr"):
        pixels = pixels[..., 2::-1]
    return np.ascontiguousarray(pixels[..., :3] if channels == 4 else pixels)
