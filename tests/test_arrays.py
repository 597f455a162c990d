"""The one home for reading arrays: nothing unpickled, any byte order read as native, special files refused before
they are opened (a FIFO never hangs), and a zip bomb refused by its sizes before anything is allocated."""

from __future__ import annotations

import os
import struct
import threading
import time
import tracemalloc
import zipfile
from pathlib import Path

import numpy as np
import pytest

from seqvpr import arrays
from seqvpr.arrays import check_regular_file, load_mat, load_npy, open_npz
from seqvpr.errors import SeqvprError
from tests.helpers import raises_one_line


class Marker:
    """Unpickling this would create a file."""

    def __init__(self, path):
        self.path = str(path)

    def __reduce__(self):
        return (open, (self.path, "w"))


def finishes(fn, *args, seconds: float = 5.0) -> BaseException | None:
    """Run ``fn`` in a thread; fail when it has not returned within ``seconds`` (a hang); what it raised."""
    raised: list[BaseException] = []

    def run():
        try:
            fn(*args)
        except BaseException as error:  # noqa: BLE001 - handed to the test
            raised.append(error)

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    thread.join(seconds)
    assert not thread.is_alive(), f"{fn.__name__} hung on {args}"
    return raised[0] if raised else None


def read_npz(path):
    with open_npz(path) as archive:
        return {name: archive[name] for name in archive.files}


def test_object_arrays_are_refused_and_never_unpickled(tmp_path):
    marker = tmp_path / "marker"
    payload = np.array([Marker(marker), 1], dtype=object)
    np.save(tmp_path / "objects.npy", payload)
    np.savez(tmp_path / "objects.npz", fine=np.zeros(3), bad=payload)
    message = raises_one_line("holds Python objects (a pickle); seqvpr never unpickles a file", load_npy,
                              tmp_path / "objects.npy")
    assert str(tmp_path / "objects.npy") in message
    message = raises_one_line("seqvpr never unpickles a file", read_npz, tmp_path / "objects.npz")
    assert "member bad.npy" in message
    assert not marker.exists()


@pytest.mark.parametrize("dtype", ["float32", "int64"])
def test_big_endian_arrays_read_equal_to_native(tmp_path, dtype):
    values = (np.arange(24).reshape(4, 6) * 3 - 7).astype(dtype)
    np.save(tmp_path / "big.npy", values.astype(values.dtype.newbyteorder(">")))
    np.savez(tmp_path / "big.npz", a=values.astype(values.dtype.newbyteorder(">")))
    for array in (load_npy(tmp_path / "big.npy"), load_npy(tmp_path / "big.npy", mmap_mode="r"),
                  read_npz(tmp_path / "big.npz")["a"]):
        assert array.dtype == np.dtype(dtype) and array.dtype.isnative
        np.testing.assert_array_equal(array, values)


def test_a_native_file_is_mapped_when_asked(tmp_path):
    np.save(tmp_path / "native.npy", np.arange(10, dtype=np.float32))
    assert isinstance(load_npy(tmp_path / "native.npy", mmap_mode="r"), np.memmap)


@pytest.mark.parametrize("reader", [load_npy, read_npz, lambda p: check_regular_file(p, "a thing")])
def test_a_fifo_is_refused_without_hanging(tmp_path, reader):
    fifo = tmp_path / "pipe.npy"
    os.mkfifo(fifo)
    error = finishes(reader, fifo)
    assert isinstance(error, SeqvprError) and "named pipe (FIFO)" in str(error) and str(fifo) in str(error)


def test_devices_and_folders_are_refused(tmp_path):
    raises_one_line("/dev/zero: is a character device, not a regular file", load_npy, "/dev/zero")
    raises_one_line("is a folder, not a regular file; give a .npz archive as a file", read_npz, tmp_path)
    raises_one_line("no such file", load_npy, tmp_path / "absent.npy")


def test_a_header_promising_more_than_the_file_holds_is_refused_before_allocating(tmp_path):
    header = {"descr": "<f8", "fortran_order": False, "shape": (1 << 20, 1 << 20)}  # 8 TiB
    with open(tmp_path / "huge.npy", "wb") as handle:
        np.lib.format.write_array_header_1_0(handle, header)
        handle.write(b"\0" * 64)
    raises_one_line("truncated: its header promises 8192.0 GiB", load_npy, tmp_path / "huge.npy")
    with zipfile.ZipFile(tmp_path / "huge.npz", "w") as archive:
        archive.writestr("a.npy", (tmp_path / "huge.npy").read_bytes())
    raises_one_line("(member a.npy): truncated", read_npz, tmp_path / "huge.npz")


def write_member(path, payload: bytes, claimed: int) -> None:
    """A .npz whose one deflated member holds ``payload`` but whose central directory claims ``claimed`` bytes
    uncompressed: a crafted bomb (what a reader trusts before decompressing)."""
    info = zipfile.ZipInfo("descriptors.npy")
    info.compress_type = zipfile.ZIP_DEFLATED
    with zipfile.ZipFile(path, "w") as archive:
        with archive.open(info, "w", force_zip64=True) as member:
            member.write(payload)
        archive.filelist[0].file_size = claimed


