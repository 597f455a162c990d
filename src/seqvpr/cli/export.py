"""``seqvpr export``: an encoder seqvpr runs, written as ONNX, TorchScript or ``torch.export``. Parse, call the
library, print.

Same name as ``seqvpr.models.export``: writing and checking the file."""

from __future__ import annotations

import click

from seqvpr.cli.options import OUT_FILE, locks_output, parse_thumbnail


@click.command(epilog="""\b
Examples:
  seqvpr export efficientnet-lite0 --image-size 320x240 --out lite0.onnx
  seqvpr export runs/jist --out jist-frames.onnx
  seqvpr export resnet50 --weights cosplace_r50.pth --format torchscript --out r50.pt
  seqvpr match -r day/ -q night/ --descriptor onnx:lite0.onnx --radius 25m -L 5
""")
@click.argument("encoder", metavar="MODEL_OR_DESCRIPTOR")
@click.option("--format", "file_format", type=click.Choice(["onnx", "torchscript", "export"]), default="onnx",
              show_default=True, help="onnx (ONNX Runtime, TensorRT...), torchscript, or export (torch.export .pt2).")
@click.option("--image-size", help="Input WIDTHxHEIGHT.  [default: 320x240 for a backbone, a model's own size]")
@click.option("--pooling", type=click.Choice(["gem"]), default="gem", show_default=True,
              help="A backbone's pooling head.")
@click.option("--weights", default="imagenet", show_default=True,
              help="A backbone's weights: 'imagenet' or a checkpoint path.")
@click.option("--out", "out_file", required=True, type=OUT_FILE, help="The file to write.")
@locks_output("out_file")
def export(encoder, file_format, image_size, pooling, weights, out_file) -> None:
    """Write MODEL_OR_DESCRIPTOR's frame encoder (a backbone by name, or a JIST or CosPlace model folder) as a file
    that takes float [batch, 3, H, W] RGB pixels in [0, 1] and returns [batch, dim] descriptors, checked against
    torch before it is kept. Read it back with --descriptor onnx:FILE (or torchscript:FILE with --normalize none)."""
    from seqvpr.models.export import export_encoder

    size = parse_thumbnail(image_size, "--image-size") if image_size else None
    written = export_encoder(encoder, out_file, file_format, size, pooling, weights)
    click.echo(f"{written.path}: {written.format}, [batch, 3, {written.height}, {written.width}] RGB in [0, 1] -> "
               f"[batch, {written.dim}] (max difference from torch {written.difference:.1e})")
