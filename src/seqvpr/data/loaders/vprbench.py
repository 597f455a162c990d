"""VPR-Bench's ``ground_truth_new.npy``: an object array of rows ``[query index, [reference indices]]``, which numpy
stores as a pickle. It is read here WITHOUT unpickling: the pickle's opcodes are walked as data
(``pickletools.genops`` decodes them and runs nothing, imports nothing), and only what such a file holds is understood
(whole numbers, lists, tuples, numpy's array and number wrappers); any other opcode or global is one line."""

from __future__ import annotations

import pickletools
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from seqvpr.arrays import check_regular_file, read_npy_header
from seqvpr.errors import SeqvprError

_MULTIARRAY = ("numpy.core.multiarray", "numpy._core.multiarray")
ALLOWED_GLOBALS = {*(f"{m} {n}" for m in _MULTIARRAY for n in ("_reconstruct", "scalar")), "numpy ndarray",
                   "numpy dtype"}
CONVERT_HINT = "save it as a dense boolean [reference, query] .npy/.npz or a GT .mat"
_PUSH = {"NONE": None, "NEWTRUE": True, "NEWFALSE": False, "EMPTY_LIST": list, "EMPTY_TUPLE": tuple,
         "EMPTY_DICT": dict}
_VALUES = {"BININT", "BININT1", "BININT2", "INT", "LONG", "LONG1", "LONG4", "BINFLOAT", "FLOAT", "SHORT_BINSTRING",
           "BINSTRING", "STRING", "BINUNICODE", "SHORT_BINUNICODE", "BINUNICODE8", "UNICODE", "BINBYTES",
           "SHORT_BINBYTES", "BINBYTES8"}
_MARK = object()


@dataclass
class _Call:
    """``func(*args)``, then ``__setstate__(state)``, as written in the pickle: recorded, never called (BUILD sets
    ``state`` in place, as unpickling would, so a memoised reference sees it)."""

    func: str
    args: tuple
    state: object = None


def read_object_rows(path: str | Path) -> list[tuple[int, np.ndarray]]:
    """The ``[query index, [reference indices]]`` rows of a VPR-Bench object-array ``.npy``, read without
    unpickling; a file that is not that is one line saying how to convert it."""
    path = check_regular_file(path, "a ground-truth file")
    with open(path, "rb") as handle:
        shape, dtype = read_npy_header(handle, str(path))
        payload = handle.read()
    if not dtype.hasobject or len(shape) != 2 or shape[1] != 2:
        raise SeqvprError(f"{path}: expected VPR-Bench rows [query_index, [reference indices]], got {dtype} {shape}")
    data = _array_items(_walk(payload, path), path)
    if len(data) != shape[0] * 2:
        raise SeqvprError(f"{path}: holds {len(data)} items for a {shape} array ({CONVERT_HINT})")
    try:
        return [(_whole(data[2 * i], path, i), np.atleast_1d(_integers(data[2 * i + 1], path, i)))
                for i in range(shape[0])]
    except (ValueError, TypeError, IndexError) as error:
        raise SeqvprError(f"{path}: a damaged object array ({error}; {CONVERT_HINT})") from None


def _walk(payload: bytes, path: Path) -> object:
    """The pickle's value as plain data plus ``_Call`` records; nothing is imported or called."""
    stack: list = []
    memo: dict = {}
    try:
        for op, arg, _ in pickletools.genops(payload):
            name = op.name
            if name == "STOP":
                return stack.pop()
            _step(name, arg, stack, memo, path)
    except SeqvprError:
        raise
    except (ValueError, IndexError, KeyError, TypeError, AttributeError) as error:
        raise SeqvprError(f"{path}: a damaged object array ({type(error).__name__}; {CONVERT_HINT})") from None
    raise SeqvprError(f"{path}: a truncated object array ({CONVERT_HINT})")


