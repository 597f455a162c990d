"""torch.distributed under torchrun's environment: the world read from it, and a gather that reaches rank 0 in rank
order or fails every rank with the failing rank's error (two gloo processes on this machine)."""

from __future__ import annotations

import json
import socket
from pathlib import Path

import pytest

from seqvpr import distributed
from seqvpr.errors import SeqvprError
from tests.helpers import raises_one_line, spawn_ranks


def test_the_world_is_torchruns_environment_or_one_process(monkeypatch):
    for name in ("RANK", "WORLD_SIZE", "LOCAL_RANK"):
        monkeypatch.delenv(name, raising=False)
    assert distributed.from_environment() == distributed.Ranks(0, 1, 0)
    monkeypatch.setenv("RANK", "1")
    monkeypatch.setenv("WORLD_SIZE", "2")
    monkeypatch.setenv("LOCAL_RANK", "1")
    assert distributed.from_environment() == distributed.Ranks(1, 2, 1)
    monkeypatch.setenv("RANK", "2")
    raises_one_line("rank 2 is not one of WORLD_SIZE=2 ranks", distributed.from_environment)
    monkeypatch.setenv("RANK", "one")
    raises_one_line("must be whole numbers", distributed.from_environment)
    assert distributed.gather_to_root(lambda: 7, distributed.Ranks()) == [7]  # alone: no process group


def _rank(rank: int, port: int, fail_rank: int, out: str) -> None:
    import os

    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), RANK=str(rank), WORLD_SIZE="2",
                      LOCAL_RANK=str(rank))

    def work() -> dict:
        if rank == fail_rank:
            raise SeqvprError(f"shard {rank} is damaged")
        return {"rank": rank}

    with distributed.process_group("cpu") as world:
        try:
            outcome = {"gathered": distributed.gather_to_root(work, world)}
        except SeqvprError as error:
            outcome = {"error": str(error)}
    Path(out, f"rank{rank}.json").write_text(json.dumps(outcome))


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


@pytest.mark.slow
@pytest.mark.parametrize("fail_rank", [-1, 1])
def test_gather_reaches_rank_0_in_order_or_fails_every_rank_with_the_failing_ranks_error(tmp_path, fail_rank):
    spawn_ranks(_rank, (free_port(), fail_rank, str(tmp_path)))
    outcomes = [json.loads((tmp_path / f"rank{rank}.json").read_text()) for rank in range(2)]
    if fail_rank < 0:
        assert outcomes == [{"gathered": [{"rank": 0}, {"rank": 1}]}, {"gathered": None}]
    else:
        assert outcomes[0] == outcomes[1] == {"error": "rank 1 of 2 failed: shard 1 is damaged"}


def test_match_under_torchrun_needs_a_sharded_map(monkeypatch, capsys, tmp_path):
    from tests.helpers import run_cli, write_route_files

    write_route_files(tmp_path, n_frames=60, dim=8, seed=0)
    monkeypatch.setenv("RANK", "0")
    monkeypatch.setenv("WORLD_SIZE", "2")
    code, _, err = run_cli(monkeypatch, capsys, "match", "-r", tmp_path / "ref.npz", "-q", tmp_path / "qry.npz",
                           "--radius", "10m", "--out", tmp_path / "out")
    assert code == 2 and "shares the work of a sharded map" in err and not (tmp_path / "out").exists()
