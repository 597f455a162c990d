"""The one home for reading arrays from files a user names: ``.npy``, ``.npz`` and MATLAB ``.mat``. Nothing is ever
unpickled (object arrays are refused), any byte order reads as native, a FIFO, device, socket or folder given as a
file is refused before it is opened (a FIFO would hang), and a ``.npz`` member that would decompress to more than
memory holds (a zip bomb) or more than its header promises is refused before anything is allocated."""

from __future__ import annotations

import contextlib
import os
import stat
import tokenize
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from seqvpr.errors import SeqvprError

PICKLE_REFUSAL = "holds Python objects (a pickle); seqvpr never unpickles a file"
#: deflate cannot shrink data more than about 1032:1: a member claiming more is lying about its size
MAX_DEFLATE_RATIO = 1100
_SPECIAL = ((stat.S_ISFIFO, "a named pipe (FIFO)"), (stat.S_ISCHR, "a character device"),
            (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"), (stat.S_ISDIR, "a folder"))


def check_regular_file(path: str | Path, what: str) -> Path:
    """``path`` as a Path when it names a regular file (after links); a FIFO, device, socket or folder is one line
    naming it, decided by ``os.stat`` before anything opens it (opening a FIFO would wait for a writer forever)."""
    path = Path(path)
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        raise SeqvprError(f"{path}: no such file ({what})") from None
    except OSError as error:
        raise SeqvprError(f"{path}: cannot be read as {what} ({error.strerror or type(error).__name__})") from None
    for test, kind in _SPECIAL:
        if test(mode):
            raise SeqvprError(f"{path}: is {kind}, not a regular file; give {what} as a file")
    if not stat.S_ISREG(mode):
        raise SeqvprError(f"{path}: not a regular file; give {what} as a file")
    return path


def memory_cap() -> int:
    """Bytes of memory available now (``MemAvailable``, else all physical memory): the most one array may need."""
    with contextlib.suppress(OSError, ValueError, IndexError):
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    with contextlib.suppress(OSError, ValueError, AttributeError):
        return os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    return 1 << 40


def _size(nbytes: float) -> str:
    """Bytes in words: ``64.0 GiB``."""
    for unit in ("bytes", "KiB", "MiB", "GiB"):
        if nbytes < 1024 or unit == "GiB":
            return f"{nbytes:.0f} {unit}" if unit == "bytes" else f"{nbytes:.1f} {unit}"
        nbytes /= 1024
    return f"{nbytes:.1f} TiB"  # pragma: no cover


def read_npy_header(handle: BinaryIO, label: str) -> tuple[tuple[int, ...], np.dtype]:
    """The shape and dtype a ``.npy`` header declares (the handle then at the data), read as numpy reads it but
    never unpickling; a header that is damaged, cut short or of an unknown version is one line naming ``label``."""
    fmt = np.lib.format
    try:
        version = fmt.read_magic(handle)
        if version not in ((1, 0), (2, 0), (3, 0)):
            raise ValueError(f"format version {version} is not known")
        reader = fmt.read_array_header_1_0 if version == (1, 0) else fmt.read_array_header_2_0  # 3.0: 2.0 in UTF-8
        shape, _, dtype = reader(handle)
    except (ValueError, EOFError, SyntaxError, TypeError, KeyError, OverflowError, tokenize.TokenError) as error:
        raise SeqvprError(f"{label}: not a NumPy .npy array ({' '.join(str(error).split())[:200]})") from None
    return shape, dtype


def _read_header(handle: BinaryIO, label: str) -> tuple[np.dtype, int, int]:
    """The dtype, element count and header length of the ``.npy`` data behind ``handle``; an object dtype (a pickle)
    is refused here, before numpy reads any of it."""
    shape, dtype = read_npy_header(handle, label)
    if dtype.hasobject:
        raise SeqvprError(f"{label}: {PICKLE_REFUSAL}")
    return dtype, int(np.prod(shape, dtype=np.int64)) if shape else 1, handle.tell()


def _check_length(label: str, dtype: np.dtype, count: int, header: int, size: int) -> None:
    """The data the header promises is what the file holds: a header claiming more (a truncated file, or one crafted
    to make numpy allocate terabytes) is one line with both sizes."""
    wanted = header + count * dtype.itemsize
    if size < wanted:
        raise SeqvprError(f"{label}: truncated: its header promises {_size(wanted)} ({count} x {dtype}), the file "
                          f"holds {_size(size)}")


def native(array: np.ndarray) -> np.ndarray:
    """``array`` in the machine's byte order (a big-endian file's values, unchanged, as native numbers)."""
    if array.dtype.isnative:
        return array
    return array.astype(array.dtype.newbyteorder("="))


def load_npy(path: str | Path, mmap_mode: str | None = None) -> np.ndarray:
    """A ``.npy`` array, never unpickled, in native byte order. With ``mmap_mode`` a native file is mapped; a
    non-native one (big-endian) cannot be mapped as native numbers, so it is loaded as a native copy instead."""
    path = check_regular_file(path, "a .npy array")
    with open(path, "rb") as handle:
        dtype, count, header = _read_header(handle, str(path))
    _check_length(str(path), dtype, count, header, os.stat(path).st_size)
    if count * dtype.itemsize > memory_cap() and mmap_mode is None:
        raise SeqvprError(f"{path}: a {_size(count * dtype.itemsize)} array, more than the memory available")
    mapped = mmap_mode if dtype.isnative else None
    return native(np.load(path, mmap_mode=mapped, allow_pickle=False))


class NpzArrays:
    """The arrays of an opened ``.npz`` (checked by ``open_npz``): ``files``, ``name in``, ``[name]`` (native). Only
    its ``.npy`` members are arrays; any other member of the zip is not one of them."""

    def __init__(self, archive: Any, label: str) -> None:
        self._archive, self.label = archive, label
        self.files: list[str] = [name[: -len(".npy")] for name in archive.zip.namelist() if name.endswith(".npy")]

    def __contains__(self, name: str) -> bool:
        return name in self.files

    def __getitem__(self, name: str) -> np.ndarray:
        if name not in self.files:
            raise KeyError(name)
        return native(self._archive[name])


def _check_members(archive: zipfile.ZipFile, path: Path) -> None:
    """Every member an ``.npy`` whose uncompressed size fits in memory and is what its compressed size can give,
    holding no objects and no more than its header promises; refused before anything is decompressed whole."""
    total, cap = 0, memory_cap()
    for info in archive.infolist():
        label = f"{path} (member {info.filename})"
        total += info.file_size
        if info.file_size > cap or total > cap:
            raise SeqvprError(f"{label}: would decompress to {_size(max(info.file_size, total))}, more than the "
                              f"{_size(cap)} of memory available (a zip bomb?)")
        limit = info.compress_size * MAX_DEFLATE_RATIO + 4096 if info.compress_type != zipfile.ZIP_STORED \
            else info.compress_size
        if info.file_size > limit:
            raise SeqvprError(f"{label}: claims {_size(info.file_size)} from {_size(info.compress_size)} compressed, "
                              "more than compression can give (a damaged or crafted archive)")
        if not info.filename.endswith(".npy"):
            continue
        with archive.open(info) as member:
            dtype, count, header = _read_header(member, label)
        _check_length(label, dtype, count, header, info.file_size)


@contextlib.contextmanager
def open_npz(path: str | Path) -> Iterator[NpzArrays]:
    """``with open_npz(path) as arrays:`` the arrays of a ``.npz``, never unpickled, in native byte order; a member
    that is a pickle, claims more than it holds, or would not fit in memory is one line naming it and its size. A
    file that is no zip raises zipfile's own error, for the caller's ``reading`` boundary to name as its kind."""
    path = check_regular_file(path, "a .npz archive")
    with zipfile.ZipFile(path) as archive:
        _check_members(archive, path)
    with np.load(path, allow_pickle=False) as archive:
        yield NpzArrays(archive, str(path))


MAT_MATRIX, MAT_COMPRESSED = 14, 15  # the MAT v5 element types that hold other elements


def check_mat_elements(path: Path) -> None:
    """A MAT v5 file's elements each fit the element (or file) that holds them, compressed ones included: scipy's
    reader trusts the sizes and can crash the process on a file whose sizes lie, so a lie is one line here first.
    Files of other versions (v4, v7.3) are left to the reader's own errors."""
    import mmap

    size = path.stat().st_size
    with open(path, "rb") as handle:
        head = handle.read(128)
        if size < 128 or head[126:128] not in (b"IM", b"MI") or head[124:126] not in (b"\x00\x01", b"\x01\x00"):
            return
        # the file's pages as a view (no copy): only the tags and headers walked here are read
        data = memoryview(mmap.mmap(handle.fileno(), 0, access=mmap.ACCESS_READ))
    _check_elements(data, 128, size, "<" if head[126:128] == b"IM" else ">", path, 0)


def _check_elements(data: bytes | memoryview, start: int, end: int, order: str, path: Path, depth: int) -> None:
    """Every element tag in ``data[start:end]`` and what it declares fit there; matrices and compressed elements
    checked inside (small elements: four bytes of data in the tag's second half)."""
    import struct
    import zlib

    if depth > 32:
        raise SeqvprError(f"{path}: MATLAB elements nested more than 32 deep (a damaged file)")
    _mat_elements(data, start, end, order, path)  # every tag known and fitting, before any is read inside
    at = start
    while at + 8 <= end:
        kind, size = struct.unpack_from(order + "II", data, at)
        if kind >> 16:  # small element: its size in the upper half, its data in the tag
            at += 8
            continue
        if kind == MAT_COMPRESSED:
            try:
                inner = zlib.decompressobj().decompress(data[at + 8 : at + 8 + size], memory_cap())
            except zlib.error as error:
                raise SeqvprError(f"{path}: a compressed MATLAB element at byte {at} is damaged ({error})") from None
            _check_elements(inner, 0, len(inner), order, path, depth + 1)
        elif kind == MAT_MATRIX:
            _check_matrix_size(data, at + 8, at + 8 + size, order, path)
            _check_elements(data, at + 8, at + 8 + size, order, path, depth + 1)
        at += 8 + size + (0 if kind == MAT_COMPRESSED else -size % 8)


MAT_TYPE_BYTES = {1: 1, 2: 1, 3: 2, 4: 2, 5: 4, 6: 4, 7: 4, 9: 8, 12: 8, 13: 8, 14: 1, 15: 1, 16: 1, 17: 2, 18: 4}
MAT_CELL, MAT_STRUCT, MAT_CHAR, MAT_SPARSE = 1, 2, 4, 5
MAT_NUMERIC = range(6, 16)  # double, single, int8 ... uint64 (a logical array is uint8)


def _mat_elements(data: bytes | memoryview, start: int, end: int, order: str,
                  path: Path) -> list[tuple[int, bytes | memoryview]]:
    """The elements in ``data[start:end]`` as (type, data), each checked to be of a known type and to fit."""
    import struct

    found, at = [], start
    while at + 8 <= end:
        kind, size = struct.unpack_from(order + "II", data, at)
        small = kind >> 16
        kind = kind & 0xFFFF if small else kind
        if kind not in MAT_TYPE_BYTES or (small and small > 4) or (not small and size > end - at - 8):
            raise SeqvprError(f"{path}: a MATLAB element at byte {at} is damaged (type {kind}, "
                              f"{small or size} bytes, {end - at - 8} remain)")
        found.append((kind, data[at + 4 : at + 4 + small] if small else data[at + 8 : at + 8 + size]))
        at += 8 if small else 8 + size + (0 if kind == MAT_COMPRESSED else -size % 8)
    return found


def _check_matrix_size(data: bytes | memoryview, start: int, end: int, order: str, path: Path) -> None:
    """A matrix's parts agree with its dimensions: a numeric or character array's data holds exactly its elements,
    a cell or struct holds as many matrices as it has elements (times fields); scipy trusts them and otherwise reads
    past the data or crashes."""
    import struct

    parts = _mat_elements(data, start, end, order, path)
    if len(parts) < 3 or len(parts[0][1]) < 4 or len(parts[1][1]) % 4:
        return  # an empty matrix: nothing to check
    flags = struct.unpack_from(order + "I", parts[0][1])[0]
    matrix_class, complex_part = flags & 0xFF, bool(flags & 0x800)
    dims = struct.unpack(order + f"{len(parts[1][1]) // 4}i", parts[1][1])
    count = int(np.prod(dims, dtype=object)) if dims else 0
    where = f"{path}: a MATLAB matrix at byte {start - 8} with dimensions {list(dims)}"
    if min(dims, default=0) < 0:
        raise SeqvprError(f"{where} is damaged (a negative dimension)")
    if matrix_class in MAT_NUMERIC or matrix_class == MAT_CHAR:
        values = parts[3:]
        expected = 2 if complex_part else 1
        if count and (len(values) != expected or any(kind != 16 and len(body) != count * MAT_TYPE_BYTES[kind]
                                                     for kind, body in values)):
            raise SeqvprError(f"{where} does not hold its {count} elements (a damaged file)")
    elif matrix_class == MAT_CELL:
        if len(parts) - 3 != count:
            raise SeqvprError(f"{where} holds {len(parts) - 3} cells, not {count} (a damaged file)")
    elif matrix_class == MAT_STRUCT and len(parts) >= 5:
        name_length = struct.unpack_from(order + "i", parts[3][1])[0] if len(parts[3][1]) >= 4 else 0
        fields = len(parts[4][1]) // name_length if name_length > 0 else -1
        if fields < 0 or len(parts) - 5 != count * fields:
            raise SeqvprError(f"{where} does not hold its {count} structs of {max(fields, 0)} fields (a damaged "
                              "file)")


def load_mat(path: str | Path, **options: Any) -> dict[str, Any]:
    """The variables of a MATLAB v5 ``.mat`` (scipy's reader runs no code); a v7.3 file, one scipy cannot read, or a
    MATLAB function handle or class object among them is one line naming it, as seqvpr reads only numbers, text and
    structs."""
    import scipy.io
    from scipy.io.matlab import MatlabFunction, MatlabOpaque

    path = check_regular_file(path, "a MATLAB .mat file")
    check_mat_elements(path)
    try:
        with open(path, "rb") as handle:
            contents = scipy.io.loadmat(handle, **options)
    except NotImplementedError:
        raise SeqvprError(f"{path}: MATLAB v7.3 (HDF5) files are not supported; save it with -v7") from None
    except (ValueError, TypeError, OSError) as error:
        raise SeqvprError(f"{path}: not a readable MATLAB file ({error})") from None
    for name, value in contents.items():
        if isinstance(value, (MatlabFunction, MatlabOpaque)):
            kind = "a function handle" if isinstance(value, MatlabFunction) else "a MATLAB class object"
            raise SeqvprError(f"{path}: variable {name!r} is {kind}; seqvpr reads only numeric arrays and structs")
    return contents


def file_mapped(array: np.ndarray) -> bool:
    """Whether ``array`` is a view of a memory-mapped file (its pages can be handed back and read again)."""
    import mmap

    node = array
    while node is not None:
        if isinstance(node, (np.memmap, mmap.mmap)):
            return True
        node = getattr(node, "base", None)
    return False


def release_pages(view: np.ndarray) -> None:
    """Hand the pages under a contiguous view of a memory-mapped file back (``MADV_DONTNEED``): they stay in the
    page cache but leave this process's memory, so reading a large file end to end does not grow it. Anything not
    file-mapped (where the advice would discard data) is left alone, as is a platform without ``madvise``."""
    import ctypes
    import mmap

    if not (view.size and view.flags.c_contiguous and file_mapped(view) and hasattr(mmap, "MADV_DONTNEED")):
        return
    start, end = view.ctypes.data, view.ctypes.data + view.nbytes
    first = -(-start // mmap.PAGESIZE) * mmap.PAGESIZE  # the whole pages inside the view: a neighbour's stay
    last = end // mmap.PAGESIZE * mmap.PAGESIZE
    if last > first:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.madvise(ctypes.c_void_p(first), ctypes.c_size_t(last - first), ctypes.c_int(mmap.MADV_DONTNEED))
