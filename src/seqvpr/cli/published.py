"""``seqvpr import``: a published checkpoint into a seqvpr model folder. Parse, call the library, print.

Same name as ``seqvpr.models.published``: the import command; reading the checkpoints there."""

from __future__ import annotations

import click

from seqvpr.cli.options import OUT_FOLDER, locks_output


@click.command(name="import", epilog="""\b
Examples:
  seqvpr import seqnet_l10_w5/checkpoints/model_best.pth.tar --flags seqnet_l10_w5/flags.json --out runs/seqnet-l10
  seqvpr import seqmatchnet/model_best.pth.tar --flags seqmatchnet/flags.json --out runs/smn
  seqvpr import JIST_r18_512_seqgem.pth --out runs/jist-r18
  seqvpr import resnet18_512_cosplace.pth --out runs/cosplace-r18
  seqvpr match -r ref.npz -q qry.npz --radius 25m --model runs/seqnet-l10
""")
@click.argument("checkpoint", type=click.Path())
@click.option("--flags", "flags_file", type=click.Path(), help="The run's flags.json (SeqNet/SeqMatchNet: seqL, w, outDims; JIST: seq_length), if you have it.")
@click.option("--out", "out_dir", required=True, type=OUT_FOLDER, help="The seqvpr model folder to write.")
@locks_output("out_dir")
def import_command(checkpoint, flags_file, out_dir) -> None:
    """Convert a published SeqNet, SeqMatchNet, CosPlace or JIST checkpoint into a model folder for seqvpr match
    --model (strictly: a missing or unexpected key is an error)."""
    from seqvpr.models.published import import_checkpoint

    imported = import_checkpoint(checkpoint, out_dir, flags_file)
    click.echo(f"{imported.kind} model: {imported.folder} (source sha256 {imported.sha256[:16]}...; "
               f"apply with: seqvpr match --model {imported.folder} ...)")
