"""A training run's files: the best model folder, and the resumable state of the last finished epoch.

``out`` holds the best model folder (``model.safetensors`` + ``config.json``), ``history.csv``, the state folder
``state/epoch_NNNN`` (the epoch's model folder plus ``train_state.safetensors``: optimizer buffers, the learner's own
tensors such as a miner cache, trainable loss parameters) and ``train_state.json`` (settings, model config,
scheduler, history, the training data's records, and the digest of every other file), written last. Each epoch's
set is built in a temporary folder and swapped in for ``out`` by one atomic exchange (``seqvpr.io.atomic_folder``),
so a kill leaves the previous epoch's complete set or this one's, never the weights of one with the config of the
other; files that did not change (the best model of an earlier epoch, a user's own files) are carried over as hard
links. Resuming checks every recorded digest and the data.
"""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Any

from seqvpr.data.traversal_record import same_data, traversal_record
from seqvpr.errors import SeqvprError, reading
from seqvpr.identity import check_digest, seal_files
from seqvpr.io import atomic_folder, carry_over
from seqvpr.models.files import CONFIG_FILE, MODEL_FILE, read_json, read_tensors, save_json, save_tensors
from seqvpr.training.settings import jsonable
from seqvpr.training.history import HISTORY_FILE, EpochRecord, record_from_dict, write_history
from seqvpr.training.state import STATE_FILE, STATE_JSON, flatten_optimizer, unflatten_optimizer

if TYPE_CHECKING:
    from seqvpr.training.learner import TrainingData, TrainingRun

LOSS_PREFIX = "loss."
#: the layout version of ``train_state.json`` (absent: a run from before it recorded digests)
STATE_VERSION = 1
#: what each epoch writes anew in ``out``; everything else there is carried over
WRITTEN = (HISTORY_FILE, STATE_JSON, "state")


def check_same(saved: dict, current: dict, path: Path) -> None:
    """Resuming with other settings would not continue the same run: name the first differing field."""
    current = jsonable(current)
    for key in sorted(set(saved) | set(current)):
        if saved.get(key) != current.get(key):
            raise SeqvprError(
                f"{path}: cannot resume with {key}={current.get(key)!r}; the run was started with {saved.get(key)!r}"
            )


def data_records(data: TrainingData) -> dict[str, dict[str, Any]]:
    """The records of the four traversals a run trains and selects on: source, file digest, frames, content."""
    return {name: traversal_record(t) for name, t in data.traversals().items()}


def check_same_data(saved: dict, current: dict[str, dict[str, Any]], path: Path) -> None:
    """Resuming (or reusing) a run on other data would mix two runs: name the first traversal that differs."""
    for name, record in current.items():
        old = saved.get(name) if isinstance(saved, dict) else None
        if not isinstance(old, dict) or not same_data(old, record):
            was = f"{old.get('source') or '?'} frames {old.get('frames')}" if isinstance(old, dict) else "nothing"
            raise SeqvprError(f"{path}: trained on other data: its {name.replace('_', ' ')} was {was}, now "
                              f"{record['source'] or name} frames {record['frames']}"
                              + (" (same frames, other content)" if isinstance(old, dict)
                                 and old.get("frames") == record["frames"] else ""))


def recorded_data(out: Path) -> dict | None:
    """The data records of the run in ``out`` (None: no run, or one from before they were recorded)."""
    path = out / STATE_JSON
    if not path.is_file():
        return None
    state = read_json(path)
    return state.get("data") if isinstance(state, dict) else None


def check_state_files(state: dict, out: Path) -> None:
    """``train_state.json``'s version, its state folder inside ``out``, and every file it records holding what it
    says (one line naming the first that does not)."""
    path = out / STATE_JSON
    if state.get("version", STATE_VERSION) != STATE_VERSION:
        raise SeqvprError(f"{path}: training state version {state.get('version')!r} is not known (this seqvpr reads "
                          f"version {STATE_VERSION})")
    parts = Path(str(state["state_dir"])).parts
    if len(parts) != 2 or parts[0] != "state" or ".." in parts:
        raise SeqvprError(f"{path}: state_dir {state['state_dir']!r} is not a state folder of {out}")
    files = state.get("files", {})
    if not isinstance(files, dict):
        raise SeqvprError(f"{path}: 'files' must map file names to digests")
    for name, digest in files.items():
        if ".." in Path(name).parts or Path(name).is_absolute():
            raise SeqvprError(f"{path}: 'files' names {name!r}, not a file of {out}")
        check_digest(out / name, str(digest), str(path))


