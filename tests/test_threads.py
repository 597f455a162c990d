"""The one thread policy: where the count comes from, and that torch, numba and faiss keep it through the imports,
numba's first launch and the localiser's open (each checked in a fresh interpreter, whose pools start unset)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from seqvpr import threads
from tests.helpers import raises_one_line, run_cli


def fresh_python(code: str, env: dict[str, str] | None = None) -> str:
    """Run ``code`` in a new interpreter with no thread variables but ``env``; its last line of stdout."""
    clean = {k: v for k, v in os.environ.items()
             if k not in ("SEQVPR_THREADS", "NUMBA_NUM_THREADS", *threads.POOL_VARIABLES)}
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                          env={**clean, **(env or {})})
    assert done.returncode == 0, done.stderr
    return done.stdout.strip().splitlines()[-1]


@pytest.fixture
def no_thread_variables(monkeypatch):
    for variable in ("SEQVPR_THREADS", "OMP_NUM_THREADS"):
        monkeypatch.delenv(variable, raising=False)
    monkeypatch.setattr(threads, "_exported", None)  # as in a process that has not applied a policy yet


def test_the_count_comes_from_the_option_then_the_variables_then_the_free_cores(monkeypatch, no_thread_variables):
    monkeypatch.setattr(threads, "usable_cores", lambda: 8)
    monkeypatch.setattr(threads, "busy_cores", lambda: 5.0)
    assert threads.choose_policy() == threads.ThreadPolicy(3, "free cores", 8, 5.0)
    monkeypatch.setenv("OMP_NUM_THREADS", "2")
    assert threads.choose_policy().threads == 2 and threads.choose_policy().source == "OMP_NUM_THREADS"
    monkeypatch.setenv("SEQVPR_THREADS", "4")
    assert (threads.choose_policy().threads, threads.choose_policy().source) == (4, "SEQVPR_THREADS")
    assert (threads.choose_policy(6).threads, threads.choose_policy(6).source) == (6, "--threads")


@pytest.mark.parametrize("cores, busy, expected", [(2, 0.0, 2), (2, 1.0, 1), (2, 2.0, 1), (2, 7.0, 1), (16, 3.0, 13),
                                                   (4, None, 4), (4, 1.4, 3), (4, 1.6, 2)])
def test_free_cores_are_the_usable_cores_no_other_process_runs_on_at_least_one(cores, busy, expected):
    assert threads.free_cores(cores, busy) == expected


def test_busy_cores_is_the_median_of_the_kernels_runnable_count_less_this_process(tmp_path):
    stat = tmp_path / "stat"
    stat.write_text("cpu  1 2 3\nprocs_running 3\nprocs_blocked 0\n")
    assert threads.busy_cores(samples=3, interval=0.0, stat=stat) == 2.0
    assert threads.busy_cores(samples=1, stat=tmp_path / "missing") is None
    for number, state in ((1, "R"), (2, "R"), (3, "S")):  # this process's own threads, two running (a BLAS pool)
        (tmp_path / "task" / str(number)).mkdir(parents=True)
        (tmp_path / "task" / str(number) / "stat").write_text(f"{number} (py thon) {state} 1 2 3\n")
    assert threads.busy_cores(samples=1, stat=stat, own=tmp_path / "task") == 1.0
    stat.write_text("cpu  1 2 3\n")
    assert threads.busy_cores(samples=1, stat=stat) is None


@pytest.mark.slow
def test_the_running_count_rises_with_busy_processes():
    spinners = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(2)]
    try:
        import time

        time.sleep(0.5)
        loaded = threads.busy_cores()
    finally:
        for process in spinners:
            process.kill()
            process.wait()
    assert loaded is not None and loaded >= 1.0


@pytest.mark.parametrize("value", ["0", "-1", "two", "1.5", "10000"])
def test_a_bad_thread_count_is_one_line_naming_where_it_came_from(monkeypatch, value):
    monkeypatch.setenv("SEQVPR_THREADS", value)
    raises_one_line("SEQVPR_THREADS", threads.choose_policy)
    raises_one_line("--threads", threads.choose_policy, int(value) if value.lstrip("-").isdigit() else 0)


def test_the_cli_refuses_a_bad_variable_in_one_line(monkeypatch, capsys):
    monkeypatch.setenv("SEQVPR_THREADS", "many")
    code, _, err = run_cli(monkeypatch, capsys, "doctor")
    assert code == 2 and err.count("\n") == 1 and "SEQVPR_THREADS" in err


POOLS_AFTER_LOCALIZING = """
import json, sys
import numpy as np
import faiss, torch  # imported first, at their own defaults
torch.get_num_threads()  # torch asked for its count first: then numba's launch resets it
{apply}
from seqvpr.localization import Localizer
from seqvpr.maps import build_map
from seqvpr.threads import pool_counts
rows = np.random.default_rng(0).standard_normal((300, 16)).astype(np.float32)
np.save({npy!r}, rows)
build_map([{npy!r}], {folder!r})
opened = Localizer.open({folder!r})
after_open = pool_counts()
for row in rows[:12]:
    opened.update(row)
