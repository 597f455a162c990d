"""The one training loop, shared by SeqMatchNet, SeqNet and JIST (one ``SequenceLearner`` adapter each).

An epoch draws its query rounds from a seeded generator (``learner.rounds``: for descriptor models the trainable
queries in a random order, in chunks of ``refresh_every``; for JIST ``refreshes`` random samples). Before each round
the learner mines triplets with the current model (``learner.mine``, no gradients); batches of them go through
``learner.batch_loss``, one optimiser step each. After each epoch the learner validates the model on its own split;
the best epoch by validation Recall@``select_k`` is saved to ``out_dir``. Every epoch leaves a complete resumable
state (model, optimizer, scheduler, the learner's own state such as a miner cache, trainable loss parameters,
history) and the best model, committed together by one atomic swap of the folder (``training.resume``), so a killed
run resumed with the same settings and data reaches the same weights.

What differs between models lives behind ``SequenceLearner``: building the model (and a loss with parameters),
the optimiser, mining, the loss of a batch, validation, and the model folder.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from seqvpr import checks, distributed, threads
from seqvpr.data.ground_truth import ground_truth_within_radius
from seqvpr.errors import SeqvprError, SettingError
from seqvpr.io import check_output_apart, check_replaceable
from seqvpr.sequences.windows import SequenceSpec, require_windows, window_starts
from seqvpr.training.history import EpochRecord
from seqvpr.training.learner import (
    LoopSettings, SequenceLearner, SilentMonitor, Step, TrainingContext, TrainingData, TrainingMonitor, TrainResult,
)
from seqvpr.training.mining import Triplet
from seqvpr.training.parallel import StepLoss, data_parallel_step, single_process_step
from seqvpr.training.resume import RunState
from seqvpr.training.state import STATE_JSON

__all__ = [
    "EpochRecord", "LoopSettings", "SequenceLearner", "SilentMonitor", "Step", "TrainingContext", "TrainingData",
    "TrainingMonitor", "TrainResult", "train_sequence_model"]


def train_sequence_model(
    data: TrainingData,
    learner: SequenceLearner,
    settings: LoopSettings,
    out_dir: str | Path,
    *,
    resume: bool = False,
    monitor: TrainingMonitor | None = None,
) -> TrainResult:
    """Train ``learner``'s model; the best one by validation R@``select_k`` is written to ``out_dir``. Under
    ``torchrun`` the ranks train one model together: rank 0 mines and shares the triplets, each rank takes its share
    of every batch, gradients are averaged, and rank 0 alone writes (``seqvpr.distributed``).

    ``out_dir`` then holds the model folder files, ``history.csv``, and the resumable state of the last finished
    epoch. ``resume`` continues from that state (a run killed before its first state starts over, so
    ``resume=True`` is always safe to pass). Epoch 0 is the untrained model: validated and recorded, but kept only
    when ``settings.select_untrained`` is set or no epoch is trained; ties keep the earlier epoch.
    """
    threads.ensure_policy()
    out = check_run_arguments(data, out_dir, resume, monitor)
    with deterministic_algorithms(), distributed.process_group(settings.device):
        return _train(data, learner, settings, out, resume, monitor or SilentMonitor())


def check_training_inputs(data: object, settings: object, settings_type: type) -> None:
    """What every trainer checks first: the data is a ``TrainingData``, the settings its own kind's."""
    checks.instance(data, "data", TrainingData, "a TrainingData (training.learner.training_data)")
    checks.instance(settings, "settings", settings_type, f"a {settings_type.__name__}")


def check_run_arguments(data: object, out_dir: object, resume: object, monitor: object) -> Path:
    """A training run's own arguments, checked before anything is built (one line naming the argument); the run
    folder returned."""
    checks.instance(data, "data", TrainingData, "a TrainingData (training.learner.training_data)")
    checks.flag(resume, "resume")
    if monitor is not None and not all(callable(getattr(monitor, name, None))
                                       for name in ("start_run", "start_epoch", "advance", "end_epoch")):
        raise SettingError("{monitor} must have start_run, start_epoch, advance and end_epoch (a TrainingMonitor), "
                           f"got {type(monitor).__name__}")
    return checks.a_path(out_dir, "out_dir")


@contextlib.contextmanager
def deterministic_algorithms() -> Iterator[None]:
    """Torch's deterministic algorithms for the duration of a training run (restored after): with them two runs of
    one seed give bit-identical weights on CPU (measured without: ~3e-9 apart with 2 threads); ops that have no
    deterministic form warn rather than fail."""
    before, warn_only = torch.are_deterministic_algorithms_enabled(), torch.is_deterministic_algorithms_warn_only_enabled()
    torch.use_deterministic_algorithms(True, warn_only=True)
    try:
        yield
    finally:
        torch.use_deterministic_algorithms(before, warn_only=warn_only)


