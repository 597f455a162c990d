"""A torchrun rank never waits unboundedly: started alone it ends with one line after $SEQVPR_RANK_TIMEOUT
seconds, and SIGTERM ends a rank waiting for the others within seconds (real subprocesses, one rank of a world
of 2)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest

from seqvpr import distributed
from seqvpr.errors import SeqvprError
from tests.helpers import QuietCapsys, run_cli, write_route_files
from tests.test_distributed import free_port


@pytest.fixture(scope="module")
def sharded(tmp_path_factory):
    """A sharded map of two shards (what ``seqvpr map index`` shares among torchrun ranks)."""
    folder = write_route_files(tmp_path_factory.mktemp("ranks"), 60, 8, 1)
    monkeypatch = pytest.MonkeyPatch()
    for args in (("map", "build", folder / "ref.npz", "--out", folder / "map"),
                 ("map", "shard", folder / "map", "--shards", "2", "--out", folder / "sharded")):
        assert run_cli(monkeypatch, QuietCapsys(), *args)[0] == 0
    monkeypatch.undo()
    return folder / "sharded"



def _lone_rank(sharded, rank: int, timeout: str | None) -> subprocess.Popen:
    """``seqvpr map index SHARDED`` as rank ``rank`` of a world of 2 whose other rank never starts."""
    env = {**os.environ, "MASTER_ADDR": "127.0.0.1", "MASTER_PORT": str(free_port()), "RANK": str(rank),
           "WORLD_SIZE": "2", "LOCAL_RANK": str(rank), "PYTHONPATH": os.pathsep.join(sys.path)}
    env.pop("SEQVPR_RANK_TIMEOUT", None)
    if timeout is not None:
        env["SEQVPR_RANK_TIMEOUT"] = timeout
    return subprocess.Popen([sys.executable, "-m", "seqvpr.cli", "map", "index", str(sharded), "--index", "flat"],
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _finish(process: subprocess.Popen, seconds: float) -> str:
    """The process's stderr once it ends; killed (and the test failed) if it runs past ``seconds``."""
    try:
        return process.communicate(timeout=seconds)[1]
    except subprocess.TimeoutExpired:
        process.kill()
        process.communicate()
        raise AssertionError(f"still running {seconds:.0f} s later") from None


def _seqvpr_lines(err: str) -> list[str]:
    return [line for line in err.splitlines() if line.startswith("seqvpr:")]


@pytest.mark.slow
def test_a_lone_rank_ends_with_one_line_after_the_rank_timeout(sharded):
    started = time.monotonic()
    processes = [_lone_rank(sharded, rank, "2") for rank in (0, 1)]  # each alone in a world of its own port
    errors = [_finish(process, 90) for process in processes]
    assert time.monotonic() - started < 60, "waited far past SEQVPR_RANK_TIMEOUT=2"
    for process, err in zip(processes, errors):
        lines = _seqvpr_lines(err)
        assert process.returncode == 2, err
        assert len(lines) == 1 and "did not join within 2 s" in lines[0] and "SEQVPR_RANK_TIMEOUT" in lines[0], err


@pytest.mark.slow
def test_sigterm_ends_a_rank_waiting_for_the_others_within_seconds(sharded):
    processes = [_lone_rank(sharded, rank, None) for rank in (0, 1)]  # the default timeout: only SIGTERM ends them
    time.sleep(6)  # started and waiting at the rendezvous
    for process in processes:
        assert process.poll() is None, process.communicate()[1]
    sent = time.monotonic()
    for process in processes:
        process.send_signal(signal.SIGTERM)
    errors = [_finish(process, 30) for process in processes]
    assert time.monotonic() - sent < 10
    for process, err in zip(processes, errors):
        assert process.returncode == 143, err
        lines = _seqvpr_lines(err)
        assert len(lines) == 1 and lines[0].startswith("seqvpr: terminated (SIGTERM)"), err


@pytest.mark.parametrize("value", ["0", "-3", "nan", "inf", "soon", "1e9"])
def test_a_bad_rank_timeout_is_one_line(monkeypatch, value):
    monkeypatch.setenv("SEQVPR_RANK_TIMEOUT", value)
    with pytest.raises(SeqvprError, match="SEQVPR_RANK_TIMEOUT"):
        distributed.rank_timeout()


def test_the_rank_timeout_is_the_variable_or_five_minutes(monkeypatch):
    monkeypatch.delenv("SEQVPR_RANK_TIMEOUT", raising=False)
    assert distributed.rank_timeout() == 300
    monkeypatch.setenv("SEQVPR_RANK_TIMEOUT", "12.5")
    assert distributed.rank_timeout() == 12.5
