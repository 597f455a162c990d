"""The operating system's no as one line: ``os_refusal`` names the path and what to do for each errno it knows, and
the atomic writers make a failed write name the output the user gave (not a temporary), leaving no temporary and
the previous output as it was."""

from __future__ import annotations

import errno
import os
import resource

import pytest

from seqvpr.errors import os_refusal
from seqvpr.io import TEMP_TAG, atomic_folder, atomic_write, output_lock

REFUSALS = {
    errno.ENOSPC: "no space left on the device holding /data/out: free space or write elsewhere",
    errno.EDQUOT: "disk quota exceeded on the device holding /data/out",
    errno.EFBIG: "file size limit reached writing /data/out (ulimit -f",
    errno.EROFS: "/data/out is on a read-only file system: write elsewhere",
    errno.EACCES: "permission denied: /data/out",
    errno.EPERM: "operation not permitted: /data/out",
    errno.ENAMETOOLONG: "a name in /data/out is longer than the file system allows (255 bytes",
    errno.EMFILE: "too many open files (opening /data/out): raise the limit (ulimit -n)",
    errno.ENFILE: "too many open files on this system (opening /data/out)",
    errno.ENOTDIR: "/data/out: a part of it is not a folder",
    errno.EISDIR: "/data/out is a folder, and a file goes there",
    errno.ELOOP: "/data/out: too many levels of symbolic links",
    errno.EIO: "input/output error on /data/out",
}


@pytest.mark.parametrize("code", list(REFUSALS), ids=[errno.errorcode[c] for c in REFUSALS])
def test_each_refusal_is_one_line_naming_the_path(code):
    message = str(os_refusal(OSError(code, os.strerror(code), "/data/out")))
    assert message.startswith(REFUSALS[code]) and "\n" not in message, message


def test_a_rename_across_file_systems_names_both_paths():
    message = str(os_refusal(OSError(errno.EXDEV, os.strerror(errno.EXDEV), "/a/new", None, "/b/old")))
    assert "/a/new and /b/old are on different file systems" in message


def test_a_refusal_naming_no_path_says_so_and_others_are_not_ours():
    assert "(a path the system did not name)" in str(os_refusal(OSError(errno.ENOSPC, "No space left on device")))
    assert "/x/y" in str(os_refusal(OSError(errno.EACCES, "Permission denied", b"/x/y")))
    assert os_refusal(OSError(errno.EAGAIN, "Resource temporarily unavailable", "/x")) is None
    assert os_refusal(OSError("no errno at all")) is None


def _leftovers(folder):
    return [p.name for p in folder.rglob("*") if TEMP_TAG in p.name]


def test_a_full_device_mid_write_names_the_file_and_keeps_the_old_one(tmp_path):
    target = tmp_path / "predictions.csv"
    target.write_text("the previous output")
    with pytest.raises(OSError) as info, atomic_write(target) as handle:
        handle.write("half")
        raise OSError(errno.ENOSPC, "No space left on device")  # what a write() says: no path
    assert info.value.filename == str(target) and "holding " + str(target) in str(os_refusal(info.value))
    assert target.read_text() == "the previous output" and not _leftovers(tmp_path)


def test_a_refused_rename_names_the_target_not_the_temporary(tmp_path, monkeypatch):
    def refuse(source, target):
        raise PermissionError(errno.EACCES, "Permission denied", str(source), None, str(target))

    monkeypatch.setattr("seqvpr.io.rename", refuse)
    target = tmp_path / "run.json"
    with pytest.raises(PermissionError) as info, atomic_write(target) as handle:
        handle.write("{}")
    assert info.value.filename == str(target) and not _leftovers(tmp_path) and not target.exists()


def test_a_folder_write_names_the_output_folder_and_the_old_folder_stays(tmp_path):
    target = tmp_path / "map"
    target.mkdir()
    (target / "info.json").write_text("old")
    with pytest.raises(OSError) as info, atomic_folder(target, "info.json") as tmp:
        (tmp / "info.json").write_text("new")
        raise OSError(errno.EROFS, "Read-only file system", str(tmp / "descriptors.npy"))
    assert info.value.filename == str(target / "descriptors.npy")
    assert (target / "info.json").read_text() == "old" and not _leftovers(tmp_path)
    with pytest.raises(OSError) as info, atomic_folder(target, "info.json"):
        raise OSError(errno.EAGAIN, "not a write error")
    assert info.value.filename is None  # an error of another kind is not said of the output


def test_a_short_write_without_errno_is_read_as_a_full_device_or_a_size_limit(tmp_path, monkeypatch):
    """numpy reports a short write as ``N requested and M written``, with no errno."""
    def short(target):
        with pytest.raises(OSError) as info, atomic_folder(target):
            raise OSError("768000 requested and 64480 written")
        return info.value

    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    if soft == resource.RLIM_INFINITY:
        assert short(tmp_path / "a").errno is None  # room, and no size limit: nothing to say
    resource.setrlimit(resource.RLIMIT_FSIZE, (1 << 40 if hard == resource.RLIM_INFINITY else hard, hard))
    try:
        limited = short(tmp_path / "b")
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
    assert limited.errno == errno.EFBIG and limited.filename == str(tmp_path / "b")
    monkeypatch.setattr(os, "statvfs", lambda _: os.statvfs_result((4096, 4096, 100, 0, 0, 0, 0, 0, 0, 255)))
    full = short(tmp_path / "c")
    assert full.errno == errno.ENOSPC and "holding " + str(tmp_path / "c") in str(os_refusal(full))
    assert not _leftovers(tmp_path)


def test_a_lock_that_cannot_be_written_is_not_left_behind(tmp_path, monkeypatch):
    """A full device refuses the lock's process id: the empty lock would otherwise refuse every later run."""
    real = os.fdopen

    def full(fd, *args, **kwargs):
        handle = real(fd, *args, **kwargs)
        handle.close()
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "fdopen", full)
    with pytest.raises(OSError) as info, output_lock(tmp_path / "out"):
        pass
    assert info.value.filename == str(tmp_path / "out") and not list(tmp_path.iterdir())