def _train(data: TrainingData, learner: SequenceLearner, settings: LoopSettings, out: Path, resume: bool,
           monitor: TrainingMonitor) -> TrainResult:
    def set_up() -> tuple[_Run, bool]:
        run = _Run(data, learner, settings)
        if run.state.exists(out) and not resume:
            raise SettingError(f"{out}: already holds a training run (use {{resume}} to continue it, or another {{out}})")
        check_replaceable(out, STATE_JSON)  # each epoch replaces the folder whole: say now if it cannot
        check_output_apart(out, [t.source for t in data.traversals().values()], "the training run")
        return run, resume and run.state.exists(out)

    # every rank set up (or all fail with the first failure's line) and looked at out before rank 0 writes
    run, resuming = distributed.everywhere(set_up)
    root = run.world.is_root  # only rank 0 reports and writes
    monitor = monitor if root else SilentMonitor()
    monitor.start_run(data, len(run.trainable))
    if resuming:
        history, best_epoch, best_recall = run.state.restore(out)
    else:
        history = [run.validate_record(0)]
        best_epoch, best_recall = -1, {k: -1.0 for k in history[0].recall}  # below any recall: epoch 1 replaces it
        if settings.select_untrained or settings.epochs == 0:
            best_epoch, best_recall = 0, history[0].recall
        if root:  # the best model (when this epoch is it) and the state, committed as one
            run.state.save(out, history, best_epoch, best_recall)
        monitor.end_epoch(history[0])
    select = run.settings.select_k
    for epoch in range(len(history), run.settings.epochs + 1):
        record = run.train_epoch(epoch, sum(r.steps for r in history), monitor)
        history.append(record)
        if record.recall[select] > best_recall[select]:
            best_epoch, best_recall = epoch, record.recall
        if root:
            run.state.save(out, history, best_epoch, best_recall)
        monitor.end_epoch(record)
    distributed.barrier(run.world)  # no rank leaves before rank 0 has written the last epoch
    return TrainResult(out, best_epoch, best_recall, history)


def training_context(data: TrainingData, spec: SequenceSpec, device: torch.device) -> TrainingContext:
    """Window starts (every traversal must have some windows), positives and non-negatives of the training pair."""
    for name, traversal in data.traversals().items():
        starts = window_starts(traversal.segment_ids, spec.length, spec.offset, spec.boundary)
        require_windows(starts, spec.length, f"{traversal.source or name} ({name.replace('_', ' ')})",
                        traversal.segment_ids)
    return TrainingContext(
        data, spec,
        window_starts(data.query.segment_ids, spec.length, spec.offset, spec.boundary),
        window_starts(data.reference.segment_ids, spec.length, spec.offset, spec.boundary),
        ground_truth_within_radius(data.query, data.reference, data.positive_radius),
        ground_truth_within_radius(data.query, data.reference, data.negative_radius),
        device,
    )


@dataclass
class _Epoch:
    """Running totals of one epoch."""

    losses: list[float] = field(default_factory=list)
    parts: dict[str, list[float]] = field(default_factory=dict)
    triplets: int = 0
    used: int = 0
    steps: int = 0
    mining_seconds: float = 0.0


