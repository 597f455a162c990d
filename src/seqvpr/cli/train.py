"""``seqvpr train seqmatchnet|seqnet|jist`` and ``seqvpr ablate seqmatchnet``: parse, call the library, print.
Option defaults are the settings dataclasses' (``training.settings``, ``models.configs``), read without torch."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import click

from seqvpr.cli.options import (
    DEVICE, ENGINE_CHOICE,
    COUNT, FRACTION, NONNEGATIVE, NONNEGATIVE_FLOAT, Number, POSITIVE, SEED, parse_ks, parse_stages,
    parse_thumbnail, with_options, OUT_FOLDER, bag_topic_options, locks_output
)
from seqvpr.cli.progress import TqdmMonitor, tqdm_progress
from seqvpr.errors import SeqvprError
from seqvpr.models.configs import JIST_BACKBONES, JIST_BRANCHES, JistConfig
from seqvpr.training.settings import (
    NEGATIVE_RADIUS_FACTOR, THUMBNAIL_RECIPE, THUMBNAIL_SIDE, CellGrouping, JistTrainSettings, SeqMatchNetSettings,
    SeqNetSettings,
)


def data_options(kind: str) -> list[Callable]:
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
        click.option("--neg-radius", help=f"Negatives lie outside this radius (default: {NEGATIVE_RADIUS_FACTOR[kind]:g}x "
                                          "--pos-radius; a buffer zone)."),
    ]


SELECT_UNTRAINED = click.option(
    "--select-untrained", is_flag=True,
    help="Let the untrained model (epoch 0) be the one kept when it validates best.  [default: trained epochs only]")


def sequence_training_options(kind: str, defaults: SeqMatchNetSettings | SeqNetSettings, model_options: list[Callable]):
    """The options of a model trained on frame descriptors (data, sequence, mining, optimisation, patchnorm), with
    the defaults of its settings class, plus ``model_options`` (its own) before --seed."""
    pool = "all" if defaults.negative_pool is None else str(defaults.negative_pool)
    per_epoch = defaults.refresh_every is None
    return with_options([
        *data_options(kind),
        click.option("--seq-len", "-L", default=defaults.sequence.length, show_default=True, type=COUNT,
                     help="Frames per sequence window."),
        click.option("--align", type=click.Choice(["centered", "causal"]), default="centered", show_default=True),
        click.option("--boundary", type=click.Choice(["drop", "shift"]), default="drop", show_default=True,
                     help="Windows at segment ends: dropped (training never uses shifted windows) or shifted."),
        click.option("--margin", default=defaults.margin, show_default=True, type=POSITIVE,
                     help="Triplet margin on sequence distances (default sqrt(0.1), as the reference)."),
        click.option("--negatives", default=defaults.negatives, show_default=True, type=COUNT,
                     help="Hard negatives per query (at most 1000)."),
        click.option("--negative-pool", default=pool, show_default=True,
                     help="Random negative candidates per query (plus its previous negatives), or 'all'."),
        click.option("--refresh-every", default=defaults.refresh_every, show_default=not per_epoch, type=COUNT,
                     help="Re-mine with the current model every N queries." + per_epoch * "  [default: once per epoch]"),
        click.option("--batch-size", default=defaults.batch_size, show_default=True, type=COUNT,
                     help="Queries (triplet groups) per step."),
        click.option("--epochs", default=defaults.epochs, show_default=True, type=NONNEGATIVE),
        click.option("--optimizer", type=click.Choice(["sgd", "adam"]), default=defaults.optimizer, show_default=True),
        click.option("--lr", default=defaults.lr, show_default=True, type=POSITIVE),
        click.option("--momentum", default=defaults.momentum, show_default=True, type=Number(float, 0, 0.999), help="SGD momentum."),
        click.option("--weight-decay", default=defaults.weight_decay, show_default=True, type=NONNEGATIVE_FLOAT),
        click.option("--lr-step", default=defaults.lr_step, show_default=True, type=COUNT,
                     help="Epochs between learning-rate steps."),
        click.option("--lr-gamma", default=defaults.lr_gamma, show_default=True, type=POSITIVE,
                     help="Learning-rate factor per step."),
        click.option("--select", "select_k", default=defaults.select_k, show_default=True, type=COUNT,
                     help="Keep the checkpoint with the best validation Recall@K for this K."),
        click.option("--k", "ks", default=",".join(map(str, defaults.ks)), show_default=True,
                     help="Recall@K values reported."),
        SELECT_UNTRAINED,
        *model_options,
        click.option("--seed", default=defaults.seed, show_default=True, type=SEED),
        click.option("--device", type=DEVICE, default="cpu", show_default=True),
        click.option("--thumbnail", default="64x32", show_default=True, help="Image folders: patch-normalised thumbnail size."),
        click.option("--patch", default=8, show_default=True, type=COUNT, help="Image folders: patch side."),
    ])


training_options = sequence_training_options("seqmatchnet", SeqMatchNetSettings(), [
    click.option("--out-dim", type=COUNT, help="Output dimension of the transform, at most 65536 (default: input dimension)."),
    click.option("--hidden", default="", help="Hidden layer sizes for the deeper MLP variant, e.g. 4096."),
    click.option("--init", type=click.Choice(["reference", "identity"]), default="reference", show_default=True,
                 help="PyTorch default initialisation (as the reference code) or identity W, zero B."),
])

seqnet_options = sequence_training_options("seqnet", SeqNetSettings(), [
    click.option("--w", "w", default=SeqNetSettings.w, show_default=True, type=COUNT,
                 help="Temporal kernel width of SeqNet's Conv1d (at most -L)."),
    click.option("--out-dim", type=COUNT, help="Output dimension of the sequence descriptor, at most 65536 (default: input dimension)."),
])

run_options = with_options([
    click.option("--resume", is_flag=True, help="Continue the run in --out from its last finished epoch."),
])


def settings_from_options(options: dict, kind: type = SeqMatchNetSettings, **model_fields: Any):
    """The settings object of ``kind`` (SeqMatchNetSettings or SeqNetSettings) the shared options describe."""
    from seqvpr.sequences.windows import SequenceSpec

    pool = options["negative_pool"]
    try:
        pool_size = None if str(pool).lower() == "all" else int(pool)
    except ValueError:
        raise SeqvprError(f"--negative-pool {pool!r}: expected a number or 'all'") from None
    return kind(
        sequence=SequenceSpec(options["seq_len"], options["align"], options["boundary"]),
        margin=options["margin"], negatives=options["negatives"], negative_pool=pool_size, refresh_every=options["refresh_every"],
        batch_size=options["batch_size"], epochs=options["epochs"], optimizer=options["optimizer"], lr=options["lr"],
        momentum=options["momentum"], weight_decay=options["weight_decay"], lr_step=options["lr_step"], lr_gamma=options["lr_gamma"],
        select_k=options["select_k"], ks=parse_ks(options["ks"]), select_untrained=options["select_untrained"], seed=options["seed"],
        device=options["device"], **model_fields,
    )


def transform_from_options(options: dict, dim: int):
    from seqvpr.models.configs import TransformConfig

    try:
        hidden = tuple(int(h) for h in options["hidden"].split(",") if h.strip())
    except ValueError:
        raise SeqvprError(f"--hidden {options['hidden']!r}: expected comma-separated sizes, e.g. 4096") from None
    return TransformConfig(dim, options["out_dim"], hidden, options["init"])


def described_data(kind: str, options: dict):
    """The training data of the options, images described as patch-normalised thumbnails; with the whole described
    training pair and the patchnorm config (for the ablation's test split)."""
    from seqvpr.data.ground_truth import parse_radius
    from seqvpr.features.patchnorm import PatchNormConfig
    from seqvpr.features.describe import describe_pair
    from seqvpr.training.data import training_data, training_pairs

    width, height = parse_thumbnail(options["thumbnail"])
    config = PatchNormConfig(width, height, options["patch"])
    prepare = lambda r, q: describe_pair(r, q, "patchnorm", config, tqdm_progress)  # noqa: E731
    train, validation, whole = training_pairs(
        options["reference"], options["query"], options["train_frames"], options["val_frames"], prepare, frames=options["frames"],
        val_reference=options["val_reference"], val_query=options["val_query"],
    )
    radii = [parse_radius(options[key]) if options[key] else None for key in ("radius", "pos_radius", "neg_radius")]
    return training_data(kind, train, validation, *radii), whole, config


def echo_best(best_epoch: int, best_recall: dict[int, float], folder: Path | str) -> None:
    """The closing lines of a training command: the best epoch's validation recall and the model folder (rank 0
    alone says them under torchrun)."""
    from seqvpr.distributed import from_environment

    if not from_environment().is_root:
        return
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
@click.option("--out", "out_dir", default="seqmatchnet-run", show_default=True, type=OUT_FOLDER,
              help="Run folder: best model (model.safetensors + config.json), history.csv, resumable state.")
@run_options
@bag_topic_options("reference", "query", "val_reference", "val_query")
@locks_output("out_dir")
def train_seqmatchnet_command(out_dir, resume, **options) -> None:
    """SeqMatchNet: a per-frame transform trained with a sequence-matching triplet loss and sequence mining."""
    from seqvpr.training.seqmatchnet import train_seqmatchnet

    settings = settings_from_options(options)
    data, _, _ = described_data("seqmatchnet", options)
    result = train_seqmatchnet(data, transform_from_options(options, data.dim), settings, out_dir, resume=resume,
                               monitor=TqdmMonitor())
    echo_best(result.best_epoch, result.best_recall, result.folder)


@train.command(name="seqnet", epilog="""\b
Example (Nordland, summer reference, winter query, +-1 frame, L=5, w=3):
  seqvpr train seqnet -r nordland_64x32/summer -q nordland_64x32/winter \\
      --train-frames 17:1200 --val-frames 1200:1600 --radius 1f --out runs/seqnet-nordland
  seqvpr match -r nordland_64x32/summer -q nordland_64x32/winter --frames 1600:2000 \\
      --radius 1f --model runs/seqnet-nordland --rerank 20
""")
@seqnet_options
@click.option("--out", "out_dir", default="seqnet-run", show_default=True, type=OUT_FOLDER,
              help="Run folder: best model (model.safetensors + config.json), history.csv, resumable state.")
@run_options
@bag_topic_options("reference", "query", "val_reference", "val_query")
@locks_output("out_dir")
def train_seqnet_command(out_dir, resume, w, out_dim, **options) -> None:
    """SeqNet: a temporal Conv1d over each window of frame descriptors, one descriptor per sequence, trained with a
    triplet loss and hard negatives mined in its own descriptor space (velocity 1)."""
    from seqvpr.training.seqnet import train_seqnet

    settings = settings_from_options(options, SeqNetSettings, w=w, out_dim=out_dim)
    data, _, _ = described_data("seqnet", options)
    result = train_seqnet(data, settings, out_dir, resume=resume, monitor=TqdmMonitor())
    echo_best(result.best_epoch, result.best_recall, result.folder)


JIST_DEFAULTS, JIST_RUN = JistConfig(), JistTrainSettings()


def _both(key: str, defaults: Any = JIST_RUN) -> str:
    """A help text's default: the reference's value and the thumbnail recipe's."""
    return f"[default: {getattr(defaults, key):g}; thumbnails: {THUMBNAIL_RECIPE[key]:g}]"


jist_options = with_options([
    *data_options("jist"),
    click.option("--backbone", type=click.Choice(list(JIST_BACKBONES)),
                 help=f"Frame encoder.  [default: {JIST_DEFAULTS.backbone}; thumbnails (frames of at most "
                      f"{THUMBNAIL_SIDE} px a side, e.g. Nordland's 64x32): thumbnail-cnn, a small CNN over "
                      "patch-normalised grey frames trained from scratch, with its own recipe (the values after "
                      "'thumbnails:' below)]"),
    click.option("--weights", help="Backbone weights: a checkpoint path (torchvision or CosPlace keys), or 'imagenet' "
                 "(efficientnet-lite0's packaged weights).  [default: random initialisation]"),
    click.option("--trainable-stages", help="Comma list of backbone stages to train (ResNet: stem, layer1..layer4; "
                 "efficientnet-lite0: stem, stage1..stage7, head).  [default: the backbone's last stage: layer4; "
                 "efficientnet-lite0: stage7,head; thumbnail-cnn: all of stage1,stage2,stage3,head]"),
    click.option("--out-dim", type=COUNT, help=f"Frame descriptor size (at most 65536).  {_both('out_dim', JIST_DEFAULTS)}"),
    click.option("--seq-len", "-L", default=JIST_DEFAULTS.seq_length, show_default=True, type=COUNT,
                 help="Frames per sequence window."),
    click.option("--epochs", type=NONNEGATIVE, help=_both("epochs")),
    click.option("--refreshes", type=COUNT, help=f"Triplet mining refreshes per epoch.  {_both('refreshes')}"),
    click.option("--max-iterations", type=COUNT, help="Most iterations per refresh.  [default: every mined batch; "
                 f"thumbnails: {THUMBNAIL_RECIPE['max_iterations']}]"),
    click.option("--batch-size", type=COUNT, help=f"Sequence triplets per iteration.  {_both('batch_size')}"),
    click.option("--images-per-batch", type=COUNT,
                 help=f"Single images per iteration for the CosPlace classification branch.  {_both('images_per_batch')}"),
    click.option("--image-size", help="Image size WIDTHxHEIGHT for training and for seqvpr match --model.  "
                 f"[default: {JIST_RUN.width}x{JIST_RUN.height}; thumbnails: their own size]"),
    click.option("--class-images", "class_images", multiple=True, metavar="SOURCE",
                 help="Another traversal of the training route (another condition; frame-aligned, or with positions) "
                      "whose --train-frames images join the CosPlace classification branch. Repeatable.  "
                      "[default: the training reference and query only]"),
    click.option("--cell-size", type=POSITIVE, help="CosPlace class cells, in the radius unit (metres, or frames "
                 f"with a frame radius).  [default: {CellGrouping.cell_m:g}; thumbnails: {THUMBNAIL_RECIPE['cell_m']:g}]"),
    click.option("--min-images", type=COUNT, help="Images a CosPlace class needs to be used.  "
                 f"[default: {CellGrouping.min_images}; thumbnails: {THUMBNAIL_RECIPE['min_images']}]"),
    click.option("--seqgem-normalize/--no-seqgem-normalize", default=JIST_DEFAULTS.seqgem_normalize, show_default=True,
                 help="L2-normalise SeqGeM's sequence descriptor (--no-seqgem-normalize: upstream JIST's forward)."),
    click.option("--lr", type=POSITIVE, help=f"Adam learning rate of the model.  {_both('lr', JIST_DEFAULTS)}"),
    click.option("--classifier-lr", default=JIST_DEFAULTS.classifier_lr, show_default=True, type=POSITIVE,
                 help="Adam learning rate of the CosFace classifiers."),
    click.option("--select", "select_k", default=JIST_RUN.select_k, show_default=True, type=COUNT,
                 help="Keep the epoch with the best validation Recall@K for this K (one of --k)."),
    click.option("--k", "ks", default=",".join(map(str, JIST_RUN.ks)), show_default=True, help="Recall@K values reported."),
    SELECT_UNTRAINED,
    click.option("--jitter", type=NONNEGATIVE_FLOAT,
                 help=f"Classification images: brightness, contrast and saturation factors in [1 - J, 1 + J].  {_both('jitter')}"),
    click.option("--hue", type=Number(float, 0, 0.5),
                 help=f"Classification images: hue turned by up to this fraction of a turn.  {_both('hue')}"),
    click.option("--crop-scale", type=FRACTION,
                 help=f"Classification images: random crops keep this share of the area or more (1: no crop).  {_both('crop_scale')}"),
    click.option("--branches", type=click.Choice(list(JIST_BRANCHES)), default=JIST_DEFAULTS.branches,
                 show_default=True, help="What the loss trains: both branches (the paper's), the sequence triplets "
                 "alone, or the CosPlace classification of single images alone."),
    click.option("--seed", default=JIST_RUN.seed, show_default=True, type=SEED),
    click.option("--device", type=DEVICE, default=JIST_RUN.device, show_default=True, help="torch device, e.g. cpu or cuda (AMP on CUDA)."),
    click.option("--engine", type=ENGINE_CHOICE, default=JIST_RUN.engine, show_default=True,
                 help="How validation describes frames: torch, or ONNX Runtime over an export made each epoch "
                      "(auto: on the CPU; not kept in the cache)."),
])


def jist_values(options: dict) -> dict[str, Any]:
    """The JIST options as the flat table ``training.jist.jist_setup`` takes (the benchmark's ``[jist]`` table);
    None where an option was not given (``training.settings.with_recipe`` fills it)."""
    width, height = parse_thumbnail(options["image_size"], "--image-size") if options["image_size"] else (None, None)
    return {
        "backbone": options["backbone"], "weights": options["weights"], "out_dim": options["out_dim"],
        "trainable_stages": parse_stages(options["trainable_stages"]), "seq_length": options["seq_len"], "lr": options["lr"],
        "classifier_lr": options["classifier_lr"], "epochs": options["epochs"], "refreshes": options["refreshes"],
        "max_iterations": options["max_iterations"], "batch_size": options["batch_size"],
        "images_per_batch": options["images_per_batch"], "width": width, "height": height, "cell_m": options["cell_size"],
        "min_images": options["min_images"], "select_k": options["select_k"], "ks": parse_ks(options["ks"]), "device": options["device"],
        "seed": options["seed"], "select_untrained": options["select_untrained"], "jitter": options["jitter"], "hue": options["hue"],
        "crop_scale": options["crop_scale"], "seqgem_normalize": options["seqgem_normalize"], "branches": options["branches"],
        "engine": options["engine"],
    }


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
@jist_options
@click.option("--out", "out_dir", default="jist-run", show_default=True, type=OUT_FOLDER,
              help="Run folder: best model (model.safetensors + config.json), history.csv, resumable state.")
@run_options
@bag_topic_options("reference", "query", "val_reference", "val_query", "class_images")
@locks_output("out_dir")
def train_jist_command(out_dir, resume, **options) -> None:
    """JIST: an image encoder and SeqGeM trained jointly on sequence triplets and CosPlace classification of
    single images, from the traversals' images (best epoch by validation Recall@K)."""
    from seqvpr.data.ground_truth import parse_radius
    from seqvpr.training.data import classification_traversals, training_data, training_pairs
    from seqvpr.training.jist import frame_size, jist_setup, train_jist
    from seqvpr.training.settings import with_recipe

    train_pair, validation, _ = training_pairs(
        options["reference"], options["query"], options["train_frames"], options["val_frames"], lambda r, q: (r,
                                                                                                              q), frames=options["frames"],
        val_reference=options["val_reference"], val_query=options["val_query"],
    )
    radii = [parse_radius(options[key]) if options[key] else None for key in ("radius", "pos_radius", "neg_radius")]
    values = with_recipe(jist_values(options), frame_size(train_pair[0]))
    config, settings = jist_setup(values)
    data = training_data("jist", train_pair, validation, *radii)
    classification = classification_traversals(data, options["class_images"], options["train_frames"],
                                               options["frames"])
    result = train_jist(data, config, settings, out_dir, resume=resume, monitor=TqdmMonitor(),
                        classification=classification)
    echo_best(result.best_epoch, result.best_recall, result.folder)
    click.echo(f"recipe: {values['recipe']} ({config.backbone} at {settings.width}x{settings.height}, lr {config.lr:g}, "
               f"{settings.epochs} epochs, branches {config.branches})")


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
@click.option("--out", "out_dir", default="seqmatchnet-ablation", show_default=True, type=OUT_FOLDER,
              help="Folder with one run per variant, ablation.csv and ablation.md.")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object instead of the table.")
@bag_topic_options("reference", "query", "val_reference", "val_query", "test_reference", "test_query")
def ablate_seqmatchnet_command(test_frames, test_reference, test_query, test_radius, out_dir, as_json, **options) -> None:
    """SeqMatchNet Table 1: loss {single, seqmatch} x mining {single, seqmatch}, plus untransformed descriptors."""
    from seqvpr.data.ground_truth import ground_truth_within_radius, parse_radius
    from seqvpr.evaluation.summary import recall_rows
    from seqvpr.experiments.ablation import ablation_json, run_ablation, write_ablation

    settings = settings_from_options(options)
    data, whole, config = described_data("seqmatchnet", options)
    test_ref, test_qry = _test_split(options, whole, config, test_frames, test_reference, test_query)
    gt = ground_truth_within_radius(test_qry, test_ref, parse_radius(test_radius or options["radius"]))
    rows = run_ablation(data, test_ref, test_qry, gt, transform_from_options(options, data.dim), settings, out_dir,
                        monitor=lambda name: TqdmMonitor(f"{name} "))
    csv_path, md_path = write_ablation(rows, settings.ks, out_dir)
    if as_json:
        click.echo(json.dumps(ablation_json(rows)))
        return
    click.echo(f"test: {test_ref!r} / {test_qry!r}, ground truth {gt.description}, L={settings.sequence.length}")
    click.echo(recall_rows([(row.name, row.test) for row in rows], 18))
    click.echo(f"tables: {md_path}, {csv_path}")


def _test_split(options: dict, whole, config, test_frames: str, test_reference: str | None, test_query: str | None):
    """The ablation's test pair: from its own sources, or a split of the training traversals disjoint from the
    training and validation frames."""
    from seqvpr.data.sources import load_pair
    from seqvpr.data.traversal import check_disjoint, slice_frame_range
    from seqvpr.features.describe import describe_pair

    if test_reference or test_query:
        pair = load_pair(test_reference or options["reference"], test_query or options["query"], options["frames"])
        whole = describe_pair(*pair, "patchnorm", config, tqdm_progress)
    else:
        check_disjoint(options["train_frames"], test_frames, ("--train-frames", "--test-frames"))
        check_disjoint(options["val_frames"], test_frames, ("--val-frames", "--test-frames"))
    return tuple(slice_frame_range(t, test_frames, "--test-frames") for t in whole)


@ablate.command(name="jist", epilog="""\b
The split (Nordland, the dataset's own): train on frames 17-1199, select the epoch on 1200-1599, test on 1600-1999:
  seqvpr ablate jist -r nordland_64x32/summer -q nordland_64x32/winter --train-frames 17:1200 \\
      --val-frames 1200:1600 --test-frames 1600:2000 --radius 1f --out runs/jist-ablation-nordland
The three frame ranges must not overlap. Rows: JIST joint, sequence branch alone, image branch alone, untrained
SeqGeM over the same starting encoder, SeqNet trained on the split (patch-normalised frames), sequence matching;
then the joint model at L = 3, 5, 10 and with each test window's frames reversed and shuffled.
""")
@jist_options
@click.option("--test-frames", required=True, help="Source frames START:STOP of the test split (disjoint from the others).")
@click.option("--variants", default=",".join(JIST_BRANCHES), show_default=True,
              help="The JIST rows to train (comma list of joint, sequence, images); each sets its own --branches.")
@click.option("--out", "out_dir", default="jist-ablation", show_default=True, type=OUT_FOLDER,
              help="Folder with one run per variant, the starting model, SeqNet's run, ablation.csv and ablation.md.")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object instead of the tables.")
@bag_topic_options("reference", "query", "val_reference", "val_query", "class_images")
def ablate_jist_command(test_frames, variants, out_dir, as_json, **options) -> None:
    """JIST's ablation: joint training against each branch alone, untrained SeqGeM, SeqNet and sequence matching on
    one split and budget, and the joint model's robustness to the window's length and frame order."""
    from seqvpr.data.ground_truth import parse_radius
    from seqvpr.data.traversal import check_disjoint, slice_frame_range
    from seqvpr.experiments.jist_ablation import (
        JistSplit, ablation_markdown, robustness_markdown, robustness_rows, run_jist_ablation, write_jist_ablation,
    )
    from seqvpr.training.data import classification_traversals, training_data, training_pairs
    from seqvpr.training.jist import frame_size
    from seqvpr.training.settings import with_recipe

    for other, name in ((options["train_frames"], "--train-frames"), (options["val_frames"], "--val-frames")):
        check_disjoint(other, test_frames, (name, "--test-frames"))
    train, select, whole = training_pairs(
        options["reference"], options["query"], options["train_frames"], options["val_frames"], lambda r, q: (r,
                                                                                                              q), frames=options["frames"],
        val_reference=options["val_reference"], val_query=options["val_query"],
    )
    test = tuple(slice_frame_range(t, test_frames, "--test-frames") for t in whole)
    radius = parse_radius(options["radius"])
    values = with_recipe(jist_values(options), frame_size(train[0]))
    classification = classification_traversals(training_data("jist", train, select, radius), options["class_images"],
                                               options["train_frames"], options["frames"])
    split = JistSplit(train, select, test, radius)  # type: ignore[arg-type]
    chosen = [v.strip() for v in variants.split(",") if v.strip()]
    rows = run_jist_ablation(split, values, out_dir, classification=classification, variants=chosen,
                             monitor=lambda name: TqdmMonitor(f"{name} "))
    robustness = robustness_rows(Path(out_dir) / "joint", split) if "joint" in chosen else []
    csv_path, md_path = write_jist_ablation(rows, robustness, out_dir)
    if as_json:
        click.echo(json.dumps({"rows": [{"row": r.name, "recall": {str(k): v for k, v in r.test.recall.items()},
                                         "best_epoch": r.best_epoch} for r in rows],
                               "robustness": [{"windows": c, **{n: e.recall[1] for n, e in s.items()}}
                                              for c, s in robustness]}))
        return
    click.echo(f"recipe: {values['recipe']}; test frames {test_frames}, radius {radius}, L={options['seq_len']}")
    click.echo(ablation_markdown(rows))
    if robustness:
        click.echo("\n" + robustness_markdown(robustness))
    click.echo(f"tables: {md_path}, {csv_path}")
