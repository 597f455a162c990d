"""The one exception type users see: a one-line message that names the file or field at fault."""

import csv
import pickle
import struct
import zipfile


class SeqvprError(ValueError):
    """Bad input or an impossible request; the CLI prints the message on one line and exits non-zero."""


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
