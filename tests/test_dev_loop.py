"""The fast development loop: hypothesis's profile follows the environment (few examples by default, each test's
full count under ``CI=true``), and a test that starts Python processes is marked slow, so ``-m "not slow"`` leaves
it out."""

import ast
from pathlib import Path

import pytest
from hypothesis import settings

from tests.helpers import DEV_EXAMPLES, examples, hypothesis_profile

TESTS = Path(__file__).resolve().parent


@pytest.mark.parametrize("env, profile", [({}, "dev"), ({"CI": "true"}, "ci"), ({"CI": "TRUE"}, "ci"),
                                          ({"CI": "false"}, "dev"), ({"HYPOTHESIS_PROFILE": "ci"}, "ci"),
                                          ({"HYPOTHESIS_PROFILE": "dev"}, "dev")])
def test_the_profile_and_the_example_counts_follow_the_environment(monkeypatch, env, profile):
    for variable in ("CI", "HYPOTHESIS_PROFILE"):
        monkeypatch.delenv(variable, raising=False)
    for variable, value in env.items():
        monkeypatch.setenv(variable, value)
    assert hypothesis_profile() == profile
    assert examples(80) == (80 if profile == "ci" else DEV_EXAMPLES)
    assert examples(DEV_EXAMPLES - 1) == DEV_EXAMPLES - 1  # never more than the test asks for


def test_this_run_loaded_the_profile_its_environment_names():
    expected = settings.get_profile(hypothesis_profile())
    assert settings.default.max_examples == expected.max_examples
    assert settings.default.deadline is None


def _starts_processes(function: ast.FunctionDef) -> bool:
    """Whether a test's own body spawns ranks, launches torchrun, or runs ``sys.executable`` in a subprocess."""
    python = "sys.executable" in ast.unparse(function)
    for node in ast.walk(function):
        if not isinstance(node, ast.Call):
            continue
        name = node.func.id if isinstance(node.func, ast.Name) else getattr(node.func, "attr", "")
        if name in ("spawn_ranks", "torchrun") or (python and name in ("run", "Popen")):
            return True
    return False


def _marked_slow(decorators: list[ast.expr]) -> bool:
    return any("mark.slow" in ast.unparse(decorator) for decorator in decorators)


def test_every_test_that_starts_python_processes_is_marked_slow():
    unmarked = []
    for path in sorted(TESTS.rglob("test_*.py")):
        tree = ast.parse(path.read_text())
        if any(isinstance(node, ast.Assign) and "pytestmark" in ast.unparse(node) and "slow" in ast.unparse(node)
               for node in tree.body):
            continue
        unmarked += [f"{path.relative_to(TESTS)}::{node.name}" for node in tree.body
                     if isinstance(node, ast.FunctionDef) and node.name.startswith("test_")
                     and _starts_processes(node) and not _marked_slow(node.decorator_list)]
    assert not unmarked, unmarked


def test_the_slow_check_sees_a_spawning_test_and_its_mark():
    tree = ast.parse("@pytest.mark.slow\ndef test_a():\n    subprocess.run([sys.executable, '-c', ''])\n"
                     "def test_b():\n    spawn_ranks(f, ())\ndef test_c():\n    subprocess.run(['true'])\n")
    a, b, c = tree.body
    assert _starts_processes(a) and _marked_slow(a.decorator_list)
    assert _starts_processes(b) and not _marked_slow(b.decorator_list)
    assert not _starts_processes(c)
