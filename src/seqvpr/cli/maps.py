"""``seqvpr map build``, ``index``, ``shard`` and ``info``: parse, call ``seqvpr.maps``, print."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import click

from seqvpr.cli.options import (
    COUNT,
    DEVICE,
    NONNEGATIVE, SEED, extraction_options, frame_description, OUT_FOLDER, bag_topic_options,
    locks_output
)
from seqvpr.cli.help import SectionedCommand, option, section
from seqvpr.cli.progress import tqdm_progress

BUILD_EPILOG = """\b
Examples:
  seqvpr map build summer.npy --out maps/summer
  seqvpr map build day/ --descriptor efficientnet-lite0 --image-size 320x240 --dtype float16 --out maps/day
  seqvpr map build drive1/ drive2/ --model runs/jist --out maps/city
  seqvpr match --map maps/summer --query winter.npy --seq-len 5 --radius 1f
"""


INDEX_HELP = ("faiss index over the frames, for --shortlist: auto (flat below 10,000 frames, else IVF-PQ with about "
              "sqrt(N) lists, at most 1,024, and a byte per 8 dimensions), flat (exact), hnsw:M (graph, e.g. hnsw:32) "
              "or ivf:NLIST[,pq:M] (k-means lists, raw or M-byte PQ codes, e.g. ivf:1024,pq:32). An interrupted "
              "build resumes from its last save when run again.")


WINDOWS_HELP = ("Index the sequence descriptors (--window-method) of the centred windows of this many frames "
                "instead of single frames: for --shortlist, one search per query window; and match --method "
                "smoothing/delta/seqgem at that L searches it instead of pooling the map (0: frames).")
METHOD_HELP = "The sequence descriptor an index over windows holds (seqnet: give its --index-model)."
#: ``seqvpr map build --help``'s sections, in order
BUILD_SECTIONS = ("Input", "Descriptors", "Storage", "Index", "Output", "Compute")


@click.group(name="map")
def map_group() -> None:
    """Build a reference map once (described, saved, memory-mapped) and inspect it; match with --map."""


@map_group.command(cls=SectionedCommand, sections=BUILD_SECTIONS, epilog=BUILD_EPILOG)
@click.argument("sources", nargs=-1, required=True)
@option("Output", "--out", "out_dir", required=True, type=OUT_FOLDER, help="The map folder to write.")
@option("Input", "--frames", help="Keep source frames START:STOP of every source (e.g. 17:2000).")
@option("Descriptors", "--model", "model_dirs", type=click.Path(), multiple=True,
        help="A JIST or CosPlace model that describes the images, and/or a SeqMatchNet model whose transform the "
             "stored frames go through (repeatable, one per kind); match the map with the same ones.")
@section("Descriptors", extraction_options)
@option("Storage", "--dtype", default="float32", show_default=True,
        help="How the descriptors are stored: float32, float16 (half), sq8 (8-bit codes over each dimension's range, "
             "a quarter) or pq:M (product quantisation, M bytes a frame); matching decodes them.")
@option("Storage", "--no-normalize", is_flag=True, help="Store the descriptors without L2 normalisation.")
@option("Index", "--index", "index_spec", help=INDEX_HELP)
@option("Index", "--windows", type=NONNEGATIVE, default=0, show_default=True, help=WINDOWS_HELP)
@option("Index", "--window-method", type=click.Choice(["smoothing", "delta", "seqgem", "seqnet"]), default="smoothing",
        show_default=True, help=METHOD_HELP)
@option("Index", "--index-model", type=click.Path(), help="The SeqNet folder of an index over seqnet windows.")
@option("Index", "--seed", type=SEED, default=0, show_default=True,
        help="Seed of the index's training sample and k-means.")
@option("Compute", "--device", type=DEVICE, default="cpu", show_default=True, help="torch device, e.g. cpu or cuda.")
@option("Output", "--thumbnails", is_flag=True,
        help="Keep each frame's thumbnail in the map (image sources), so seqvpr node --publish-images shows the "
             "matched frame where the source images are not (a bag, a map copied to the robot).")
@option("Output", "--shards", type=COUNT,
        help="Write the map as this many shards (as seqvpr map shard does) for matching under torchrun.")
@option("Output", "--overlap", type=NONNEGATIVE, default=63, show_default=True,
        help="With --shards: frames each shard shares with each neighbour (windows of up to OVERLAP + 1).")
@section("Input", bag_topic_options("sources"))
@locks_output("out_dir")
def build(sources: tuple[str, ...], out_dir: str, frames: str | None, model_dirs: tuple[str, ...], dtype: str,
          no_normalize: bool, index_spec: str | None, windows: int, window_method: str, index_model: str | None,
          seed: int, device: str, thumbnails: bool, shards: int | None, overlap: int, **options: Any) -> None:
    """Describe SOURCES (descriptor files, image folders, dbStruct, dataset.toml) and save them as one map (or as
    --shards shard maps)."""
    from seqvpr.io import check_replaceable
    from seqvpr.maps.files import INFO_FILE, SHARDS_FILE
    from seqvpr.maps.codes import parse_storage
    from seqvpr.maps.index import parse_index_spec

    spec = parse_index_spec(index_spec) if index_spec else None  # a bad spec or storage fails before any work
    parse_storage(dtype)
    check_replaceable(Path(out_dir), SHARDS_FILE if shards else INFO_FILE)
    description, extraction = frame_description(options, device)
    models = _models(model_dirs, device)

    index = (spec, seed, windows, window_method, index_model)
    if not shards:
        _build_map(sources, out_dir, description, models, extraction, dtype=dtype, normalize=not no_normalize,
                   device=device, frames=frames, index=index, thumbnails=thumbnails)
        return
    if thumbnails:
        from seqvpr.errors import SeqvprError

        raise SeqvprError("--thumbnails: a sharded map keeps no thumbnails yet; build one map")
    _build_sharded(sources, out_dir, (shards, overlap), description, models, extraction, dtype=dtype,
                   normalize=not no_normalize, device=device, frames=frames, index=index)


def _build_map(sources, out_dir, description, models, extraction, *, dtype, normalize, device, frames, index,
               thumbnails=False) -> None:
    """Build one map (with its index, if one is asked for, committed as one) and print what it holds."""
    from seqvpr.maps import build_map
    from seqvpr.maps.index import add_index

    spec, seed, windows, window_method, index_model = index
    records = []
    indexed = None if spec is None else (lambda saved: records.append(
        add_index(saved, spec, seed, tqdm_progress, windows, window_method, index_model)))
    saved = build_map(sources, out_dir, description, models, dtype=dtype, normalize=normalize, device=device,
                      progress=tqdm_progress, frames=frames, indexed=indexed, thumbnails=thumbnails, **extraction)
    _echo_built(out_dir, saved.info)
    for record in records:
        _echo_index(record)


def _build_sharded(sources, out_dir, sharding, description, models, extraction, *, dtype, normalize, device, frames,
                   index) -> None:
    """Build the map straight as shards (each with its index, if one is asked for; committed as one) and print
    what they hold."""
    from seqvpr.maps import build_sharded_map
    from seqvpr.maps.shards import index_shards

    spec, seed, windows, window_method, index_model = index
    records = []
    indexed = None if spec is None else (lambda sharded: records.extend(
        index_shards(sharded, spec, seed, tqdm_progress, windows, window_method, index_model)))
    sharded = build_sharded_map(sources, out_dir, *sharding, description, models, dtype=dtype, normalize=normalize,
                                device=device, progress=tqdm_progress, frames=frames,
                                indexed=indexed, **extraction)
    _echo_built(out_dir, sharded.as_map().info)
    click.echo(f"sharded map: {out_dir} ({sharded.count} frames in {len(sharded.shards)} shards, overlap "
               f"{sharded.overlap})")
    for shard, record in zip(sharded.shards, records):
        click.echo(f"{shard.folder}: ", nl=False)
        _echo_index(record)


def _echo_built(out_dir: str, info) -> None:
    click.echo(f"{out_dir}: {info.count} frames from {len(info.sources)} source(s), {info.dim}-D "
               f"{info.description['descriptor']} descriptors, {info.dtype}")


@map_group.command(name="index")
@click.argument("map_dir", type=click.Path())
@click.option("--index", "index_spec", required=True, help=INDEX_HELP)
@click.option("--windows", type=NONNEGATIVE, default=0, show_default=True, help=WINDOWS_HELP)
@click.option("--window-method", type=click.Choice(["smoothing", "delta", "seqgem", "seqnet"]), default="smoothing",
              show_default=True, help=METHOD_HELP)
@click.option("--seed", type=SEED, default=0, show_default=True, help="Seed of the index's training sample and k-means.")
@click.option("--index-model", type=click.Path(), help="The SeqNet folder of an index over seqnet windows.")
def index_command(map_dir: str, index_spec: str, windows: int, window_method: str, seed: int,
                  index_model: str | None) -> None:
    """Build (or rebuild) MAP's faiss index over its frames, for seqvpr match --map MAP --shortlist S. A sharded
    MAP gets one index a shard (under torchrun, each rank builds its shards')."""
    from seqvpr.maps import open_map
    from seqvpr.maps.files import is_sharded_map
    from seqvpr.maps.index import add_index, parse_index_spec

    spec = parse_index_spec(index_spec)
    if is_sharded_map(map_dir):
        _index_sharded(map_dir, spec, seed, windows, window_method, index_model)
        return
    _echo_index(add_index(open_map(map_dir), spec, seed, tqdm_progress, windows, window_method, index_model))


def _index_sharded(map_dir: str, spec, seed: int, windows: int, window_method: str, index_model: str | None) -> None:
    from seqvpr import distributed
    from seqvpr.maps.files import open_sharded_map
    from seqvpr.maps.shards import index_shards

    sharded = open_sharded_map(map_dir)
    with distributed.process_group() as world:
        records = index_shards(sharded, spec, seed, tqdm_progress if world.is_root else None, windows,
                               window_method, index_model)
    for shard, record in zip(sharded.shards, records or []):
        click.echo(f"{shard.folder}: ", nl=False)
        _echo_index(record)


def _echo_index(record: dict) -> None:
    click.echo(f"index {record['spec']} over {record['over']} ({record['ntotal']} rows) in {record['build_seconds']} s "
               f"({record['file']})")


SHARD_EPILOG = """\b
Examples:
  seqvpr map shard maps/city --shards 4 --out maps/city-4
  torchrun --standalone --nproc-per-node 4 "$(command -v seqvpr)" match --map maps/city-4 -q drive.npy -L 5 --radius 25m
  seqvpr match --map maps/city-4 -q drive.npy -L 5 --radius 25m      # one process matches every shard in turn
"""


@map_group.command(epilog=SHARD_EPILOG)
@click.argument("map_dir", type=click.Path())
@click.option("--shards", type=COUNT, required=True, help="How many shards: one (or more) per torchrun rank.")
@click.option("--overlap", type=NONNEGATIVE, default=63, show_default=True,
              help="Frames each shard shares with each neighbour: windows of up to OVERLAP + 1 frames (any "
                   "velocity) are never cut at a shard edge.")
@click.option("--out", "out_dir", required=True, type=OUT_FOLDER, help="The sharded map folder to write.")
@locks_output("out_dir")
def shard(map_dir: str, shards: int, overlap: int, out_dir: str) -> None:
    """Split MAP into --shards maps for matching under torchrun, one rank per shard (match --map SHARDED)."""
    from seqvpr.maps.sharding import shard_map

    sharded = shard_map(map_dir, out_dir, shards, overlap)
    for record in sharded.shards:
        click.echo(f"{record.folder}: rows {record.own_first}..{record.own_last - 1} "
                   f"(stored from {record.first}, overlap {sharded.overlap})")
    click.echo(f"sharded map: {out_dir} ({sharded.count} frames in {len(sharded.shards)} shards)")


@map_group.command()
@click.argument("map_dir", type=click.Path())
@click.option("--json", "as_json", is_flag=True, help="Print map.json as one JSON object.")
def info(map_dir: str, as_json: bool) -> None:
    """Print what a map holds: frames, dimension, storage, how it was described, its sources and files."""
    from seqvpr.maps import open_map

    saved = open_map(map_dir)
    values = saved.info.to_json()
    if as_json:
        click.echo(json.dumps(values))
        return
    for key in ("format", "version", "count", "dim", "dtype", "metric", "normalized", "library_version", "created"):
        click.echo(f"{key + ':':17}{values[key]}")
    click.echo(f"{'descriptor:':17}{json.dumps(values['description'])}")
    click.echo(f"{'model:':17}{json.dumps(values['model'])}")
    click.echo(f"{'columns:':17}{', '.join(values['columns']) or '-'}")
    click.echo(f"{'crs:':17}{values['crs'] or '-'}")
    click.echo(f"{'index:':17}{json.dumps(values['index'])}")
    click.echo(f"{'descriptors:':17}{saved.descriptors.nbytes / 2**20:.1f} MiB, {saved.info.count} x {saved.info.dim}")
    for source in values["sources"]:
        click.echo(f"  source {source['source']} ({source['name']}): rows {source['first']}.."
                   f"{source['first'] + source['frames'] - 1}")
    _echo_sessions(saved.info)
    _echo_shards(map_dir)


def _echo_sessions(info) -> None:
    """The map's sessions: name, frames, sources, when added."""
    from seqvpr.maps.parts import sessions_of

    sessions = sessions_of(info)
    click.echo(f"{'sessions:':17}{len(sessions)}")
    for session in sessions:
        sources = ", ".join(info.sources[i].source for i in session["sources"])
        click.echo(f"  session {session['name']}: {session['frames']} frames from row {session['first']}, "
                   f"added {session['added'] or '-'} ({sources})")


@map_group.command(name="add", cls=SectionedCommand, sections=("Input", "Descriptors", "Compute"))
@click.argument("map_dir", type=click.Path())
@click.argument("sources", nargs=-1, required=True)
@option("Input", "--session", help="The name of the session the sources become.  [default: session-N]")
@option("Input", "--frames", help="Keep source frames START:STOP of every source (e.g. 17:2000).")
@option("Descriptors", "--model", "model_dirs", type=click.Path(), multiple=True,
        help="The model(s) the map was built through (the map refuses others).")
@section("Descriptors", extraction_options)
@option("Compute", "--device", type=DEVICE, default="cpu", show_default=True, help="torch device, e.g. cpu or cuda.")
@section("Input", bag_topic_options("sources"))
@locks_output("map_dir")
def add(map_dir: str, sources: tuple[str, ...], session: str | None, frames: str | None,
        model_dirs: tuple[str, ...], device: str, **options: Any) -> None:
    """Append SOURCES to the map MAP_DIR as one new session, described as the map's frames were: only the new rows
    are written (the map's own are linked), a frame index gains them, and the grown map replaces the old as one."""
    from seqvpr.maps.grow import add_to_map

    _, extraction = frame_description(options, device)
    grown = add_to_map(map_dir, list(sources), session, _models(model_dirs, device), device=device,
                       progress=tqdm_progress, frames=frames, **extraction)
    added = grown.info.sessions[-1]
    click.echo(f"{map_dir}: session {added['name']} added, {added['frames']} frames (rows {added['first']}.."
               f"{added['first'] + added['frames'] - 1}); the map now holds {grown.info.count} frames")


@map_group.command(name="check")
@click.argument("map_dir", type=click.Path())
def check_command(map_dir: str) -> None:
    """Verify MAP in full: every file against the digest map.json records, every row finite (unit length in a
    normalised map), the index and each shard the ones recorded. Opening a map checks only what is cheap."""
    from seqvpr.maps.check import check_map

    for line in check_map(map_dir):
        click.echo(line)
    click.echo("ok")


def _echo_shards(map_dir: str) -> None:
    """A sharded map's shards: the rows each owns, where it starts, and its own index."""
    from seqvpr.maps.files import is_sharded_map, open_sharded_map

    if not is_sharded_map(map_dir):
        return
    sharded = open_sharded_map(map_dir)
    click.echo(f"{'shards:':17}{len(sharded.shards)}, overlap {sharded.overlap}")
    for number, record in enumerate(sharded.shards):
        index = sharded.open_shard(number).info.index
        click.echo(f"  {record.folder}: rows {record.own_first}..{record.own_last - 1} (stored from {record.first}), "
                   f"index {'-' if not index else index['spec'] + ' over ' + index['over']}")


def _models(folders: tuple[str, ...], device: str) -> dict:
    """The --model folders loaded by kind (one per kind)."""
    from seqvpr.models.registry import load_models

    return load_models(folders, device)
