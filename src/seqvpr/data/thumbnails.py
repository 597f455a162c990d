"""Frame thumbnails, made once per image content: a frame's small JPEG is cached under its file's digest
(``seqvpr.identity.file_digest``, remembered by the file's stamp, so a second use costs a stat a frame) in seqvpr's
cache folder; the viewer links them into a page's folder, a map built with thumbnails keeps them in one file
(``seqvpr.maps.thumbnails``), the node publishes them. A frame whose image is gone gets none."""

from __future__ import annotations

import os
import shutil
from collections.abc import Callable, Sequence
from pathlib import Path

THUMB_WIDTH = 160
THUMB_KIND = "thumbnails"


def thumbnail_cache() -> Path:
    """Where thumbnails are kept (``$SEQVPR_CACHE/thumbnails``), created when first needed."""
    from seqvpr.cache import cache_folder, writable_folder

    return writable_folder(cache_folder(THUMB_KIND))


def cached_thumbnail(image: str | Path, cache: Path) -> Path | None:
    """The cached thumbnail of ``image`` (made now if it is not there yet); None where the image cannot be read."""
    from seqvpr.identity import file_digest

    try:
        digest = file_digest(image).split(":")[-1][:32]
    except OSError:
        return None
    path = cache / f"{digest}-{THUMB_WIDTH}.jpg"
    if path.is_file():
        return path
    return path if make_thumbnail(Path(image), path) else None


def make_thumbnail(image: Path, path: Path) -> bool:
    """A JPEG ``THUMB_WIDTH`` pixels wide of ``image`` at ``path`` (written under a temporary name, then renamed)."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(image) as opened:
            opened.draft("RGB", (THUMB_WIDTH, THUMB_WIDTH))  # JPEG: decode at the nearest scale above
            small = opened.convert("RGB")
            small.thumbnail((THUMB_WIDTH, 10 * THUMB_WIDTH))
            part = path.with_name(path.name + f".{os.getpid()}.part")
            small.save(part, "JPEG", quality=80)
    except (OSError, UnidentifiedImageError, ValueError):
        return False
    os.replace(part, path)
    return True


def page_thumbnails(images: Sequence[str] | None, folder: Path, subfolder: str = "thumbs",
                    tick: Callable[[int], None] | None = None) -> list[str]:
    """Each image's thumbnail linked into ``folder/subfolder``: the page-relative source of each ("" where there is
    none). One file per distinct image content."""
    if not images:
        return []
    cache, out = thumbnail_cache(), folder / subfolder
    out.mkdir(parents=True, exist_ok=True)
    sources = []
    for image in images:
        cached = cached_thumbnail(image, cache)
        if cached is None:
            sources.append("")
        else:
            target = out / cached.name
            if not target.exists():
                _link(cached, target)
            sources.append(f"{subfolder}/{cached.name}")
        if tick:
            tick(1)
    return sources


def _link(source: Path, target: Path) -> None:
    try:
        os.link(source, target)
    except OSError:
        shutil.copyfile(source, target)
