"""``seqvpr train seqmatchnet|seqnet|jist`` and ``seqvpr ablate seqmatchnet``: thin layers over ``seqvpr.training``."""

from __future__ import annotations

import csv
import io
import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import click
from tqdm import tqdm

from seqvpr.cli import describe_pair, load_pair, parse_ks, parse_thumbnail, recall_table
from seqvpr.data.groundtruth import Radius, ground_truth_within_radius, parse_radius
from seqvpr.data.traversal import Traversal
from seqvpr.errors import SeqvprError
from seqvpr.features.patchnorm import PatchNormConfig
from seqvpr.io import atomic_write
from seqvpr.models.jist import JIST_BACKBONES, JistConfig
from seqvpr.models.seqmatchnet import TransformConfig
from seqvpr.sequences.windows import SequenceSpec
from seqvpr.experiments.ablation import ablation_markdown, run_ablation
from seqvpr.training.cosplace import CellGrouping
from seqvpr.training.jist import JistData, JistTrainSettings, jist_positions, train_jist
from seqvpr.training.seqmatchnet import EpochRecord, TrainingData, TrainSettings, train_seqmatchnet
from seqvpr.training.seqnet import SeqNetSettings, train_seqnet

Settings = TypeVar("Settings", TrainSettings, SeqNetSettings)
Pair = tuple[Traversal, Traversal]


class TqdmMonitor:
    """A progress bar per epoch with the running loss, and one summary line per epoch on stderr."""

    def __init__(self, label: str = "") -> None:
        self.label = label
        self.bar: tqdm | None = None
        self.losses: list[float] = []

    def start_run(self, data: TrainingData, trainable_queries: int) -> None:
        click.echo(
            f"{self.label}train: {data.reference!r} / {data.query!r}\n{self.label}validation: {data.val_reference!r} / "
            f"{data.val_query!r}\n{self.label}positives within {data.positive_radius}, negatives outside "
            f"{data.negative_radius}; {trainable_queries} training queries",
            err=True,
        )

    def start_epoch(self, epoch: int, epochs: int, queries: int) -> None:
        self.losses = []
        self.bar = tqdm(total=queries, desc=f"{self.label}epoch {epoch}/{epochs}", unit="query",
                        file=sys.stderr, leave=False, disable=None)

    def advance(self, queries: int, loss: float | None) -> None:
        if loss is not None:
            self.losses.append(loss)
        if self.bar is not None:
            self.bar.update(queries)
            if loss is not None:
                self.bar.set_postfix(loss=f"{sum(self.losses) / len(self.losses):.4f}")

    def end_epoch(self, record: EpochRecord) -> None:
        if self.bar is not None:
            self.bar.close()
        recall = " ".join(f"R@{k} {v:.3f}" for k, v in sorted(record.recall.items()))
        timing = "" if record.epoch == 0 else (
            f"loss {record.loss:.4f}, {record.triplets} triplets, {record.queries_skipped} queries skipped, "
            f"{record.epoch_seconds:.1f}s (mining {record.mining_seconds:.2f}s); "
        )
        click.echo(f"{self.label}epoch {record.epoch}: {timing}validation {recall}", err=True)


def with_options(options: list[Callable]) -> Callable[[Callable], Callable]:
    """A decorator adding click ``options`` to a command, in the order ``--help`` shows them."""

    def decorate(function: Callable) -> Callable:
        for option in reversed(options):
            function = option(function)
        return function

    return decorate


def data_options(negative_default: str) -> list[Callable]:
    """Training and validation traversals, their splits and the radii (shared by every training command)."""
    return [
        click.option("--reference", "-r", required=True, help="Training reference traversal (any source seqvpr reads)."),
        click.option("--query", "-q", required=True, help="Training query traversal."),
        click.option("--frames", help="Keep source frames START:STOP of both traversals first (e.g. 17:2000)."),
        click.option("--train-frames", required=True, help="Source frames START:STOP used for training."),
        click.option("--val-frames", required=True, help="Source frames START:STOP used for validation (model selection)."),
        click.option("--val-reference", help="Validation reference (default: --reference)."),
        click.option("--val-query", help="Validation query (default: --query)."),
        click.option("--radius", required=True, help="Ground truth for validation (and test): 25m or 2f."),
        click.option("--pos-radius", help="Positives for training are within this radius (default: --radius)."),
        click.option("--neg-radius",
                     help=f"Negatives lie outside this radius (default: {negative_default}; a buffer zone)."),
    ]


