"""``seqvpr train seqmatchnet`` and ``seqvpr ablate seqmatchnet``: thin layers over ``seqvpr.training``."""

from __future__ import annotations

import csv
import io
import json
import sys
from pathlib import Path

import click
from tqdm import tqdm

from seqvpr.cli import describe_pair, load_pair, parse_ks, parse_thumbnail, recall_table
from seqvpr.data.groundtruth import Radius, ground_truth_within_radius, parse_radius
from seqvpr.data.traversal import Traversal
from seqvpr.errors import SeqvprError
from seqvpr.features.patchnorm import PatchNormConfig
from seqvpr.io import atomic_write
from seqvpr.models.seqmatchnet import TransformConfig
from seqvpr.sequences.windows import SequenceSpec
from seqvpr.training.ablation import ablation_markdown, run_ablation
from seqvpr.training.seqmatchnet import EpochRecord, TrainingData, TrainSettings, train_seqmatchnet


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


def training_options(function):
    """Options shared by train and ablate: data, radii, sequence, model and optimisation."""
    options = [
        click.option("--reference", "-r", required=True, help="Training reference traversal (any source seqvpr reads)."),
        click.option("--query", "-q", required=True, help="Training query traversal."),
        click.option("--frames", help="Keep source frames START:STOP of both traversals first (e.g. 17:2000)."),
        click.option("--train-frames", required=True, help="Source frames START:STOP used for training."),
        click.option("--val-frames", required=True, help="Source frames START:STOP used for validation (model selection)."),
        click.option("--val-reference", help="Validation reference (default: --reference)."),
        click.option("--val-query", help="Validation query (default: --query)."),
        click.option("--radius", required=True, help="Ground truth for validation (and test): 25m or 2f."),
        click.option("--pos-radius", help="Positives for training are within this radius (default: --radius)."),
        click.option("--neg-radius", help="Negatives lie outside this radius (default: 4x --pos-radius; a buffer zone)."),
        click.option("--seq-len", "-L", default=5, show_default=True, type=int, help="Frames per sequence window."),
        click.option("--align", type=click.Choice(["centered", "causal"]), default="centered", show_default=True),
        click.option("--boundary", type=click.Choice(["drop", "shift"]), default="drop", show_default=True,
                     help="Windows at segment ends: dropped (training never uses shifted windows) or shifted."),
        click.option("--margin", default=TrainSettings.margin, show_default=True, type=float,
                     help="Triplet margin on sequence distances (default sqrt(0.1), as the reference)."),
        click.option("--negatives", default=10, show_default=True, type=int, help="Hard negatives per query."),
        click.option("--negative-pool", default="1000", show_default=True,
                     help="Random negative candidates per query (plus its previous negatives), or 'all'."),
        click.option("--refresh-every", default=1000, show_default=True, type=int,
                     help="Re-mine with the current model every N queries."),
        click.option("--batch-size", default=16, show_default=True, type=int, help="Queries (triplet groups) per step."),
        click.option("--epochs", default=50, show_default=True, type=int),
        click.option("--optimizer", type=click.Choice(["sgd", "adam"]), default="sgd", show_default=True),
        click.option("--lr", default=1e-3, show_default=True, type=float),
        click.option("--momentum", default=0.9, show_default=True, type=float, help="SGD momentum."),
        click.option("--weight-decay", default=1e-3, show_default=True, type=float),
        click.option("--lr-step", default=5, show_default=True, type=int, help="Epochs between learning-rate steps."),
        click.option("--lr-gamma", default=0.5, show_default=True, type=float, help="Learning-rate factor per step."),
        click.option("--select", "select_k", default=1, show_default=True, type=int,
                     help="Keep the checkpoint with the best validation Recall@K for this K."),
        click.option("--k", "ks", default="1,5,10,20", show_default=True, help="Recall@K values reported."),
        click.option("--out-dim", type=int, help="Output dimension of the transform (default: input dimension)."),
        click.option("--hidden", default="", help="Hidden layer sizes for the deeper MLP variant, e.g. 4096."),
        click.option("--init", type=click.Choice(["reference", "identity"]), default="reference", show_default=True,
                     help="PyTorch default initialisation (as the reference code) or identity W, zero B."),
        click.option("--seed", default=123, show_default=True, type=int),
        click.option("--device", default="cpu", show_default=True),
        click.option("--thumbnail", default="64x32", show_default=True, help="Image folders: patch-normalised thumbnail size."),
        click.option("--patch", default=8, show_default=True, type=int, help="Image folders: patch side."),
    ]
    for option in reversed(options):
        function = option(function)
    return function


