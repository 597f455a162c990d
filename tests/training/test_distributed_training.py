"""Data-parallel training under torchrun's environment (two gloo processes on this machine): with the same global
batch and seed, two ranks give the single process's weights and history, resume included, and only rank 0 writes.

Tolerance: the ranks' gradients are summed in another order than one process sums them (each rank's part, then
the all-reduce), so weights agree to float32 rounding, not bit for bit: about 1e-6 relative after a few SGD epochs,
and up to about 2e-5 absolute for JIST, whose Adam steps divide by small second moments early on. Mining and every
random draw are rank 0's, shared, so the triplets are the same exactly. A trainable BatchNorm normalises each
rank's part of a batch, not the whole batch (on CPU: gloo has no SyncBatchNorm): the JIST test uses a backbone
without one, and BENCHMARKS.md gives the difference one makes."""

from __future__ import annotations

import socket
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch.multiprocessing as mp
from torch import nn

from seqvpr.models import files as ckpt
from seqvpr.training.state import STATE_JSON
from tests.helpers import spawn_ranks
from tests.training.test_seqmatchnet_training import SMALL as SMN, small_data
from tests.training.test_seqnet_training import SMALL as SEQNET, route_data

pytestmark = pytest.mark.slow  # every test spawns two gloo ranks


def train(kind: str, out: Path, epochs: int, resume: bool = False):
    if kind == "seqmatchnet":
        from seqvpr.models.seqmatchnet import TransformConfig
        from seqvpr.training.seqmatchnet import train_seqmatchnet

        return train_seqmatchnet(small_data(), TransformConfig(16), replace(SMN, epochs=epochs), out, resume=resume)
    from seqvpr.training.seqnet import train_seqnet

    return train_seqnet(route_data(1), replace(SEQNET, epochs=epochs), out, resume=resume)


def _rank(rank: int, port: int, kind: str, runs: list[tuple[str, int, bool]]) -> None:
    """One rank's training runs in turn: (folder, epochs, resume) each."""
    import os

    from seqvpr.threads import use_threads

    use_threads(1)  # the one policy (a bare torch count would be re-asserted away)
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), RANK=str(rank), WORLD_SIZE="2",
                      LOCAL_RANK=str(rank))
    for out, count, resume in runs:
        train(kind, Path(out), count, resume)


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def state_weights(folder: Path) -> dict:
    state = ckpt.read_json(folder / STATE_JSON)
    return ckpt.read_tensors(folder / state["state_dir"] / ckpt.MODEL_FILE)


@pytest.fixture(scope="module")
def alone_run(tmp_path_factory):
    """``alone_run(kind)``: the single-process 3-epoch run (one thread, as each rank) and its folder, trained once
    per kind for the module's tests that compare the ranks with it."""
    from seqvpr.threads import use_threads

    runs: dict[str, tuple] = {}

    def run(kind: str) -> tuple:
        if kind not in runs:
            use_threads(1)  # the one policy (a bare torch count would be re-asserted away)
            out = tmp_path_factory.mktemp(f"alone-{kind}")
            runs[kind] = (train(kind, out, 3), out)
        return runs[kind]

    return run


@pytest.mark.parametrize("kind", ["seqmatchnet", "seqnet"])
def test_two_ranks_train_the_single_process_model_and_resume(tmp_path, kind, alone_run):
    from seqvpr.threads import use_threads

    use_threads(1)  # the one policy (a bare torch count would be re-asserted away)
    alone, alone_dir = alone_run(kind)
    two, resumed = str(tmp_path / "two"), str(tmp_path / "resumed")
    spawn_ranks(_rank, (free_port(), kind, [(two, 3, False), (resumed, 1, False), (resumed, 3, True)]))
    expected = state_weights(alone_dir)
    for run in ("two", "resumed"):
        got = state_weights(tmp_path / run)
        assert got.keys() == expected.keys()
        for key in expected:
            np.testing.assert_allclose(got[key].numpy(), expected[key].numpy(), rtol=1e-5, atol=1e-6, err_msg=key)
        history = ckpt.read_json(tmp_path / run / STATE_JSON)["history"]
        assert [h["triplets"] for h in history] == [r.triplets for r in alone.history]  # the same mined triplets
        np.testing.assert_allclose([h["loss"] for h in history], [r.loss for r in alone.history], rtol=1e-5)
        assert not list((tmp_path / run).glob("*.part"))


class NoNormBackbone(nn.Module):
    """The JIST tests' tiny backbone without its BatchNorm (see the module docstring)."""

    out_channels = 16

    def __init__(self) -> None:
        super().__init__()
        self.conv1 = nn.Sequential(nn.Conv2d(3, 8, 3, stride=2, padding=1), nn.ReLU())
        self.conv2 = nn.Sequential(nn.Conv2d(8, 16, 3, stride=2, padding=1), nn.ReLU())

    def features(self, images):
        return self.conv2(self.conv1(images))