def sequence_training_options(defaults: TrainSettings | SeqNetSettings, model_options: list[Callable]):
    """The options of a model trained on frame descriptors (data, sequence, mining, optimisation, patchnorm), with
    the defaults of its settings class, plus ``model_options`` (its own) before --seed."""
    pool = "all" if defaults.negative_pool is None else str(defaults.negative_pool)
    per_epoch = defaults.refresh_every is None
    options = [
        *data_options("4x --pos-radius"),
        click.option("--seq-len", "-L", default=defaults.sequence.length, show_default=True, type=int,
                     help="Frames per sequence window."),
        click.option("--align", type=click.Choice(["centered", "causal"]), default="centered", show_default=True),
        click.option("--boundary", type=click.Choice(["drop", "shift"]), default="drop", show_default=True,
                     help="Windows at segment ends: dropped (training never uses shifted windows) or shifted."),
        click.option("--margin", default=defaults.margin, show_default=True, type=float,
                     help="Triplet margin on sequence distances (default sqrt(0.1), as the reference)."),
        click.option("--negatives", default=defaults.negatives, show_default=True, type=int,
                     help="Hard negatives per query."),
        click.option("--negative-pool", default=pool, show_default=True,
                     help="Random negative candidates per query (plus its previous negatives), or 'all'."),
        click.option("--refresh-every", default=defaults.refresh_every, show_default=not per_epoch, type=int,
                     help="Re-mine with the current model every N queries."
                          + per_epoch * "  [default: once per epoch]"),
        click.option("--batch-size", default=defaults.batch_size, show_default=True, type=int,
                     help="Queries (triplet groups) per step."),
        click.option("--epochs", default=defaults.epochs, show_default=True, type=int),
        click.option("--optimizer", type=click.Choice(["sgd", "adam"]), default=defaults.optimizer, show_default=True),
        click.option("--lr", default=defaults.lr, show_default=True, type=float),
        click.option("--momentum", default=defaults.momentum, show_default=True, type=float, help="SGD momentum."),
        click.option("--weight-decay", default=defaults.weight_decay, show_default=True, type=float),
        click.option("--lr-step", default=defaults.lr_step, show_default=True, type=int,
                     help="Epochs between learning-rate steps."),
        click.option("--lr-gamma", default=defaults.lr_gamma, show_default=True, type=float,
                     help="Learning-rate factor per step."),
        click.option("--select", "select_k", default=defaults.select_k, show_default=True, type=int,
                     help="Keep the checkpoint with the best validation Recall@K for this K."),
        click.option("--k", "ks", default=",".join(map(str, defaults.ks)), show_default=True,
                     help="Recall@K values reported."),
        *model_options,
        click.option("--seed", default=defaults.seed, show_default=True, type=int),
        click.option("--device", default="cpu", show_default=True),
        click.option("--thumbnail", default="64x32", show_default=True, help="Image folders: patch-normalised thumbnail size."),
        click.option("--patch", default=8, show_default=True, type=int, help="Image folders: patch side."),
    ]
    return with_options(options)


training_options = sequence_training_options(TrainSettings(), [
    click.option("--out-dim", type=int, help="Output dimension of the transform (default: input dimension)."),
    click.option("--hidden", default="", help="Hidden layer sizes for the deeper MLP variant, e.g. 4096."),
    click.option("--init", type=click.Choice(["reference", "identity"]), default="reference", show_default=True,
                 help="PyTorch default initialisation (as the reference code) or identity W, zero B."),
])