class _Run:
    """One training run: the learner prepared on the data, the model, its optimiser and the run's state files."""

    def __init__(self, data: TrainingData, learner: SequenceLearner, settings: LoopSettings) -> None:
        if settings.select_k not in settings.ks:
            from dataclasses import replace

            settings = replace(settings, ks=tuple(sorted({*settings.ks, settings.select_k})))  # type: ignore[type-var]
        learner.check_data(data)
        self.data, self.learner, self.settings = data, learner, settings
        self.world = distributed.current()
        self.device = torch.device(settings.device)
        context = training_context(data, learner.spec, self.device)
        self.trainable = np.flatnonzero((context.query_starts >= 0) & context.positives.has_positive())
        if len(self.trainable) == 0:
            raise SeqvprError(
                f"no training query has both a window of {learner.spec.length} frames and a positive within "
                f"{data.positive_radius}"
            )
        learner.prepare(context, settings)
        self.val_gt = ground_truth_within_radius(data.val_query, data.val_reference, data.val_radius)
        torch.manual_seed(settings.seed)
        self.model = learner.build_model(settings).to(self.device)
        self.loss = learner.build_loss(settings)
        if self.loss is not None:
            self.loss = self.loss.to(self.device)
        self.optimizer, self.scheduler = learner.build_optimizer(self.model, self.loss, settings)
        self.scaler = torch.amp.GradScaler("cuda") if learner.mixed_precision(settings) else None
        self.state = RunState(self)
        self._stepper: StepLoss | None = None

    def train_epoch(self, epoch: int, first_step: int, monitor: TrainingMonitor) -> EpochRecord:
        started = time.perf_counter()
        rng = np.random.default_rng([self.settings.seed, epoch])
        rounds = self.learner.rounds(self.trainable, rng, self.settings)
        monitor.start_epoch(epoch, self.settings.epochs, sum(len(r) for r in rounds))
        lr = self.optimizer.param_groups[0]["lr"]
        totals = _Epoch()
        self.learner.features_seconds = 0.0
        for queries in rounds:
            tick = time.perf_counter()
            triplets = self._mine(queries, rng)
            totals.mining_seconds += time.perf_counter() - tick
            totals.used += len(triplets)
            stepped = 0
            for batch in self.learner.batches(triplets, self.settings):
                self._step(batch, Step(epoch, first_step + totals.steps), rng, totals)
                totals.triplets += sum(len(t.negatives) for t in batch)
                stepped += len(batch)
                monitor.advance(len(batch), totals.losses[-1])
            monitor.advance(len(queries) - stepped, None)
        if self.scheduler is not None:
            self.scheduler.step()
        return self._record(epoch, lr, totals, sum(len(r) for r in rounds), time.perf_counter() - started)

    def _mine(self, queries: np.ndarray, rng: np.random.Generator) -> list[Triplet]:
        """The round's triplets with the current model; with several ranks rank 0 mines and sends them with its
        random state, so every rank holds the same triplets and draws the same numbers after."""
        self.model.eval()

        def mine() -> tuple[list[Triplet], dict]:
            with torch.no_grad():
                return self.learner.mine(self.model, queries, rng), rng.bit_generator.state

        triplets, state = distributed.broadcast_from_root(mine, self.world)
        rng.bit_generator.state = state
        return triplets

    def _step(self, batch: Sequence[Triplet], step: Step, rng: np.random.Generator, totals: _Epoch) -> None:
        """One optimiser step on a batch of mined triplets (under autocast with a scaler when asked). With several
        ranks each takes its share of the batch, weighted by its share of the loss's terms, and DistributedDataParallel
        averages the gradients over the ranks in backward: the whole batch's step (``_share``, ``_step_loss``)."""
        self.model.train()
        if self.loss is not None:
            self.loss.train()
        part, weight = self._share(batch)
        autocast = torch.autocast("cuda", dtype=torch.float16) if self.scaler else contextlib.nullcontext()
        self.optimizer.zero_grad(set_to_none=True)
        with autocast:
            parts = self._step_loss()(part, step, rng)
        total = parts["total"] * (weight * self.world.size)  # DistributedDataParallel averages over the ranks
        if self.scaler is not None:
            self.scaler.scale(total).backward()
            self.scaler.step(self.optimizer)
            self.scaler.update()
        else:
            total.backward()
            self.optimizer.step()
        names = [name for name in parts if name != "total"]  # the learner's order, the same on every rank
        values = distributed.sum_over_ranks([float(parts[name].detach()) * weight for name in ["total", *names]],
                                            self.world)
        totals.losses.append(values[0])
        for name, value in zip(names, values[1:]):
            totals.parts.setdefault(name, []).append(value)
        totals.steps += 1

    def _step_loss(self) -> StepLoss:
        """The batch loss of a step: the learner's own alone, through DistributedDataParallel with several ranks
        (built at the first step, once every rank holds its resumed weights)."""
        if self._stepper is None:
            parts = (self.learner, self.model, self.loss, self.settings)
            self._stepper = single_process_step(*parts) if self.world.size == 1 else data_parallel_step(*parts, self.device)
        return self._stepper

    def _share(self, batch: Sequence[Triplet]) -> tuple[Sequence[Triplet], float]:
        """This rank's triplets of a batch and their share of its loss terms (alone: all of it, 1); a batch with
        fewer triplets than ranks is computed whole on every rank, each weighing it 1 / ranks."""
        size = self.world.size
        if size == 1:
            return batch, 1.0
        if len(batch) < size:
            return batch, 1.0 / size
        part = [batch[i] for i in np.array_split(np.arange(len(batch)), size)[self.world.rank]]
        return part, self.learner.loss_terms(part) / self.learner.loss_terms(batch)

    def _trainable(self) -> list[torch.Tensor]:
        return [p for group in self.optimizer.param_groups for p in group["params"]]

    def _record(self, epoch: int, lr: float, totals: _Epoch, queries: int, seconds: float) -> EpochRecord:
        record = self.validate_record(epoch)
        record.loss = float(np.mean(totals.losses)) if totals.losses else 0.0
        record.triplets, record.queries_used, record.queries_skipped = totals.triplets, totals.used, queries - totals.used
        record.features_seconds = self.learner.features_seconds
        record.lr, record.mining_seconds = lr, totals.mining_seconds - record.features_seconds
        record.steps = totals.steps
        record.parts = {name: float(np.mean(values)) for name, values in totals.parts.items()}
        record.epoch_seconds = seconds
        return record

    def validate_record(self, epoch: int) -> EpochRecord:
        self.model.eval()
        evaluation = self.learner.validate(self.model, self.data, self.val_gt, self.settings)
        return EpochRecord(epoch, 0.0, 0, 0, 0, self.optimizer.param_groups[0]["lr"], 0.0, 0.0, 0.0, evaluation.recall)