print(json.dumps({{"open": after_open, "update": pool_counts()}}))
"""


@pytest.mark.slow
@pytest.mark.parametrize("apply, env", [("", {"SEQVPR_THREADS": "1"}),
                                        ("from seqvpr.threads import use_threads; use_threads(1)", {}),
                                        ("", {"OMP_NUM_THREADS": "1"})])
def test_the_policy_survives_the_numba_matchers_build_and_the_localizers_open(tmp_path, apply, env):
    code = POOLS_AFTER_LOCALIZING.format(apply=apply, npy=str(tmp_path / "rows.npy"), folder=str(tmp_path / "map"))
    counts = json.loads(fresh_python(code, env))
    assert counts["open"] == {"torch": 1, "numba": 1, "faiss": 1}
    assert counts["update"] == {"torch": 1, "numba": 1, "faiss": 1}


@pytest.mark.slow
def test_without_the_policy_numbas_launch_resets_torch_which_is_why_it_exists():
    code = """
import numpy as np, torch
torch.get_num_threads()  # torch asked for its count first: then numba's launch resets it
torch.set_num_threads(1)
from seqvpr.sequences._fused import squared_norms
squared_norms(np.ones((128, 2), np.float32))  # enough rows for the parallel kernel
print(torch.get_num_threads())
"""
    if os.cpu_count() == 1:
        pytest.skip("one core: every count is 1")
    assert fresh_python(code) != "1"


@pytest.mark.slow
def test_a_policy_applied_after_numba_started_still_holds_every_pool():
    code = """
import json
import numpy as np
from seqvpr.sequences._fused import squared_norms
squared_norms(np.ones((4, 2), np.float32))  # numba's pool started at its default
import faiss, torch
torch.get_num_threads()
from seqvpr.threads import pool_counts, use_threads
use_threads(1)
squared_norms(np.ones((64, 8), np.float32))
print(json.dumps(pool_counts()))
"""
    assert json.loads(fresh_python(code)) == {"torch": 1, "numba": 1, "faiss": 1}


def test_doctor_prints_the_policy_in_force(monkeypatch, capsys):
    code, out, _ = run_cli(monkeypatch, capsys, "doctor", "--threads", "1", "--json")
    report = json.loads(out)
    assert code == 0 and report["compute"]["thread policy"].startswith("1 thread (from --threads")
    assert report["devices"]["torch threads"] == 1 and report["compute"]["numba threads"] == 1
    assert report["compute"]["faiss threads"] == 1
    threads.use_threads(None)  # the rest of the session at the default again


def test_every_command_takes_threads(monkeypatch, capsys):
    from seqvpr.cli import COMMANDS, cli

    import click

    ctx = click.Context(cli)
    for name in COMMANDS:
        command = cli.get_command(ctx, name)
        leaves = list(command.commands.values()) if isinstance(command, click.Group) else [command]
        for leaf in leaves:
            assert "--threads" in [o for p in leaf.params for o in getattr(p, "opts", [])], f"{name} {leaf.name}"


def test_the_count_this_process_exported_is_not_read_back_as_a_choice(monkeypatch, no_thread_variables):
    monkeypatch.setattr(threads, "_applied", threads.current_policy())  # restored after: the session's policy
    for variable in (*threads.POOL_VARIABLES, "NUMBA_NUM_THREADS"):
        monkeypatch.setenv(variable, os.environ.get(variable, "1"))
    monkeypatch.setattr(threads, "busy_cores", lambda: 0.0)
    monkeypatch.setattr(threads, "usable_cores", lambda: 4)
    threads.apply_policy(threads.ThreadPolicy(1, "--threads", 4))
    assert os.environ["OMP_NUM_THREADS"] == "1"  # what child processes inherit
    assert (threads.choose_policy().threads, threads.choose_policy().source) == (4, "free cores")