def test_a_zip_bomb_is_refused_by_its_size_fast_and_without_allocating(tmp_path):
    bomb = tmp_path / "bomb.npz"
    write_member(bomb, b"\0" * (1 << 20), 64 << 30)
    tracemalloc.start()
    start = time.perf_counter()
    message = raises_one_line("would decompress to 64.0 GiB", read_npz, bomb)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert time.perf_counter() - start < 2 and peak < 16 << 20
    assert str(bomb) in message and "descriptors.npy" in message and "of memory available" in message


def test_a_member_claiming_more_than_deflate_can_give_is_refused(tmp_path):
    liar = tmp_path / "liar.npz"
    write_member(liar, os.urandom(4096), 512 << 20)
    raises_one_line("claims 512.0 MiB from", read_npz, liar)


def test_an_honest_member_larger_than_memory_is_refused(tmp_path, monkeypatch):
    np.savez_compressed(tmp_path / "zeros.npz", descriptors=np.zeros((1024, 1024), np.float64))
    monkeypatch.setattr(arrays, "memory_cap", lambda: 1 << 20)
    raises_one_line("would decompress to 8.0 MiB, more than the 1.0 MiB of memory available", read_npz,
                    tmp_path / "zeros.npz")
    monkeypatch.undo()
    assert read_npz(tmp_path / "zeros.npz")["descriptors"].shape == (1024, 1024)


def _element(kind: int, payload: bytes) -> bytes:
    """A MAT v5 data element: type, length, payload padded to 8 bytes."""
    return struct.pack("<II", kind, len(payload)) + payload + b"\0" * (-len(payload) % 8)


def _matrix(mclass: int, name: bytes, body: bytes) -> bytes:
    flags = _element(6, struct.pack("<II", mclass, 0))
    return _element(14, flags + _element(5, struct.pack("<ii", 1, 1)) + _element(1, name) + body)


def write_function_handle_mat(path, name: str = "f") -> None:
    """A MAT v5 file whose variable ``name`` is a MATLAB function handle (which scipy's writer cannot make)."""
    inner = _matrix(6, b"", _element(9, struct.pack("<d", 1.0)))  # mxDOUBLE_CLASS 1.0
    header = b"MATLAB 5.0 MAT-file".ljust(116, b" ") + b"\0" * 8 + struct.pack("<H", 0x0100) + b"IM"
    path.write_bytes(header + _matrix(16, name.encode(), inner))  # 16: mxFUNCTION_CLASS


def test_a_matlab_function_handle_is_one_line(tmp_path):
    write_function_handle_mat(tmp_path / "fn.mat", "GT")
    message = raises_one_line("variable 'GT' is a function handle; seqvpr reads only numeric arrays and structs",
                              load_mat, tmp_path / "fn.mat")
    assert str(tmp_path / "fn.mat") in message


def _file_rss_kb() -> int:
    with open(f"/proc/{os.getpid()}/status") as handle:
        return next(int(line.split()[1]) for line in handle if line.startswith("RssFile:"))


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="reads this process's memory from /proc")
def test_released_pages_leave_the_process_and_read_back_the_same(tmp_path):
    """A memory-mapped file's pages handed back leave this process's memory and read back as they were; memory
    that is not a mapped file is never advised (the advice would zero it)."""
    from seqvpr.arrays import file_mapped, load_npy, release_pages

    values = np.random.default_rng(0).standard_normal((4096, 1024)).astype(np.float32)  # 16 MiB
    np.save(tmp_path / "a.npy", values)
    mapped = np.asarray(load_npy(tmp_path / "a.npy", mmap_mode="r"))
    assert file_mapped(mapped) and not file_mapped(values)
    assert np.array_equal(mapped, values)
    before = _file_rss_kb()
    release_pages(mapped)
    assert _file_rss_kb() < before - 8 * 1024
    assert np.array_equal(mapped, values)
    release_pages(values)
    assert np.array_equal(values, np.random.default_rng(0).standard_normal((4096, 1024)).astype(np.float32))


@pytest.mark.parametrize("compressed", [False, True])
def test_mat_files_whose_sizes_lie_are_one_line_before_scipy_reads_them(tmp_path, compressed):
    """scipy's MAT reader trusts element sizes and dimensions (a lying size crashed the process, a lying dimension
    took a minute): both are one line first; real files of every class read as before (a sparse matrix's dimensions
    may exceed its bytes)."""
    import scipy.io
    import scipy.sparse

    path = tmp_path / "x.mat"
    contents = {"a": np.random.default_rng(0).random((6, 4)), "s": {"f": np.eye(3), "g": "text"},
                "c": np.array([[1.0, 2.0]], dtype=object), "sp": scipy.sparse.csc_matrix(([1.0], ([0], [0])),
                                                                                        shape=(100000, 100000))}
    scipy.io.savemat(path, contents, do_compression=compressed)
    assert sorted(k for k in load_mat(path) if not k.startswith("__")) == ["a", "c", "s", "sp"]
    if compressed:
        return
    data = bytearray(path.read_bytes())
    lying_size = bytearray(data)
    lying_size[128 + 12 : 128 + 16] = (2**31).to_bytes(4, "little")  # the first matrix's flags claim 2 GiB
    path.write_bytes(bytes(lying_size))
    raises_one_line("a MATLAB element at byte", load_mat, path)
    lying_dims = bytearray(data)
    lying_dims[128 + 36 : 128 + 40] = (10**6).to_bytes(4, "little")  # the first matrix's second dimension
    path.write_bytes(bytes(lying_dims))
    raises_one_line("does not hold its", load_mat, path)