seqnet_options = sequence_training_options(SeqNetSettings(), [
    click.option("--w", "w", default=SeqNetSettings.w, show_default=True, type=int,
                 help="Temporal kernel width of SeqNet's Conv1d (at most -L)."),
    click.option("--out-dim", type=int, help="Output dimension of the sequence descriptor (default: input dimension)."),
])


def settings_from_options(o: dict, kind: type[Settings] = TrainSettings, **model_fields: Any) -> Settings:
    """The settings object of ``kind`` (TrainSettings or SeqNetSettings) the shared options describe."""
    pool = o["negative_pool"]
    try:
        pool_size = None if str(pool).lower() == "all" else int(pool)
    except ValueError:
        raise SeqvprError(f"--negative-pool {pool!r}: expected a number or 'all'") from None
    ks = parse_ks(o["ks"])
    return kind(
        sequence=SequenceSpec(o["seq_len"], o["align"], o["boundary"]),
        margin=o["margin"], negatives=o["negatives"], negative_pool=pool_size, refresh_every=o["refresh_every"],
        batch_size=o["batch_size"], epochs=o["epochs"], optimizer=o["optimizer"], lr=o["lr"],
        momentum=o["momentum"], weight_decay=o["weight_decay"], lr_step=o["lr_step"], lr_gamma=o["lr_gamma"],
        select_k=o["select_k"], ks=ks, seed=o["seed"], device=o["device"], **model_fields,
    )


def transform_from_options(o: dict, dim: int) -> TransformConfig:
    try:
        hidden = tuple(int(h) for h in o["hidden"].split(",") if h.strip())
    except ValueError:
        raise SeqvprError(f"--hidden {o['hidden']!r}: expected comma-separated sizes, e.g. 4096") from None
    return TransformConfig(dim, o["out_dim"], hidden, o["init"])


def radii_from_options(o: dict, negative_factor: float = 4.0) -> tuple[Radius, Radius, Radius]:
    """Validation radius, positive radius (default: the validation one), negative radius (default
    ``negative_factor`` x positive)."""
    val = parse_radius(o["radius"])
    pos = parse_radius(o["pos_radius"]) if o["pos_radius"] else val
    neg = parse_radius(o["neg_radius"]) if o["neg_radius"] else Radius(negative_factor * pos.value, pos.unit)
    return val, pos, neg


def split(traversal: Traversal, frames: str, option: str) -> Traversal:
    """The frames START:STOP of a traversal."""
    from seqvpr.cli import parse_frames

    start, stop = parse_frames(frames)
    try:
        return traversal.slice_frames(start, stop)
    except SeqvprError as error:
        raise SeqvprError(f"{option} {frames}: {error}") from None


def disjoint(a: str, b: str, names: tuple[str, str]) -> None:
    """Splits of the same traversals must not overlap (validation is neither train nor test)."""
    from seqvpr.cli import parse_frames

    (a0, a1), (b0, b1) = parse_frames(a), parse_frames(b)
    lo = max(a0 if a0 is not None else -10**18, b0 if b0 is not None else -10**18)
    hi = min(a1 if a1 is not None else 10**18, b1 if b1 is not None else 10**18)
    if lo < hi:
        raise SeqvprError(f"{names[0]} {a} and {names[1]} {b} overlap on the same traversals; use disjoint ranges")


def training_splits(o: dict, prepare: Callable[[Traversal, Traversal], Pair]) -> tuple[Pair, Pair, Pair]:
    """The train and validation pairs of the data options, each loaded pair passed through ``prepare`` (e.g.
    described) before splitting; returns them with the whole prepared training pair."""
    ref_all, qry_all = prepare(*load_pair(o["reference"], o["query"], o["frames"]))
    if o["val_reference"] or o["val_query"]:
        val_ref_all, val_qry_all = prepare(
            *load_pair(o["val_reference"] or o["reference"], o["val_query"] or o["query"], o["frames"])
        )
    else:
        disjoint(o["train_frames"], o["val_frames"], ("--train-frames", "--val-frames"))
        val_ref_all, val_qry_all = ref_all, qry_all
    train = split(ref_all, o["train_frames"], "--train-frames"), split(qry_all, o["train_frames"], "--train-frames")
    val = split(val_ref_all, o["val_frames"], "--val-frames"), split(val_qry_all, o["val_frames"], "--val-frames")
    return train, val, (ref_all, qry_all)