def jist_data(root: Path):
    from seqvpr.data.ground_truth import Radius
    from seqvpr.data.sources import load_traversal
    from seqvpr.training.trainer import TrainingData

    load = lambda key, role: load_traversal(str(root / key), role)  # noqa: E731
    return TrainingData(load("train_reference", "reference"), load("train_query", "query"),
                        load("test_reference", "reference"), load("test_query", "query"),
                        Radius(10.0, "m"), Radius(25.0, "m"), Radius(25.0, "m"))


def train_jist_run(root: Path, out: Path) -> None:
    from seqvpr.training.jist import train_jist
    from tests.training.test_jist_training import CONFIG, SETTINGS

    train_jist(jist_data(root), CONFIG, SETTINGS, out, backbone_factory=NoNormBackbone)


def _jist_rank(rank: int, port: int, root: str, out: str) -> None:
    import os

    from seqvpr.threads import use_threads

    use_threads(1)  # the one policy (a bare torch count would be re-asserted away)
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), RANK=str(rank), WORLD_SIZE="2",
                      LOCAL_RANK=str(rank))
    train_jist_run(Path(root), Path(out))


def test_two_ranks_train_jist_as_one_process(tmp_path):

    from seqvpr.synthetic.world import write_demo_world
    from tests.training.test_jist_training import H, W

    from seqvpr.threads import use_threads

    use_threads(1)  # the one policy (a bare torch count would be re-asserted away)
    write_demo_world(tmp_path / "world", frames=40, width=W, height=H, seed=0, query_condition="dusk")
    train_jist_run(tmp_path / "world", tmp_path / "alone")
    spawn_ranks(_jist_rank, (free_port(), str(tmp_path / "world"), str(tmp_path / "two")))
    expected, got = state_weights(tmp_path / "alone"), state_weights(tmp_path / "two")
    assert got.keys() == expected.keys()
    for key in expected:
        np.testing.assert_allclose(got[key].numpy(), expected[key].numpy(), rtol=1e-4, atol=1e-4, err_msg=key)


def _failing_rank(rank: int, port: int, out: str) -> None:
    import os

    from seqvpr.threads import use_threads

    use_threads(1)  # the one policy (a bare torch count would be re-asserted away)
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), RANK=str(rank), WORLD_SIZE="2",
                      LOCAL_RANK=str(rank))
    from seqvpr.models.seqmatchnet import TransformConfig
    from seqvpr.training.seqmatchnet import train_seqmatchnet

    from seqvpr.sequences.windows import SequenceSpec

    # rank 1's windows are longer than the data: it fails after joining the group, while rank 0 goes on to write
    length = SMN.sequence.length if rank == 0 else 500
    train_seqmatchnet(small_data(), TransformConfig(16), replace(SMN, epochs=2, sequence=SequenceSpec(length)),
                      Path(out))


def test_a_rank_that_fails_fails_the_run_before_rank_0_writes_anything(tmp_path):
    with pytest.raises(mp.ProcessRaisedException, match="rank 1 of 2 failed: .*longer than every segment"):
        spawn_ranks(_failing_rank, (free_port(), str(tmp_path / "run")))
    assert not (tmp_path / "run").exists() or not any((tmp_path / "run").iterdir())


def _rank_failing_in_epoch_2(rank: int, port: int, out: str) -> None:
    """A rank of a 3-epoch SeqMatchNet run whose rank 1 fails in a step of epoch 2 (after epoch 1 is saved)."""
    from seqvpr.training.seqmatchnet import SeqMatchNetLearner

    if rank == 1:
        real = SeqMatchNetLearner.batch_loss

        def failing(self, model, loss, batch, step, rng, settings):
            if step.epoch == 2:
                raise RuntimeError("rank 1 lost its data disk")
            return real(self, model, loss, batch, step, rng, settings)

        SeqMatchNetLearner.batch_loss = failing  # type: ignore[method-assign]
    _rank(rank, port, "seqmatchnet", [(out, 3, False)])


def test_a_rank_failing_mid_run_fails_it_with_its_error_and_leaves_the_last_whole_epoch_to_resume(tmp_path, alone_run):
    from seqvpr.threads import use_threads

    use_threads(1)  # the one policy (a bare torch count would be re-asserted away)
    with pytest.raises(mp.ProcessRaisedException, match="rank 1 lost its data disk"):
        spawn_ranks(_rank_failing_in_epoch_2, (free_port(), str(tmp_path / "run")))
    state = ckpt.read_json(tmp_path / "run" / STATE_JSON)
    assert [h["epoch"] for h in state["history"]] == [0, 1]  # epoch 1 whole (after the untrained 0), none of 2
    assert not list((tmp_path / "run").rglob("*.part"))
    spawn_ranks(_rank, (free_port(), "seqmatchnet", [(str(tmp_path / "run"), 3, True)]))
    alone, alone_dir = alone_run("seqmatchnet")
    expected, got = state_weights(alone_dir), state_weights(tmp_path / "run")
    for key in expected:
        np.testing.assert_allclose(got[key].numpy(), expected[key].numpy(), rtol=1e-5, atol=1e-6, err_msg=key)
    assert [h["triplets"] for h in ckpt.read_json(tmp_path / "run" / STATE_JSON)["history"]] == [
        r.triplets for r in alone.history]
