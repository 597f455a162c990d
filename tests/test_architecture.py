"""The shape of the package: layered imports without cycles, what the command line imports, small functions and
modules. These are the foundation's rules (docs/concepts/architecture.md), checked on the source itself."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src"
PACKAGE = SRC / "seqvpr"

#: lower layers never import higher ones (docs/concepts/architecture.md: cli -> ros2 -> localization ->
#: experiments/maps -> methods -> training -> matchers -> models -> evaluation/features -> data/sequences/synthetic ->
#: errors/io)
LAYERS = {
    "seqvpr": 0, "seqvpr.errors": 0, "seqvpr.io": 0, "seqvpr.threads": 0, "seqvpr.progress": 0, "seqvpr.cache": 0,
    "seqvpr.identity": 0, "seqvpr.arrays": 0,
    "seqvpr.data": 1, "seqvpr.sequences": 1, "seqvpr.results": 1,
    "seqvpr.features": 2, "seqvpr.evaluation": 2, "seqvpr.synthetic": 2,
    "seqvpr.models": 3,
    "seqvpr.matchers": 4,
    "seqvpr.training": 5,
    "seqvpr.methods": 6,
    "seqvpr.maps": 7, "seqvpr.api": 7,
    "seqvpr.localization": 8,
    "seqvpr.experiments": 9,  # cli -> experiments -> localization (ARCHITECTURE.md)
    "seqvpr.viewer": 9,  # reads every output seqvpr writes: runs, localisations, maps
    "seqvpr.ros2": 9,
    "seqvpr.cli": 10,
}
HEAVY = ("torch", "numba", "faiss", "matplotlib", "scipy")


def module_name(path: Path) -> str:
    parts = path.relative_to(SRC).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def layer(module: str) -> int:
    """The layer of a module: that of its longest listed prefix."""
    prefix = max((p for p in LAYERS if module == p or module.startswith(p + ".")), key=len)
    return LAYERS[prefix]


def imports_of(path: Path) -> set[str]:
    """The seqvpr modules a file imports, at module level, inside functions or for type checking only (a type-only
    import is a tie between two modules as real as any other)."""
    tree = ast.parse(path.read_text())
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("seqvpr"):
            found.add(node.module)
            found.update(f"{node.module}.{a.name}" for a in node.names)
        elif isinstance(node, ast.Import):
            found.update(a.name for a in node.names if a.name.startswith("seqvpr"))
    modules = {module_name(p) for p in PACKAGE.rglob("*.py")}
    return {m for m in found if m in modules} - {module_name(path)}


def import_graph() -> dict[str, set[str]]:
    return {module_name(p): imports_of(p) for p in PACKAGE.rglob("*.py")}


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        for other in graph.get(node, ()):
            if other not in index:
                visit(other)
                low[node] = min(low[node], low[other])
            elif other in stack:
                low[node] = min(low[node], index[other])
        if low[node] == index[node]:
            component = []
            while True:
                top = stack.pop()
                component.append(top)
                if top == node:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return found


def test_imports_point_down_the_layers_and_form_no_cycle():
    graph = import_graph()
    upward = [f"{a} -> {b}" for a, targets in graph.items() for b in targets
              if layer(b) > layer(a) and not (a == "seqvpr" or b.startswith(a + "."))]
    assert upward == []
    assert cycles(graph) == []
    assert not any(b.startswith("seqvpr.training") for a, t in graph.items() if a.startswith("seqvpr.models") for b in t)


def test_cli_command_modules_share_only_options_progress_and_help():
    graph = import_graph()
    commands = ("seqvpr.cli.match", "seqvpr.cli.extract", "seqvpr.cli.export", "seqvpr.cli.train",
                "seqvpr.cli.experiments", "seqvpr.cli.published", "seqvpr.cli.maps")
    for module in commands:
        shared = {"seqvpr.cli.options", "seqvpr.cli.progress", "seqvpr.cli.help"}
        assert {m for m in graph[module] if m.startswith("seqvpr.cli")} <= shared


def test_the_checker_sees_an_upward_import_and_a_cycle():
    assert layer("seqvpr.models.jist") < layer("seqvpr.training.jist") < layer("seqvpr.cli.train")
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def python(code: str, cwd: Path | None = None) -> str:
    """Run ``code`` in a fresh interpreter (nothing imported yet); its stdout."""
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=cwd, timeout=300)
    assert done.returncode == 0, done.stderr
    return done.stdout.strip()


LOADED = "import sys; print(sorted({m.split('.')[0] for m in sys.modules} & set(%r)))" % (HEAVY,)


@pytest.mark.slow
@pytest.mark.parametrize("args", [["--help"], ["match", "--help"], ["train", "jist", "--help"],
                                  ["train", "seqmatchnet", "--help"], ["ablate", "seqmatchnet", "--help"],
                                  ["benchmark", "--help"], ["demo", "--help"], ["extract", "--help"],
                                  ["eval", "--help"], ["match", "-r", "a", "-q", "b", "--k", "x"],
                                  ["match", "--method", "magic"],
                                  ["extract", "a", "--descriptor", "torchscript:missing.pt", "--out", "b.npz"]])
def test_help_and_option_errors_import_no_heavy_library(args):
    code = f"""
import sys
from seqvpr.cli import main
sys.argv = ["seqvpr", *{args!r}]
try:
    main()