def training_data(o: dict) -> tuple[TrainingData, Traversal, Traversal, PatchNormConfig]:
    """Described train/validation splits; returns the data and the full described traversals."""
    width, height = parse_thumbnail(o["thumbnail"])
    config = PatchNormConfig(width, height, o["patch"])
    val, pos, neg = radii_from_options(o)
    train, validation, (ref_all, qry_all) = training_splits(o, lambda ref, qry: describe_pair(ref, qry, config))
    return TrainingData(*train, *validation, pos, neg, val), ref_all, qry_all, config


def echo_best(best_epoch: int, best_recall: dict[int, float], folder: Path | str) -> None:
    """The closing lines of a training command: the best epoch's validation recall and the model folder."""
    best = " ".join(f"R@{k} {v:.3f}" for k, v in sorted(best_recall.items()))
    click.echo(f"best epoch {best_epoch}: validation {best}\nmodel: {folder} "
               f"(apply with: seqvpr match --model {folder} ...)")


@click.group()
def train() -> None:
    """Train a model on a training split, selecting the best checkpoint on a validation split."""


@train.command(name="seqmatchnet", epilog="""\b
Example (Nordland, summer reference, winter query, +-1 frame, L=5):
  seqvpr train seqmatchnet -r nordland_64x32/summer -q nordland_64x32/winter \\
      --train-frames 17:1200 --val-frames 1200:1600 --radius 1f -L 5 --out runs/nordland
  seqvpr match -r nordland_64x32/summer -q nordland_64x32/winter --frames 1600:2000 \\
      --radius 1f --model runs/nordland
""")
@training_options
@click.option("--out", "out_dir", default="seqmatchnet-run", show_default=True, type=click.Path(),
              help="Run folder: best model (model.safetensors + config.json), history.csv, resumable state.")
@click.option("--resume", is_flag=True, help="Continue the run in --out from its last finished epoch.")
def train_seqmatchnet_command(out_dir, resume, **o) -> None:
    """SeqMatchNet: a per-frame transform trained with a sequence-matching triplet loss and sequence mining."""
    settings = settings_from_options(o)
    data, _, _, _ = training_data(o)
    transform = transform_from_options(o, data.dim)
    result = train_seqmatchnet(data, transform, settings, out_dir, resume=resume, monitor=TqdmMonitor())
    echo_best(result.best_epoch, result.best_recall, result.folder)


@train.command(name="seqnet", epilog="""\b
Example (Nordland, summer reference, winter query, +-1 frame, L=5, w=3):
  seqvpr train seqnet -r nordland_64x32/summer -q nordland_64x32/winter \\
      --train-frames 17:1200 --val-frames 1200:1600 --radius 1f --out runs/seqnet-nordland
  seqvpr match -r nordland_64x32/summer -q nordland_64x32/winter --frames 1600:2000 \\
      --radius 1f --model runs/seqnet-nordland --rerank 20
""")
@seqnet_options
@click.option("--out", "out_dir", default="seqnet-run", show_default=True, type=click.Path(),
              help="Run folder: best model (model.safetensors + config.json), history.csv, resumable state.")
@click.option("--resume", is_flag=True, help="Continue the run in --out from its last finished epoch.")
def train_seqnet_command(out_dir, resume, w, out_dim, **o) -> None:
    """SeqNet: a temporal Conv1d over each window of frame descriptors, one descriptor per sequence, trained with a
    triplet loss and hard negatives mined in its own descriptor space (velocity 1)."""
    settings = settings_from_options(o, SeqNetSettings, w=w, out_dim=out_dim)
    data, _, _, _ = training_data(o)
    result = train_seqnet(data, settings, out_dir, resume=resume, monitor=TqdmMonitor())
    echo_best(result.best_epoch, result.best_recall, result.folder)


