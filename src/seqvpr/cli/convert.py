"""``seqvpr convert``: any source seqvpr reads into the files the upstream research code reads (a seqNet /
SeqMatchNet ``.db`` struct with per-side descriptors and seqBounds files, tied by a ``dataset.toml``) or into a
traversal ``.npz``."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from seqvpr.cli.options import OUT_FILE, bag_topic_options, locks_output
from seqvpr.errors import SeqvprError


@click.command("convert", epilog="""\b
Examples:
  seqvpr convert -r day/ -q night/ --frames 0:200 --radius 2f --to dbstruct --out gp/gardens.db
  seqvpr convert -r run1.bag -q run2.bag --radius 25m --to dbstruct --out city/city.db
  seqvpr convert -r dataset.toml --role query --to npz --out query.npz""")
@click.option("-r", "--reference", required=True, type=click.Path(), help="Reference source (or the one source, npz).")
@click.option("-q", "--query", type=click.Path(), help="Query source (dbstruct).")
@click.option("--role", type=click.Choice(["reference", "query"]), default="reference", show_default=True,
              help="npz: which side of a two-sided source (a .db or dataset.toml) to write.")
@click.option("--frames", help="Keep source frames START:STOP.")
@click.option("--radius", help="dbstruct: posDistThr, e.g. 25m (positions) or 2f (frame-aligned).")
@click.option("--to", "target", type=click.Choice(["dbstruct", "npz"]), required=True)
@click.option("--out", "out_file", required=True, type=OUT_FILE, help="The .db (its siblings beside it) or .npz.")
@bag_topic_options("reference", "query")
@locks_output("out_file")
def convert(**options: Any) -> None:
    """Write SOURCE(s) as a .db struct + descriptors + seqBounds + dataset.toml, or as a traversal .npz."""
    from seqvpr.data.sources import load_traversal, save_traversal_npz
    from seqvpr.data.traversal import slice_frame_range
    from seqvpr.io import check_output_apart

    check_output_apart(options["out_file"], [options["reference"], options["query"]], "--out")

    if options["target"] == "npz":
        traversal = slice_frame_range(load_traversal(options["reference"], options["role"]), options["frames"])
        if traversal.descriptors is None:
            raise SeqvprError(f"{options['reference']}: images, not descriptors: describe them with seqvpr extract --out FILE.npz")
        save_traversal_npz(Path(options["out_file"]), traversal)
        click.echo(f"{options['out_file']}: {len(traversal)} frames, {len(set(traversal.segment_ids.tolist()))} segments")
        return
    if not options["query"] or not options["radius"]:
        raise SeqvprError("--to dbstruct needs a --query and a --radius (the struct's posDistThr)")
    written = write_dbstruct_set(Path(options["out_file"]), *(slice_frame_range(load_traversal(options[role], role),
                                                                                options["frames"])
                                                        for role in ("reference", "query")), options["radius"])
    click.echo("wrote " + ", ".join(str(p) for p in written))


def write_dbstruct_set(out: Path, reference, query, radius_text: str) -> list[Path]:
    """The .db, each side's seqBounds (and descriptors .npy, when it has them) and the dataset.toml naming them,
    committed as one set (``seqvpr.io.atomic_file_set``, the .toml last): never a new .db beside old .npy files."""
    from seqvpr.data.ground_truth import parse_radius
    from seqvpr.data.loaders.dbstruct import write_dbstruct
    from seqvpr.io import atomic_file_set

    radius = parse_radius(radius_text)
    aligned = reference.positions is None or query.positions is None
    if (radius.unit == "m") == aligned:
        raise SeqvprError(f"--radius {radius_text}: use {'frames (e.g. 2f)' if aligned else 'metres (e.g. 25m)'} for "
                          f"{'frame-aligned traversals' if aligned else 'traversals with positions'}")
    description = out.with_suffix(".toml")
    names = [out.name, *(f"{out.stem}_{side}{tail}" for tail in ("_seqBounds.txt", ".npy")
                         for side in ("database", "query")), description.name]
    with atomic_file_set(out.parent, names, description.name) as tmp:
        written = [write_dbstruct(tmp / out.name, reference, query, radius.value, out.stem)]
        table = [_write_side(tmp, out, role, side, traversal, written)
                 for role, side, traversal in (("reference", "database", reference), ("query", "query", query))]
        (tmp / description.name).write_text("\n".join(table))
    return [out.parent / p.name for p in (*written, description)]


def _write_side(folder: Path, out: Path, role: str, side: str, traversal, written: list[Path]) -> str:
    """One side's seqBounds (and descriptors .npy) in ``folder``, added to ``written``; its dataset.toml entry."""
    import numpy as np

    from seqvpr.data.loaders.seq_bounds import seq_bounds_rows

    bounds = folder / f"{out.stem}_{side}_seqBounds.txt"
    np.savetxt(bounds, seq_bounds_rows(traversal.segment_ids), fmt="%d")
    written.append(bounds)
    if traversal.descriptors is None:
        return f'[{role}]\ndbstruct = "{out.name}"\nseq_bounds = "{bounds.name}"\n'
    rows = folder / f"{out.stem}_{side}.npy"
    np.save(rows, np.asarray(traversal.descriptors, dtype=np.float32))
    written.append(rows)
    return f'[{role}]\ndescriptors = "{rows.name}"\ndbstruct = "{out.name}"\nseq_bounds = "{bounds.name}"\n'