except SystemExit:
    pass
{LOADED}
"""
    assert python(code).splitlines()[-1] == "[]"


@pytest.fixture(scope="module")
def model_folders(tmp_path_factory) -> dict[str, Path]:
    """One tiny model folder of each kind, plus descriptor and image traversals to match with them."""
    import numpy as np
    from PIL import Image

    from seqvpr.data.sources import save_traversal_npz
    from seqvpr.data.traversal import Traversal
    from seqvpr.models.configs import JistConfig, TransformConfig
    from seqvpr.models.cosplace import build_cosplace, save_cosplace
    from seqvpr.models.jist import build_jist, save_jist
    from seqvpr.models.seqmatchnet import FrameTransform, save_seqmatchnet
    from seqvpr.models.seqnet import save_seqnet
    from seqvpr.sequences.descriptors import SeqNet

    root = tmp_path_factory.mktemp("models")
    rng = np.random.default_rng(0)
    for name in ("ref", "qry"):
        save_traversal_npz(root / f"{name}.npz", Traversal.from_descriptors(rng.normal(size=(30, 8)), name))
        folder = root / f"{name}_images"
        folder.mkdir()
        rows = ["name,easting,northing"]
        for i in range(12):
            Image.fromarray(rng.integers(0, 255, (24, 32, 3), dtype=np.uint8)).save(folder / f"{i:03d}.png")
            rows.append(f"{i:03d}.png,{2.0 * i},0")
        (folder / "positions.csv").write_text("\n".join(rows) + "\n")
    save_seqmatchnet(root / "seqmatchnet", FrameTransform(TransformConfig(8)), {"sequence": {"length": 3}})
    save_seqnet(root / "seqnet", SeqNet(8, 8, 2), {"sequence": {"length": 3}})
    config = JistConfig(backbone="efficientnet-lite0", out_dim=16, seq_length=3)
    save_jist(root / "jist", build_jist(config), config, {"image_size": [32, 24]})
    save_cosplace(root / "cosplace", build_cosplace("resnet18", 16), "resnet18", {"image_size": [32, 24]})
    return {"root": root, **{k: root / k for k in ("seqmatchnet", "seqnet", "jist", "cosplace")}}


@pytest.mark.slow
def test_loading_and_matching_with_any_model_imports_no_training_and_no_renderer(model_folders, tmp_path):
    """Every model kind loaded and matched with, in one fresh process (what one kind imports, the union holds)."""
    root, kinds = model_folders["root"], ("seqmatchnet", "seqnet", "jist", "cosplace")
    runs = []
    for kind in kinds:
        images = kind in ("jist", "cosplace")
        ref, qry = (root / "ref_images", root / "qry_images") if images else (root / "ref.npz", root / "qry.npz")
        runs.append((str(model_folders[kind]), ["match", "-r", str(ref), "-q", str(qry), "--radius",
                                                "3m" if images else "1f", "--model", str(model_folders[kind]),
                                                "--json", "--out", str(tmp_path / kind)]))
    code = f"""
import json, sys
from seqvpr.cli import main
from seqvpr.models.registry import load_trained_model
for folder, args in {runs!r}:
    model = load_trained_model(folder)
    sys.argv = ["seqvpr", *args]
    try:
        main()
    except SystemExit as exit_:
        assert not exit_.code, exit_.code
    print(model.kind, model.length)
print(sorted(m for m in sys.modules if m.startswith("seqvpr.training") or m == "seqvpr.synthetic.world"))
"""
    lines = python(code).splitlines()
    assert sum('"recall"' in line for line in lines) == 4
    assert [line for line in lines if line.split(" ")[0] in kinds] == [
        f"{kind} {1 if kind == 'cosplace' else 3}" for kind in kinds]
    assert lines[-1] == "[]"


def long_functions() -> list[str]:
    """Functions over 50 lines, numba kernels (``@njit``) excepted."""
    found = []
    for path in PACKAGE.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                jitted = any("njit" in ast.unparse(d) or "jit" == ast.unparse(d).split("(")[0] for d in node.decorator_list)
                if not jitted and node.end_lineno - node.lineno + 1 > 50:
                    found.append(f"{path.relative_to(SRC)}:{node.lineno} {node.name}")
    return found


def test_functions_and_modules_stay_small():
    assert long_functions() == []
    big = [str(p.relative_to(SRC)) for p in PACKAGE.rglob("*.py")
           if len(p.read_text().splitlines()) > 500 and p.name != "world.py"]  # the renderer is the exception
    assert big == []


def test_modules_of_one_name_are_one_concept_at_two_layers_and_say_so():
    """Two modules of one name (in different packages) must be the same concept at two layers, and each module's
    docstring names the other; any other pair is renamed."""
    by_name: dict[str, list[Path]] = {}
    for path in PACKAGE.rglob("*.py"):
        if path.name != "__init__.py":
            by_name.setdefault(path.name, []).append(path)
    unexplained = []
    for paths in by_name.values():
        for path in paths:
            docstring = ast.get_docstring(ast.parse(path.read_text())) or ""
            for other in paths:
                if other != path and f"``{module_name(other)}``" not in docstring:
                    unexplained.append(f"{module_name(path)} does not name {module_name(other)}")
    assert unexplained == []
