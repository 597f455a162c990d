"""A training run's files: the best model folder, and the resumable state of the last finished epoch.

Each epoch writes a complete state folder (``state/epoch_NNNN``: the model folder, plus ``train_state.safetensors``
with optimizer buffers, the learner's own tensors such as a miner cache, and trainable loss parameters), then the
pointer ``train_state.json`` (settings, model config, scheduler, history) is written atomically: that is the
commit. Older state folders are removed after it.
"""

from __future__ import annotations

import shutil
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Any

from seqvpr.errors import SeqvprError
from seqvpr.models.files import read_json, read_tensors, save_json, save_tensors
from seqvpr.training.settings import jsonable
from seqvpr.training.history import HISTORY_FILE, EpochRecord, record_from_dict, write_history
from seqvpr.training.state import STATE_FILE, STATE_JSON, flatten_optimizer, unflatten_optimizer

if TYPE_CHECKING:
    from seqvpr.training.trainer import _Run

LOSS_PREFIX = "loss."


def check_same(saved: dict, current: dict, path: Path) -> None:
    """Resuming with other settings would not continue the same run: name the first differing field."""
    current = jsonable(current)
    for key in sorted(set(saved) | set(current)):
        if saved.get(key) != current.get(key):
            raise SeqvprError(
                f"{path}: cannot resume with {key}={current.get(key)!r}; the run was started with {saved.get(key)!r}"
            )


class RunState:
    """Saves and restores one run's model folders and resumable state."""

    def __init__(self, run: _Run) -> None:
        self.run = run

    @staticmethod
    def exists(out: Path) -> bool:
        return (out / STATE_JSON).is_file()

    def metadata(self, epoch: int, recall: dict[int, float]) -> dict[str, Any]:
        """What a model folder's config records besides the model: L, epoch, validation recall, settings, data."""
        run = self.run
        spec, data = run.learner.spec, run.data
        return {
            "sequence": {"length": spec.length, "align": spec.align, "boundary": spec.boundary},
            "epoch": epoch,
            "validation_recall": {str(k): v for k, v in recall.items()},
            "training": run.settings.as_dict(),
            "data": {
                "reference": data.reference.source, "query": data.query.source,
                "val_reference": data.val_reference.source, "val_query": data.val_query.source,
                "positive_radius": str(data.positive_radius), "negative_radius": str(data.negative_radius),
                "val_radius": str(data.val_radius),
            },
        }

    def save_best(self, out: Path, epoch: int, recall: dict[int, float]) -> None:
        self.run.learner.save_model(out, self.run.model, self.metadata(epoch, recall))

    def save(self, out: Path, history: list[EpochRecord], best_epoch: int, best_recall: dict[int, float]) -> None:
        """A complete state folder for this epoch, then the pointer to it (the commit), then old folders go."""
        run, epoch = self.run, history[-1].epoch
        folder = out / "state" / f"epoch_{epoch:04d}"
        run.learner.save_model(folder, run.model, self.metadata(epoch, history[-1].recall))
        tensors, rest = flatten_optimizer(run.optimizer.state_dict())
        tensors.update(run.learner.state_tensors())
        if run.loss is not None:
            tensors.update({LOSS_PREFIX + k: v for k, v in run.loss.state_dict().items()})
        save_tensors(folder / STATE_FILE, tensors)
        write_history(out / HISTORY_FILE, history)
        save_json(out / STATE_JSON, {
            "state_dir": str(folder.relative_to(out)),
            "settings": run.settings.resume_key(),
            run.learner.config_key: run.learner.config(),
            "optimizer": rest,
            "scheduler": None if run.scheduler is None else run.scheduler.state_dict(),
            "best_epoch": best_epoch,
            "best_recall": {str(k): v for k, v in best_recall.items()},
            "history": [asdict(r) for r in history],
        })
        for old in (out / "state").iterdir():
            if old != folder:
                shutil.rmtree(old, ignore_errors=True)

    def restore(self, out: Path) -> tuple[list[EpochRecord], int, dict[int, float]]:
        """Load the last finished epoch's state; the run's settings and model config must match the saved ones."""
        run, path = self.run, out / STATE_JSON
        state = read_json(path)
        check_same(state["settings"], run.settings.resume_key(), path)
        key = run.learner.config_key
        if key not in state:
            raise SeqvprError(f"{path}: not a state of this kind of run (no {key!r} entry)")
        check_same(state[key], run.learner.config(), path)
        folder = out / state["state_dir"]
        run.model.load_state_dict(run.learner.load_weights(folder))
        tensors = read_tensors(folder / STATE_FILE)
        run.optimizer.load_state_dict(unflatten_optimizer(tensors, state["optimizer"]))
        if run.scheduler is not None:
            run.scheduler.load_state_dict(state["scheduler"])
        run.learner.load_state_tensors(tensors)
        if run.loss is not None:
            run.loss.load_state_dict({k[len(LOSS_PREFIX):]: v for k, v in tensors.items() if k.startswith(LOSS_PREFIX)})
        history = [record_from_dict(r) for r in state["history"]]
        best = {int(k): float(v) for k, v in state["best_recall"].items()}
        return history, int(state["best_epoch"]), best