def _step(name: str, arg: object, stack: list, memo: dict, path: Path) -> None:
    """One opcode applied to the symbolic stack; one outside the known set is refused."""
    if name in ("PROTO", "FRAME"):
        return
    if name in _PUSH:
        value = _PUSH[name]
        stack.append(value() if callable(value) else value)
    elif name in _VALUES:
        stack.append(arg)
    elif name in ("GLOBAL", "STACK_GLOBAL"):
        stack.append(_global(arg if name == "GLOBAL" else f"{stack.pop(-2)} {stack.pop()}", path))
    elif name in ("BINPUT", "LONG_BINPUT", "PUT", "MEMOIZE"):
        memo[len(memo) if name == "MEMOIZE" else arg] = stack[-1]
    elif name in ("BINGET", "LONG_BINGET", "GET"):
        stack.append(memo[arg])
    elif name == "MARK":
        stack.append(_MARK)
    elif name in ("TUPLE", "LIST", "APPENDS"):
        items = _pop_mark(stack)
        if name == "APPENDS":
            _list(stack[-1]).extend(items)
        else:
            stack.append(tuple(items) if name == "TUPLE" else items)
    elif name in ("TUPLE1", "TUPLE2", "TUPLE3"):
        count = int(name[-1])
        items = tuple(stack[-count:])
        del stack[-count:]
        stack.append(items)
    elif name == "APPEND":
        value = stack.pop()
        _list(stack[-1]).append(value)
    elif name in ("REDUCE", "BUILD"):
        second, first = stack.pop(), stack.pop()
        if name == "REDUCE":
            stack.append(_Call(first, second))
        else:
            _built(first).state = second
            stack.append(first)
    else:
        raise SeqvprError(f"{path}: its pickle uses {name}, beyond what a ground-truth array holds; seqvpr never "
                          f"unpickles a file ({CONVERT_HINT})")


def _global(name: str, path: Path) -> str:
    if name not in ALLOWED_GLOBALS:
        raise SeqvprError(f"{path}: its pickle names {name!r}, not part of a numpy array; seqvpr never unpickles a "
                          f"file ({CONVERT_HINT})")
    return name


def _pop_mark(stack: list) -> list:
    at = max(i for i, item in enumerate(stack) if item is _MARK)
    items = stack[at + 1:]
    del stack[at:]
    return items


def _built(value: object) -> _Call:
    if not isinstance(value, _Call) or value.state is not None:
        raise TypeError("BUILD of a non-object")
    return value


def _list(value: object) -> list:
    if not isinstance(value, list):
        raise TypeError("append to a non-list")
    return value


def _array_items(value: object, path: Path) -> list:
    """The items of a pickled object ndarray: ``_reconstruct(ndarray, ...)`` built with (version, shape, dtype,
    fortran, items)."""
    if isinstance(value, _Call) and value.func.endswith("_reconstruct") and isinstance(value.state, tuple) and value.state and isinstance(value.state[-1], list):
        return value.state[-1]
    raise SeqvprError(f"{path}: not a pickled numpy object array ({CONVERT_HINT})")


def _dtype(value: object) -> np.dtype | None:
    """The numeric dtype a pickled ``numpy.dtype('i8', ...)`` with its byte-order state names, else None."""
    if isinstance(value, _Call) and value.func == "numpy dtype" and isinstance(value.state, tuple) \
            and len(value.state) > 1 and value.args and str(value.args[0])[:1] in "biu":
        order = value.state[1] if value.state[1] in ("<", ">", "=") else "|"
        dtype = np.dtype(order + str(value.args[0]) if order != "|" else str(value.args[0]))
        return dtype if dtype.kind in "biu" else None
    return None


def _integers(value: object, path: Path, row: int) -> np.ndarray:
    """Whole numbers from a Python int or list, a numpy number or a numpy int array, as int64."""
    if isinstance(value, list):
        return np.array([_whole(v, path, row) for v in value], dtype=np.int64)
    if isinstance(value, _Call) and isinstance(value.state, tuple) and len(value.state) == 5 \
            and isinstance(value.state[4], bytes) and _dtype(value.state[2]) is not None:
        return np.frombuffer(value.state[4], dtype=_dtype(value.state[2])).astype(np.int64)
    return np.array([_whole(value, path, row)], dtype=np.int64)


def _whole(value: object, path: Path, row: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, _Call)):
        raise SeqvprError(f"{path}: row {row} is not [query_index, [reference indices]]")
    if isinstance(value, _Call):  # numpy.core.multiarray.scalar(dtype, bytes): a numpy whole number
        dtype = _dtype(value.args[0]) if len(value.args) == 2 and isinstance(value.args[1], bytes) else None
        if not value.func.endswith(" scalar") or dtype is None:
            raise SeqvprError(f"{path}: row {row} is not [query_index, [reference indices]]")
        return int(np.frombuffer(value.args[1], dtype=dtype)[0])
    return value