class RunState:
    """Saves and restores one run's model folders and resumable state."""

    def __init__(self, run: TrainingRun) -> None:
        self.run = run
        self._records: dict[str, dict[str, Any]] | None = None

    @staticmethod
    def exists(out: Path) -> bool:
        return (out / STATE_JSON).is_file()

    def records(self) -> dict[str, dict[str, Any]]:
        """The run's data records (computed once: the content digests read every descriptor)."""
        if self._records is None:
            self._records = data_records(self.run.data)
        return self._records

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
                "val_radius": str(data.val_radius), "records": self.records(),
            },
        }

    def save(self, out: Path, history: list[EpochRecord], best_epoch: int, best_recall: dict[int, float]) -> None:
        """This epoch's complete set (a new best model folder when this epoch is the best, else the old one carried
        over; the state folder; history; ``train_state.json`` last), swapped in for ``out`` whole."""
        run, epoch = self.run, history[-1].epoch
        best = best_epoch == epoch
        with atomic_folder(out, STATE_JSON) as tmp:
            carry_over(out, tmp, (*WRITTEN, MODEL_FILE, CONFIG_FILE) if best else WRITTEN)
            if best:
                run.learner.save_model(tmp, run.model, self.metadata(epoch, best_recall))
            folder = tmp / "state" / f"epoch_{epoch:04d}"
            run.learner.save_model(folder, run.model, self.metadata(epoch, history[-1].recall))
            save_tensors(folder / STATE_FILE, self._tensors())
            write_history(tmp / HISTORY_FILE, history)
            save_json(tmp / STATE_JSON, self._pointer(tmp, folder, history, best_epoch, best_recall))

    def _tensors(self) -> dict[str, Any]:
        """The optimizer's buffers, the learner's own state and the loss's parameters, as one tensor dict."""
        run = self.run
        tensors, _ = flatten_optimizer(run.optimizer.state_dict())
        tensors.update(run.learner.state_tensors())
        if run.loss is not None:
            tensors.update({LOSS_PREFIX + k: v for k, v in run.loss.state_dict().items()})
        return tensors

    def _pointer(self, out: Path, folder: Path, history: list[EpochRecord], best_epoch: int,
                 best_recall: dict[int, float]) -> dict[str, Any]:
        """``train_state.json``: what resuming needs, the data records, and the digest of every file of the set."""
        run, state_dir = self.run, folder.relative_to(out)
        names = [name for name in (MODEL_FILE, CONFIG_FILE, HISTORY_FILE) if (out / name).is_file()]
        names += [f"{state_dir.as_posix()}/{name}" for name in (MODEL_FILE, CONFIG_FILE, STATE_FILE)]
        return {
            "version": STATE_VERSION,
            "state_dir": state_dir.as_posix(),
            "settings": run.settings.resume_key(),
            run.learner.config_key: run.learner.config(),
            "optimizer": flatten_optimizer(run.optimizer.state_dict())[1],
            "scheduler": None if run.scheduler is None else run.scheduler.state_dict(),
            "best_epoch": best_epoch,
            "best_recall": {str(k): v for k, v in best_recall.items()},
            "history": [asdict(r) for r in history],
            "data": self.records(),
            "files": seal_files(out, names),
        }

    def restore(self, out: Path) -> tuple[list[EpochRecord], int, dict[int, float]]:
        """Load the last finished epoch's state; its files must hold what it records, and the run's settings, model
        config and data must match the saved ones."""
        path = out / STATE_JSON
        with reading(path, "a training state"):
            state = read_json(path)
            if not isinstance(state, dict):
                raise SeqvprError(f"{path}: not a training state (not a JSON object)")
            check_state_files(state, out)
            check_same(state["settings"], self.run.settings.resume_key(), path)
            key = self.run.learner.config_key
            if key not in state:
                raise SeqvprError(f"{path}: not a state of this kind of run (no {key!r} entry)")
            check_same(state[key], self.run.learner.config(), path)
            if "data" in state:  # runs from before the data was recorded resume unchecked
                check_same_data(state["data"], self.records(), path)
            return self._load(out / state["state_dir"], state)

    def _load(self, folder: Path, state: dict[str, Any]) -> tuple[list[EpochRecord], int, dict[int, float]]:
        """The model, optimizer, scheduler, learner and loss state of the state folder, then the history."""
        run = self.run
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
