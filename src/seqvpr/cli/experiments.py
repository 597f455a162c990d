"""``seqvpr benchmark`` and ``seqvpr demo``: parse, call the experiment runners, print."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import click

from seqvpr.cli.progress import TqdmMonitor, tqdm_progress
from seqvpr.cli.options import (
    DEVICE, ENGINE_OPTION,
    COUNT, NONNEGATIVE, SEED, OUT_FOLDER, locks_output
)
from seqvpr.errors import SeqvprError
from seqvpr.synthetic import CONDITIONS


@click.command(epilog="""\b
Example:
  seqvpr benchmark bench/benchmark.toml --out runs/benchmark
""")
@click.argument("config_file", metavar="CONFIG")
@click.option("--out", "out_dir", default="seqvpr-benchmark", show_default=True, type=OUT_FOLDER,
              help="Folder for trained models, results.csv and results.md.")
@locks_output("out_dir")
def benchmark(config_file, out_dir) -> None:
    """Every method of CONFIG on every dataset's test split: one table like the papers', plus a length table."""
    from seqvpr.experiments.benchmark import read_config, run_benchmark
    from seqvpr.experiments.tables import length_table, main_table, write_results
    from seqvpr.io import check_output_apart

    check_output_apart(out_dir, [config_file], "--out")
    config = read_config(config_file)
    out = Path(out_dir)
    rows = run_benchmark(config, out, progress=tqdm_progress, monitors=lambda kind: TqdmMonitor(f"{kind} "),
                         echo=lambda text: click.echo(text, err=True))
    csv_path, md_path = write_results(rows, config, out)
    click.echo(f"Methods at L={config.seq_len}:\n{main_table(rows, config)}\n")
    click.echo(f"Sequence length (R@{config.ks[0]}):\n{length_table(rows, config)}\n")
    click.echo(f"results: {csv_path}, {md_path}")


@click.command(epilog="""\b
Examples:
  seqvpr demo                      # about 1.5 minutes on 2 cores
  seqvpr demo --quick              # a smaller world, about 35 s
  seqvpr demo --condition winter --seed 3 --out demo-winter
""")
@click.option("--out", "out_dir", default="seqvpr-demo", show_default=True, type=OUT_FOLDER,
              help="Folder for the rendered world, the descriptor cache, the model and the report.")
@click.option("--quick", is_flag=True, help="A smaller world (200 frames per traversal) and a short training run.")
@click.option("--seed", default=0, show_default=True, type=SEED, help="Seed of the world and of training.")
@click.option("--frames", "n_frames", type=COUNT, help="Frames per traversal, 50 to 20000.  [default: 600; --quick: 200]")
@click.option("--condition", type=click.Choice(list(CONDITIONS)), default="night", show_default=True,
              help="The query drive's condition (the reference is driven by day).")
@click.option("--epochs", type=NONNEGATIVE, help="SeqMatchNet training epochs.  [default: 30; --quick: 10]")
@click.option("--no-train", is_flag=True, help="Skip SeqMatchNet training (matching baselines only).")
@click.option("--device", type=DEVICE, default="cpu", show_default=True, help="torch device, e.g. cpu or cuda.")
@ENGINE_OPTION
@locks_output("out_dir")
def demo(out_dir, quick, seed, n_frames, condition, epochs, no_train, device, engine) -> None:
    """Render a synthetic route world, describe it with EfficientNet-Lite0, match single images and sequences,
    train SeqMatchNet, and write an HTML report (OUT/report/index.html)."""
    from seqvpr.experiments.demo import DemoSettings, demo_recall_table, run_demo

    settings = DemoSettings.quick() if quick else DemoSettings()
    changes = {"seed": seed, "condition": condition, "train": not no_train, "device": device, "engine": engine}
    changes.update({k: v for k, v in (("frames", n_frames), ("epochs", epochs)) if v is not None})
    settings = replace(settings, **changes)
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise SeqvprError(f"{out}: --out exists and is not a folder")
    click.echo(f"rendering a {settings.frames}-frame world (seed {seed}; query: {condition}) into {out / 'world'}")
    result = run_demo(out, settings, progress=tqdm_progress, monitor=TqdmMonitor("seqmatchnet "),
                      echo=lambda text: click.echo(text))
    click.echo(f"test route, correct within {settings.radius_m:g} m:")
    click.echo(demo_recall_table(result.runs))
    click.echo(result.loops.text())
    click.echo("seconds: " + ", ".join(f"{stage} {value:.0f}" for stage, value in result.seconds.items()))
    click.echo(f"report: {result.report}")
    world = out / "world"
    click.echo(
        f"the same from the command line: seqvpr match -r {world / 'test_reference'} -q {world / 'test_query'} "
        f"--descriptor efficientnet-lite0 --image-size {settings.width}x{settings.height} --radius "
        f"{settings.radius_m:g}m -L 5 --cache-dir {out / 'cache'}"
    )