# --- JIST ---------------------------------------------------------------------------------------------------------

JIST_STAGES = {"resnet18": ("layer4",), "resnet50": ("layer4",), "efficientnet-lite0": ("stage7", "head")}


class JistProgress:
    """A tqdm bar of iterations per epoch (with the running loss) and one line per epoch on stderr."""

    def __init__(self, per_epoch: int | None, label: str = "") -> None:
        self.per_epoch, self.label = per_epoch, label
        self.bar: tqdm | None = None
        self.totals: list[float] = []

    def iteration(self, epoch: int, losses: dict[str, float]) -> None:
        if self.bar is None:
            self.totals = []
            self.bar = tqdm(total=self.per_epoch, desc=f"{self.label}epoch {epoch}", unit="it", file=sys.stderr, leave=False,
                            disable=None)
        self.totals.append(losses["total"])
        self.bar.update(1)
        self.bar.set_postfix(loss=f"{sum(self.totals) / len(self.totals):.4f}")

    def epoch(self, record: dict[str, Any]) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None
        recall = " ".join(f"R@{key.split('@')[1]} {value:.3f}" for key, value in record.items()
                          if key.startswith("recall@"))
        click.echo(
            f"{self.label}epoch {record['epoch']}: {record['iterations']} iterations, loss {record['loss']:.4f} (sequence "
            f"{record['sequence_loss']:.4f}, images {record['image_loss']:.4f}), {record['seconds']:.1f}s; "
            f"validation {recall}",
            err=True,
        )


def jist_data(o: dict) -> JistData:
    """The undescribed train/validation splits (JIST reads the images) and the radii, in metres or in frames."""
    val, pos, neg = radii_from_options(o, 2.5)
    if len({val.unit, pos.unit, neg.unit}) > 1:
        raise SeqvprError("--radius, --pos-radius and --neg-radius must share one unit (all m or all f)")
    train, validation, _ = training_splits(o, lambda ref, qry: (jist_positions(ref, val), jist_positions(qry, val)))
    return JistData(*train, *validation, positive_radius=pos.value, negative_radius=neg.value, val_radius=val.value)


def jist_config(o: dict) -> JistConfig:
    """The model and loss options as a JistConfig (trainable stages default to the backbone's last stage)."""
    stages = tuple(s.strip() for s in (o["trainable_stages"] or "").split(",") if s.strip())
    return JistConfig(
        backbone=o["backbone"], weights=o["weights"], out_dim=o["out_dim"],
        trainable_stages=stages or JIST_STAGES[o["backbone"]], seq_length=o["seq_len"], lr=o["lr"],
        classifier_lr=o["classifier_lr"],
    )


def jist_settings(o: dict) -> JistTrainSettings:
    """The schedule, batch, image-size and grouping options as JistTrainSettings."""
    width, height = parse_thumbnail(o["image_size"], "--image-size")
    return JistTrainSettings(
        epochs=o["epochs"], refreshes=o["refreshes"], max_iterations=o["max_iterations"], batch_size=o["batch_size"],
        images_per_batch=o["images_per_batch"], width=width, height=height,
        grouping=CellGrouping(cell_m=o["cell_size"], min_images=o["min_images"]), select_k=o["select_k"],
        ks=parse_ks(o["ks"]), device=o["device"], seed=o["seed"],
    )


