"""Content identities of saved files: a file's digest (sha256 of its bytes), an artifact's identity (a digest of
its files' digests), and a check that a file still holds what its manifest says. A file checked once is
remembered by its inode, size and change times under the cache folder, so opening a large artifact again costs a
``stat``, not a read; a file copied, replaced, symlinked from elsewhere or edited in place is read again."""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Mapping
from pathlib import Path

from seqvpr.cache import cache_folder
from seqvpr.errors import SeqvprError

ALGORITHM = "sha256"
_CHUNK = 1 << 22


def digest_bytes(data: bytes) -> str:
    """The digest of some bytes: ``sha256:HEX``."""
    return f"{ALGORITHM}:{hashlib.sha256(data).hexdigest()}"


class DigestWriter:
    """A binary handle that keeps only the digest of what is written to it (``np.save`` and plain writes take
    it): the digest a file of those bytes would have, without the file."""

    def __init__(self) -> None:
        self.hash = hashlib.new(ALGORITHM)

    def write(self, data) -> int:
        self.hash.update(data)
        return len(data)

    def digest(self) -> str:
        return f"{ALGORITHM}:{self.hash.hexdigest()}"

    def __enter__(self) -> DigestWriter:
        return self

    def __exit__(self, *_: object) -> None:
        return None


def digest_file(path: str | Path) -> str:
    """The digest of a file's bytes, read in one streamed pass: ``sha256:HEX``."""
    with open(path, "rb") as handle:
        return f"{ALGORITHM}:{hashlib.file_digest(handle, ALGORITHM).hexdigest()}"


def combined_identity(digests: Mapping[str, str]) -> str:
    """One identity for a set of named files: the digest of their names and digests (order does not matter)."""
    return digest_bytes(json.dumps(sorted(digests.items())).encode())


def _stamp(path: Path) -> str | None:
    """What makes a file's bytes this file's bytes: device, inode, size, modification and change times (ctime
    cannot be set back, so an edit in place is always seen); None if it cannot be read."""
    try:
        s = os.stat(path)
    except OSError:
        return None
    return f"{s.st_dev}:{s.st_ino}:{s.st_size}:{s.st_mtime_ns}:{s.st_ctime_ns}"


def _record(stamp: str) -> Path:
    return cache_folder("verified") / hashlib.sha256(stamp.encode()).hexdigest()[:40]


def remembered_digest(path: str | Path) -> str | None:
    """The digest recorded when this very file (same inode, size and times) was last hashed, or None."""
    stamp = _stamp(Path(path))
    if stamp is None:
        return None
    try:
        return _record(stamp).read_text().strip() or None
    except OSError:
        return None


def remember_digest(path: str | Path, digest: str) -> None:
    """Record that ``path``, as it is now, holds ``digest`` (silently skipped where the cache is not writable)."""
    stamp = _stamp(Path(path))
    if stamp is None:
        return
    record = _record(stamp)
    try:
        record.parent.mkdir(parents=True, exist_ok=True)
        temporary = record.with_name(f".{record.name}.{os.getpid()}")
        temporary.write_text(digest)
        os.replace(temporary, record)
    except OSError:
        pass


def file_digest(path: str | Path, fresh: bool = False) -> str:
    """A file's digest: the remembered one when the file is unchanged since it was hashed (unless ``fresh``),
    else read and remembered."""
    digest = None if fresh else remembered_digest(path)
    if digest is None:
        digest = digest_file(path)
        remember_digest(path, digest)
    return digest


def check_digest(path: str | Path, expected: str, owner: str, fresh: bool = False) -> None:
    """``path`` holds the bytes ``expected`` names, or one line saying it was changed or replaced since ``owner``
    (the manifest that records it) was written."""
    path = Path(path)
    if not path.is_file():
        raise SeqvprError(f"{path}: missing (named by {owner})")
    try:
        found = file_digest(path, fresh)
    except OSError as error:
        raise SeqvprError(f"{path}: unreadable ({error.strerror})") from None
    if found != expected:
        raise SeqvprError(f"{path}: its content is not what {owner} records (changed, replaced or copied from "
                          "elsewhere since it was written); rebuild it")


def seal_files(folder: Path, names: list[str]) -> dict[str, str]:
    """The digests of the files ``names`` in ``folder`` (just written: each read once, page-cache hot), remembered
    so that opening them later costs no read."""
    return {name: file_digest(folder / name, fresh=True) for name in names}