def settings_from_options(o: dict) -> TrainSettings:
    pool = o["negative_pool"]
    try:
        pool_size = None if str(pool).lower() == "all" else int(pool)
    except ValueError:
        raise SeqvprError(f"--negative-pool {pool!r}: expected a number or 'all'") from None
    ks = parse_ks(o["ks"])
    return TrainSettings(
        sequence=SequenceSpec(o["seq_len"], o["align"], o["boundary"]),
        margin=o["margin"], negatives=o["negatives"], negative_pool=pool_size, refresh_every=o["refresh_every"],
        batch_size=o["batch_size"], epochs=o["epochs"], optimizer=o["optimizer"], lr=o["lr"],
        momentum=o["momentum"], weight_decay=o["weight_decay"], lr_step=o["lr_step"], lr_gamma=o["lr_gamma"],
        select_k=o["select_k"], ks=ks, seed=o["seed"], device=o["device"],
    )


def transform_from_options(o: dict, dim: int) -> TransformConfig:
    try:
        hidden = tuple(int(h) for h in o["hidden"].split(",") if h.strip())
    except ValueError:
        raise SeqvprError(f"--hidden {o['hidden']!r}: expected comma-separated sizes, e.g. 4096") from None
    return TransformConfig(dim, o["out_dim"], hidden, o["init"])


def radii_from_options(o: dict) -> tuple[Radius, Radius, Radius]:
    """Validation radius, positive radius (default: the validation one), negative radius (default 4x positive)."""
    val = parse_radius(o["radius"])
    pos = parse_radius(o["pos_radius"]) if o["pos_radius"] else val
    neg = parse_radius(o["neg_radius"]) if o["neg_radius"] else Radius(4 * pos.value, pos.unit)
    return val, pos, neg


def split(traversal: Traversal, frames: str, option: str) -> Traversal:
    """The frames START:STOP of a described traversal."""
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


def training_data(o: dict) -> tuple[TrainingData, Traversal, Traversal, PatchNormConfig]:
    """Described train/validation splits; returns the data and the full described traversals."""
    width, height = parse_thumbnail(o["thumbnail"])
    config = PatchNormConfig(width, height, o["patch"])
    ref_all, qry_all = describe_pair(*load_pair(o["reference"], o["query"], o["frames"]), config)
    if o["val_reference"] or o["val_query"]:
        val_ref_all, val_qry_all = describe_pair(
            *load_pair(o["val_reference"] or o["reference"], o["val_query"] or o["query"], o["frames"]), config
        )
    else:
        disjoint(o["train_frames"], o["val_frames"], ("--train-frames", "--val-frames"))
        val_ref_all, val_qry_all = ref_all, qry_all
    val, pos, neg = radii_from_options(o)
    data = TrainingData(
        split(ref_all, o["train_frames"], "--train-frames"), split(qry_all, o["train_frames"], "--train-frames"),
        split(val_ref_all, o["val_frames"], "--val-frames"), split(val_qry_all, o["val_frames"], "--val-frames"),
        pos, neg, val,
    )
    return data, ref_all, qry_all, config


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
    best = " ".join(f"R@{k} {v:.3f}" for k, v in sorted(result.best_recall.items()))
    click.echo(f"best epoch {result.best_epoch}: validation {best}\nmodel: {result.folder} "
               f"(apply with: seqvpr match --model {result.folder} ...)")


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
