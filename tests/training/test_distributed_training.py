"""Data-parallel training under torchrun's environment (two gloo processes on this machine): with the same global
batch and seed, two ranks give the single process's weights and history, resume included, and only rank 0 writes.

Tolerance: the ranks' gradients are summed in another order than one process sums them (each rank's part, then
the all-reduce), so weights agree to float32 rounding, not bit for bit; after a few epochs of SGD that is about
1e-6 relative. Mining and every random draw are rank 0's, shared, so the triplets are the same exactly."""

from __future__ import annotations

import socket
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch.multiprocessing as mp

from seqvpr.models import files as ckpt
from seqvpr.training.state import STATE_JSON
from tests.training.test_seqmatchnet_training import SMALL as SMN, small_data
from tests.training.test_seqnet_training import SMALL as SEQNET, route_data


def train(kind: str, out: Path, epochs: int, resume: bool = False):
    if kind == "seqmatchnet":
        from seqvpr.models.seqmatchnet import TransformConfig
        from seqvpr.training.seqmatchnet import train_seqmatchnet

        return train_seqmatchnet(small_data(), TransformConfig(16), replace(SMN, epochs=epochs), out, resume=resume)
    from seqvpr.training.seqnet import train_seqnet

    return train_seqnet(route_data(1), replace(SEQNET, epochs=epochs), out, resume=resume)


def _rank(rank: int, port: int, kind: str, out: str, epochs: list[tuple[int, bool]]) -> None:
    import os

    import torch

    torch.set_num_threads(1)
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), RANK=str(rank), WORLD_SIZE="2",
                      LOCAL_RANK=str(rank))
    for count, resume in epochs:
        train(kind, Path(out), count, resume)


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def state_weights(folder: Path) -> dict:
    state = ckpt.read_json(folder / STATE_JSON)
    return ckpt.read_tensors(folder / state["state_dir"] / ckpt.MODEL_FILE)


@pytest.mark.parametrize("kind", ["seqmatchnet", "seqnet"])
def test_two_ranks_train_the_single_process_model_and_resume(tmp_path, kind):
    import torch

    torch.set_num_threads(1)
    alone = train(kind, tmp_path / "alone", 3)
    mp.spawn(_rank, args=(free_port(), kind, str(tmp_path / "two"), [(3, False)]), nprocs=2, join=True)
    mp.spawn(_rank, args=(free_port(), kind, str(tmp_path / "resumed"), [(1, False), (3, True)]), nprocs=2, join=True)
    expected = state_weights(tmp_path / "alone")
    for run in ("two", "resumed"):
        got = state_weights(tmp_path / run)
        assert got.keys() == expected.keys()
        for key in expected:
            np.testing.assert_allclose(got[key].numpy(), expected[key].numpy(), rtol=1e-5, atol=1e-6, err_msg=key)
        history = ckpt.read_json(tmp_path / run / STATE_JSON)["history"]
        assert [h["triplets"] for h in history] == [r.triplets for r in alone.history]  # the same mined triplets
        np.testing.assert_allclose([h["loss"] for h in history], [r.loss for r in alone.history], rtol=1e-5)
        assert not list((tmp_path / run).glob("*.part"))
