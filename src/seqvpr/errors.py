"""The one exception type users see: a one-line message that names the file or field at fault."""

import csv
import errno
import os
import pickle
import re
import struct
import zipfile
from collections.abc import Mapping


class SeqvprError(ValueError):
    """Bad input or an impossible request; the CLI prints the message on one line and exits non-zero."""


SETTING_NAME = re.compile(r"\{([a-z][a-z0-9_]*)\}")  # a setting named in a SettingError's template


class SettingError(SeqvprError):
    """A bad argument or setting. Its ``template`` names settings in braces (``{seq_len} must be ...``): the message
    names them as a Python caller passes them (``seq_len must be ...``), and ``naming(names)`` as another caller
    spells them (the command line's flags: ``--seq-len must be ...``)."""

    def __init__(self, template: str) -> None:
        self.template = template
        super().__init__(self.naming({}))

    def naming(self, names: Mapping[str, str]) -> str:
        """The message with each setting called what ``names`` calls it (its own name where ``names`` has none)."""
        return SETTING_NAME.sub(lambda found: names.get(found.group(1), found.group(1)), self.template)


class SeqvprWarning(UserWarning):
    """Input that works but is suspect (a ground-truth file naming frames the traversal lacks): the CLI prints it as
    one ``seqvpr: warning:`` line and goes on."""


#: what reading a malformed file raises, in numpy, scipy, zipfile, pickle, csv, tomllib, json and the file system
READ_ERRORS = (OSError, EOFError, ValueError, TypeError, KeyError, IndexError, UnicodeError, NotImplementedError,
               ArithmeticError, zipfile.BadZipFile, pickle.UnpicklingError, csv.Error, struct.error)

#: libraries whose own exception classes (scipy's MatReadError, PIL's, safetensors') mean "this file is malformed"
READER_MODULES = ("scipy.io", "PIL", "safetensors", "rosbags")


def unreadable(what: object, kind: str, error: BaseException) -> SeqvprError:
    """The one-line error for a ``what`` (a file, usually) that could not be read as a ``kind``."""
    detail = " ".join(str(error).split())[:200] or type(error).__name__
    return SeqvprError(f"{what}: not readable as {kind} ({type(error).__name__}: {detail})")


class reading:
    """``with reading(path, "a traversal"):`` turns what a malformed input raises inside the block into one
    SeqvprError naming ``path``: the boundary where every file a user names is read. SeqvprErrors pass unchanged."""

    def __init__(self, what: object, kind: str) -> None:
        self.what, self.kind = what, kind

    def __enter__(self) -> None:
        return None

    def __exit__(self, kind, error, traceback) -> bool:
        if error is None or isinstance(error, SeqvprError):
            return False
        if not (isinstance(error, READ_ERRORS) or type(error).__module__.startswith(READER_MODULES)):
            return False
        raise unreadable(self.what, self.kind, error) from error


#: errno -> what the system refused and what to do; ``{path}`` is the path it named (``{other}`` a second one)
OS_REFUSALS = {
    "ENOSPC": "no space left on the device holding {path}: free space or write elsewhere",
    "EDQUOT": "disk quota exceeded on the device holding {path}: free space or write elsewhere",
    "EFBIG": "file size limit reached writing {path} (ulimit -f, or the file system's largest file): raise the "
             "limit or write elsewhere",
    "EROFS": "{path} is on a read-only file system: write elsewhere",
    "EACCES": "permission denied: {path}: change its permissions or write elsewhere",
    "EPERM": "operation not permitted: {path}: change its permissions or write elsewhere",
    "ENAMETOOLONG": "a name in {path} is longer than the file system allows (255 bytes; 4096 for the whole path): "
                    "give a shorter one",
    "EMFILE": "too many open files (opening {path}): raise the limit (ulimit -n)",
    "ENFILE": "too many open files on this system (opening {path}): close other programs or raise the limit",
    "ENOTDIR": "{path}: a part of it is not a folder",
    "EISDIR": "{path} is a folder, and a file goes there",
    "ELOOP": "{path}: too many levels of symbolic links (a loop?)",
    "EXDEV": "{path} and {other} are on different file systems: write the output on one file system",
    "ENOENT": "{path}: no such file or folder",
    "EIO": "input/output error on {path}: the device may be failing or disconnected",
    "EBUSY": "{path} is busy (in use by the system or another program)",
    "ETXTBSY": "{path} is busy (a running program's file)",
}
_REFUSALS = {getattr(errno, name): text for name, text in OS_REFUSALS.items() if hasattr(errno, name)}


def os_refusal(error: OSError) -> SeqvprError | None:
    """The one line for an OSError whose errno says the operating system refused (no space, a read-only file system,
    permission denied, a name too long...): what happened, the path it named and what to do. None for any other."""
    text = _REFUSALS.get(error.errno)
    if text is None:
        return None
    return SeqvprError(text.format(path=_path_text(error.filename), other=_path_text(error.filename2)))


def _path_text(name: object) -> str:
    """A path an OSError names, as text; a placeholder where the system named none (a write to an open file)."""
    if isinstance(name, (str, bytes, os.PathLike)):
        return os.fsdecode(name)
    return "(a path the system did not name)"
