"""``seqvpr extract``: describe a traversal's images (a descriptor, an encoder file or a model's frame encoder) and
save a traversal file. Parse, call the library, print."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from seqvpr.cli.options import (
    DEVICE, OUT_FILE, bag_topic_options, extraction_options, extraction_settings, given_image_size, locks_output,
)
from seqvpr.cli.progress import tqdm_progress
from seqvpr.errors import SeqvprError


@click.command(epilog="""\b
Examples:
  seqvpr extract images/ --out ref.npz
  seqvpr extract images/ --descriptor resnet50 --weights cosplace_r50.pth --image-size 512x384 --out ref.npz
  seqvpr extract images/ --descriptor torchscript:megaloc.pt --image-size 322x322 --out ref.npz
  seqvpr match --reference ref.npz --query qry.npz --radius 25m -L 5
""")
@click.argument("images")
@extraction_options
@click.option("--cluster-images", help="netvlad: traversal whose images initialise the clusters  [default: IMAGES]; "
              "extract the query with the reference's images here so both share one NetVLAD head.")
@click.option("--role", type=click.Choice(["reference", "query"]), default="reference", show_default=True,
              help="Which side of a dbStruct or description file to read.")
@click.option("--device", type=DEVICE, default="cpu", show_default=True, help="torch device, e.g. cpu or cuda.")
@click.option("--out", "out_file", required=True, type=OUT_FILE,
              help="Traversal file (.npz: descriptors, positions, segments, frame_index) for seqvpr match.")
@click.option("--model", "model_dirs", multiple=True, type=click.Path(),
              help="A model folder that describes images (JIST: its frame encoder; CosPlace): its frame descriptors, "
                   "at its image size unless --image-size is given.")
@bag_topic_options("images", "cluster_images")
@locks_output("out_file")
def extract(images, cluster_images, role, device, out_file, model_dirs, **options: Any) -> None:
    """Describe the images of a traversal (image folder, @UTM folder, dbStruct...) and save a traversal file."""
    descriptor, patchnorm, extraction = extraction_settings(options, device)
    from seqvpr.data.sources import load_traversal, save_traversal_npz
    from seqvpr.features.describe import describe, dropped_frames, netvlad_extractor
    from seqvpr.io import check_output_apart

    check_output_apart(out_file, [images, cluster_images, options["cache_dir"]], "--out")

    traversal = load_traversal(images, role)
    if traversal.image_paths is None:
        raise SeqvprError(f"{images}: holds descriptors, not images; nothing to extract")
    if descriptor != "patchnorm" and options["pooling"] == "netvlad":
        source = load_traversal(cluster_images, "reference") if cluster_images else traversal
        if source.image_paths is None:
            raise SeqvprError(f"{cluster_images}: --cluster-images must be a traversal of images")
        extraction["model"] = netvlad_extractor(extraction["extractor"], source.image_paths, device, tqdm_progress)
    if model_dirs:
        described = _model_frames(traversal, model_dirs, options, device)
        descriptor = f"model {model_dirs[0]}"
    else:
        described = describe(traversal, descriptor, patchnorm, tqdm_progress, **extraction)
    skipped = dropped_frames(traversal, described)
    if skipped:
        click.echo(f"skipped {len(skipped)} unreadable images: {', '.join(skipped)}", err=True)
    save_traversal_npz(Path(out_file), described)
    click.echo(f"{out_file}: {len(described)} frames, {described.descriptors.shape[1]}-D {descriptor} descriptors")


def _model_frames(traversal, model_dirs: tuple[str, ...], options: dict[str, Any], device: str):
    """``extract --model``: the frame descriptors of the one model folder given, which must describe images."""
    from seqvpr.methods import image_model
    from seqvpr.models.jist import describe_images
    from seqvpr.models.registry import load_models

    models = load_models(model_dirs, device)
    model = image_model(models)
    if model is None or len(models) != 1:
        raise SeqvprError(f"--model {', '.join(model_dirs)}: give one model that describes images (JIST or CosPlace)")
    width, height = given_image_size(options) or model.image_size
    return describe_images(model.module, traversal, width, height, device, engine=options["engine"])
