"""Nothing seqvpr reads is ever unpickled, checked on the source: every call that could unpickle a file (numpy's
load, torch's load, pickle and its kin) is found by its resolved name, and allowed only in its safe form."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "src" / "seqvpr"
#: the one module that may call numpy's loader (with allow_pickle=False written out) and scipy's MATLAB reader
ARRAY_HOME = "seqvpr/arrays.py"
#: calls that unpickle whatever the file holds, allowed nowhere
NEVER = ("pickle.load", "pickle.loads", "pickle.Unpickler", "_pickle.load", "_pickle.loads", "_pickle.Unpickler",
         "joblib.load", "dill.load", "dill.loads", "cloudpickle.load", "cloudpickle.loads", "shelve.open",
         "marshal.load", "marshal.loads", "pandas.read_pickle", "numpy.lib.format.read_array",
         "torch.serialization._load", "torch.jit._load_for_lite_interpreter")
#: calls allowed only in ARRAY_HOME
ARRAY_ONLY = ("numpy.load", "numpy.fromfile", "scipy.io.loadmat", "scipy.io.matlab.loadmat")
TORCH_LOAD = ("torch.load", "torch.serialization.load")
#: loaders that fall back to full unpickling inside torch: allowed only under ``with _weights_only_loads()``
FORCED = ("torch.export.load",)


def aliases(tree: ast.AST) -> dict[str, str]:
    """The full dotted name each imported name stands for (``np`` -> ``numpy``, ``loads`` -> ``pickle.loads``)."""
    names: dict[str, str] = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                names[alias.asname or alias.name.split(".")[0]] = alias.name if alias.asname else alias.name.split(".")[0]
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            for alias in node.names:
                names[alias.asname or alias.name] = f"{node.module}.{alias.name}"
    return names


def resolved(func: ast.expr, names: dict[str, str]) -> str | None:
    """The full dotted name a called expression stands for, or None when it is not a plain name path."""
    parts: list[str] = []
    while isinstance(func, ast.Attribute):
        parts.append(func.attr)
        func = func.value
    if not isinstance(func, ast.Name):
        return None
    parts.append(names.get(func.id, func.id))
    return ".".join(reversed(parts))


def literal(call: ast.Call, keyword: str, value: object) -> bool:
    """The call passes ``keyword=value`` written out as a constant."""
    return any(k.arg == keyword and isinstance(k.value, ast.Constant) and k.value.value is value
               for k in call.keywords)


def unpickling_calls(source: str, module: str) -> list[str]:
    """``module:line name`` for every call in ``source`` that could unpickle a file."""
    tree = ast.parse(source)
    names = aliases(tree)
    forced = {id(n) for node in ast.walk(tree) if isinstance(node, ast.With)
              and any("_weights_only_loads" in ast.unparse(item.context_expr) for item in node.items)
              for child in node.body for n in ast.walk(child)}
    found = []
    for node in ast.walk(tree):
        name = resolved(node.func, names) if isinstance(node, ast.Call) else None
        if name is None:
            continue
        if name in NEVER \
                or (name in ARRAY_ONLY and module != ARRAY_HOME) \
                or (name == "numpy.load" and not literal(node, "allow_pickle", False)) \
                or (name in TORCH_LOAD and not literal(node, "weights_only", True)) \
                or (name in FORCED and id(node) not in forced):
            found.append(f"{module}:{node.lineno} {name}")
    return found


def test_nothing_in_the_package_can_unpickle_a_file():
    found = []
    for path in sorted(PACKAGE.rglob("*.py")):
        found += unpickling_calls(path.read_text(), path.relative_to(PACKAGE.parent).as_posix())
    assert found == []


def test_the_scanner_sees_the_package_loading_arrays_and_checkpoints():
    """It finds what it must judge: numpy's loader in the array home, torch's in the checkpoint readers."""
    tree = ast.parse((PACKAGE / "arrays.py").read_text())
    calls = {resolved(n.func, aliases(tree)) for n in ast.walk(tree) if isinstance(n, ast.Call)}
    assert {"numpy.load", "scipy.io.loadmat"} <= calls
    published = (PACKAGE / "models" / "published.py").read_text()
    assert unpickling_calls(published.replace("weights_only=True", "weights_only=False"), "m.py")


@pytest.mark.parametrize("source,module", [
    ("import numpy as np\nnp.load(x, allow_pickle=True)\n", ARRAY_HOME),
    ("import numpy as np\nnp.load(x, allow_pickle=True)\n", "seqvpr/data/x.py"),
    ("import numpy as np\nnp.load(x, allow_pickle=False)\n", "seqvpr/data/x.py"),  # outside the home
    ("import numpy\nnumpy.load(x, allow_pickle=flag)\n", ARRAY_HOME),  # not written out
    ("import numpy as np\nnp.load(x)\n", ARRAY_HOME),
    ("from numpy import load\nload(x, allow_pickle=True)\n", ARRAY_HOME),
    ("import torch\ntorch.load(p)\n", "seqvpr/models/x.py"),
    ("import torch\ntorch.load(p, weights_only=False)\n", "seqvpr/models/x.py"),
    ("import pickle\npickle.loads(b)\n", "seqvpr/x.py"),
    ("from pickle import loads as l\nl(b)\n", "seqvpr/x.py"),
    ("import pickle\nclass U(pickle.Unpickler): pass\nU(f)\npickle.Unpickler(f).load()\n", "seqvpr/x.py"),
    ("import joblib\njoblib.load(p)\n", "seqvpr/x.py"),
    ("import torch\ntorch.export.load(p)\n", "seqvpr/features/x.py"),  # torch retries it with full unpickling
    ("import scipy.io\nscipy.io.loadmat(p)\n", "seqvpr/data/x.py"),
])
def test_the_scanner_fails_an_unpickling_call(source, module):
    assert len(unpickling_calls(source, module)) == 1


@pytest.mark.parametrize("source,module", [
    ("import numpy as np\nnp.load(x, allow_pickle=False)\n", ARRAY_HOME),
    ("import numpy as np\nnp.load(x, mmap_mode='r', allow_pickle=False)\n", ARRAY_HOME),
    ("import torch\ntorch.load(p, map_location='cpu', weights_only=True)\n", "seqvpr/models/x.py"),
    ("import pickle\ntry:\n    f()\nexcept pickle.UnpicklingError:\n    pass\n", "seqvpr/x.py"),
    ("import numpy as np\nnp.loadtxt(p)\n", "seqvpr/data/x.py"),
    ("import torch\nwith a() as b, _weights_only_loads():\n    torch.export.load(p)\n", "seqvpr/features/x.py"),
])
def test_the_scanner_passes_a_safe_call(source, module):
    assert unpickling_calls(source, module) == []
