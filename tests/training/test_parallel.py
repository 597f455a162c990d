"""Data-parallel steps: what DistributedDataParallel wraps, and SyncBatchNorm on CUDA only."""

import torch
from torch import nn

from seqvpr.training.parallel import LearnerStep, synced_batch_norm


def _model() -> nn.Module:
    return nn.Sequential(nn.Linear(4, 4), nn.BatchNorm1d(4), nn.ReLU(), nn.Sequential(nn.BatchNorm1d(4)))


def test_cuda_models_normalize_with_the_whole_batch_keeping_their_parameters():
    model = _model()
    before = {name: id(p) for name, p in model.named_parameters()}
    keys = list(model.state_dict())
    synced = synced_batch_norm(model, torch.device("cuda", 0))
    kinds = [type(m) for m in synced.modules()]
    assert nn.BatchNorm1d not in kinds and kinds.count(nn.SyncBatchNorm) == 2
    assert {name: id(p) for name, p in synced.named_parameters()} == before  # the optimiser's own parameters
    assert list(synced.state_dict()) == keys  # checkpoints load either way


def test_cpu_models_keep_their_batch_norm():
    model = _model()
    assert synced_batch_norm(model, torch.device("cpu")) is model
    assert sum(isinstance(m, nn.SyncBatchNorm) for m in model.modules()) == 0


class _Learner:
    def batch_loss(self, model, loss, batch, step, rng, settings):
        return {"total": model(torch.as_tensor(batch, dtype=torch.float32)).sum() * settings}


def test_a_learner_step_holds_the_model_and_loss_and_computes_the_learners_loss():
    model, loss = nn.Linear(2, 1), nn.Linear(1, 1)
    step = LearnerStep(_Learner(), model, loss, 3.0)  # type: ignore[arg-type]
    assert {id(p) for p in step.parameters()} == {id(p) for p in [*model.parameters(), *loss.parameters()]}
    batch = [[1.0, 2.0], [3.0, 4.0]]
    expected = model(torch.tensor(batch)).sum() * 3.0
    assert torch.allclose(step(batch, None, None)["total"], expected)