@train.command(name="jist", epilog="""\b
Examples:
  # a route with positions (metres): positives within 10 m, negatives outside 25 m, validation within 25 m
  seqvpr train jist -r city/day -q city/night --train-frames 0:4000 --val-frames 4000:5000 \\
      --radius 25m --pos-radius 10m --backbone resnet18 --weights cosplace_r18.pth --out runs/jist-city
  # Nordland image folders (frame-aligned, no positions): radii and cells count frames
  seqvpr train jist -r nordland/summer -q nordland/winter --train-frames 17:1200 --val-frames 1200:1600 \\
      --radius 1f --backbone efficientnet-lite0 --weights imagenet --out runs/jist-nordland
  seqvpr match -r nordland/summer -q nordland/winter --frames 1600:2000 --radius 1f --model runs/jist-nordland
""")
@with_options(data_options("2.5x --pos-radius, as the reference's 10/25 m"))
@click.option("--backbone", type=click.Choice(list(JIST_BACKBONES)), default=JistConfig.backbone, show_default=True)
@click.option("--weights", help="Backbone weights: a checkpoint path (torchvision or CosPlace keys), or 'imagenet' "
              "(efficientnet-lite0's packaged weights).  [default: random initialisation]")
@click.option("--trainable-stages", help="Comma list of backbone stages to train (ResNet: stem, layer1..layer4; "
              "efficientnet-lite0: stem, stage1..stage7, head).  [default: layer4; efficientnet-lite0: stage7,head]")
@click.option("--out-dim", default=JistConfig.out_dim, show_default=True, type=int, help="Frame descriptor size.")
@click.option("--seq-len", "-L", default=JistConfig.seq_length, show_default=True, type=int,
              help="Frames per sequence window.")
@click.option("--epochs", default=JistTrainSettings.epochs, show_default=True, type=int)
@click.option("--refreshes", default=JistTrainSettings.refreshes, show_default=True, type=int,
              help="Triplet mining refreshes per epoch.")
@click.option("--max-iterations", type=int, help="Most iterations per refresh.  [default: every mined batch]")
@click.option("--batch-size", default=JistTrainSettings.batch_size, show_default=True, type=int,
              help="Sequence triplets per iteration.")
@click.option("--images-per-batch", default=JistTrainSettings.images_per_batch, show_default=True, type=int,
              help="Single images per iteration for the CosPlace classification branch.")
@click.option("--image-size", default=f"{JistTrainSettings.width}x{JistTrainSettings.height}", show_default=True,
              help="Image size WIDTHxHEIGHT for training and for seqvpr match --model.")
@click.option("--cell-size", default=CellGrouping.cell_m, show_default=True, type=float,
              help="CosPlace class cells, in the radius unit (metres, or frames with a frame radius).")
@click.option("--min-images", default=CellGrouping.min_images, show_default=True, type=int,
              help="Images a CosPlace class needs to be used.")
@click.option("--lr", default=JistConfig.lr, show_default=True, type=float, help="Adam learning rate of the model.")
@click.option("--classifier-lr", default=JistConfig.classifier_lr, show_default=True, type=float,
              help="Adam learning rate of the CosFace classifiers.")
@click.option("--select", "select_k", default=JistTrainSettings.select_k, show_default=True, type=int,
              help="Keep the epoch with the best validation Recall@K for this K (one of --k).")
@click.option("--k", "ks", default="1,5,10", show_default=True, help="Recall@K values reported.")
@click.option("--seed", default=JistTrainSettings.seed, show_default=True, type=int)
@click.option("--device", default="cpu", show_default=True, help="torch device, e.g. cpu or cuda (AMP on CUDA).")
@click.option("--out", "out_dir", default="jist-run", show_default=True, type=click.Path(),
              help="Run folder: best epoch's model (model.safetensors + config.json) and history.csv.")
def train_jist_command(out_dir, **o) -> None:
    """JIST: an image encoder and SeqGeM trained jointly on sequence triplets and CosPlace classification of
    single images, from the traversals' images (best epoch by validation Recall@K)."""
    config, settings = jist_config(o), jist_settings(o)
    data = jist_data(o)
    click.echo(
        f"train: {data.train_reference!r} / {data.train_query!r}\nvalidation: {data.val_reference!r} / "
        f"{data.val_query!r}\npositives within {data.positive_radius:g}, negatives outside {data.negative_radius:g}, "
        f"validation within {data.val_radius:g} ({parse_radius(o['radius']).unit})",
        err=True,
    )
    per_epoch = None if settings.max_iterations is None else settings.refreshes * settings.max_iterations
    result = train_jist(data, config, settings, out_dir, monitor=JistProgress(per_epoch))
    echo_best(result.best_epoch, result.best_recall, result.out_dir)

@click.group()
def ablate() -> None:
    """Run a method's ablation grid and print one row per variant."""


@ablate.command(name="seqmatchnet", epilog="""\b
Example (SeqMatchNet Table 1 on Nordland):
  seqvpr ablate seqmatchnet -r nordland_64x32/summer -q nordland_64x32/winter --train-frames 17:1200 \\
      --val-frames 1200:1600 --test-frames 1600:2000 --radius 1f -L 5 --out runs/ablation-nordland
""")
@training_options
@click.option("--test-frames", required=True, help="Source frames START:STOP of the test split.")
@click.option("--test-reference", help="Test reference (default: --reference).")
@click.option("--test-query", help="Test query (default: --query).")
@click.option("--test-radius", help="Test ground truth (default: --radius), e.g. to test in metres after training in frames.")
@click.option("--out", "out_dir", default="seqmatchnet-ablation", show_default=True, type=click.Path(),
              help="Folder with one run per variant, ablation.csv and ablation.md.")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object instead of the table.")
def ablate_seqmatchnet_command(test_frames, test_reference, test_query, test_radius, out_dir, as_json, **o) -> None:
    """SeqMatchNet Table 1: loss {single, seqmatch} x mining {single, seqmatch}, plus untransformed descriptors."""
    settings = settings_from_options(o)
    data, ref_all, qry_all, config = training_data(o)
    if test_reference or test_query:
        ref_all, qry_all = describe_pair(
            *load_pair(test_reference or o["reference"], test_query or o["query"], o["frames"]), config
        )
    else:
        disjoint(o["train_frames"], test_frames, ("--train-frames", "--test-frames"))
        disjoint(o["val_frames"], test_frames, ("--val-frames", "--test-frames"))
    test_ref, test_qry = split(ref_all, test_frames, "--test-frames"), split(qry_all, test_frames, "--test-frames")
    gt = ground_truth_within_radius(test_qry, test_ref, parse_radius(test_radius or o["radius"]))
    transform = transform_from_options(o, data.dim)
    rows = run_ablation(data, test_ref, test_qry, gt, transform, settings, out_dir,
                        monitor=lambda name: TqdmMonitor(f"{name} "))
    ks = settings.ks
    markdown = ablation_markdown(rows, ks)
    out = Path(out_dir)
    buffer = io.StringIO()
    writer = csv.writer(buffer)
    writer.writerow(["loss", "mining", *[f"R@{k}" for k in ks], "best_epoch", "queries_evaluated"])
    for row in rows:
        writer.writerow([row.loss or "untransformed", row.mining or "", *[f"{row.test.recall[k]:.4f}" for k in ks],
                         "" if row.training is None else row.training.best_epoch, row.test.queries_evaluated])
    with atomic_write(out / "ablation.csv") as handle:
        handle.write(buffer.getvalue())
    with atomic_write(out / "ablation.md") as handle:
        handle.write(markdown + "\n")
    if as_json:
        click.echo(json.dumps([{"loss": r.loss, "mining": r.mining, "recall": {str(k): v for k, v in r.test.recall.items()},
                                "best_epoch": None if r.training is None else r.training.best_epoch} for r in rows]))
        return
    click.echo(f"test: {test_ref!r} / {test_qry!r}, ground truth {gt.description}, L={settings.sequence.length}")
    tables = [recall_table(row.test, row.name, 18).split("\n") for row in rows]
    click.echo("\n".join([tables[0][0], *[table[1] for table in tables], tables[0][2]]))
    click.echo(f"tables: {out / 'ablation.md'}, {out / 'ablation.csv'}")
