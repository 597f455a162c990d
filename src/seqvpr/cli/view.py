"""``seqvpr view``: one interactive HTML page for seqvpr's outputs (a match run, several to compare, a
localisation, a map) that opens offline from disk. Parse, call the library (``seqvpr.viewer``), print."""

from __future__ import annotations

from pathlib import Path

import click

from seqvpr.cli.help import SectionedCommand, option
from seqvpr.cli.options import OUT_FOLDER, locks_output
from seqvpr.cli.progress import tqdm_progress

VIEW_SECTIONS = ("Input", "Output")
VIEW_EPILOG = """\b
Examples:
  seqvpr view runs/night-L5                         # writes runs/night-L5/view/index.html
  seqvpr view runs/single runs/night-L5 --out cmp   # two methods side by side
  seqvpr view runs/localize-night --open            # a localisation: timeline, map, each frame's estimate
  seqvpr view maps/campus                           # a map: sessions, settings, identity, route
"""


@click.command(cls=SectionedCommand, sections=VIEW_SECTIONS, epilog=VIEW_EPILOG)
@click.argument("runs", nargs=-1, required=True, type=click.Path())
@option("Output", "--out", "out_dir", type=OUT_FOLDER,
        help="The page's folder  [default: RUN/view for a run, MAP.view beside a map].")
@option("Output", "--open", "open_page", is_flag=True, help="Open the page in the default browser.")
@locks_output("out_dir")
def view(runs: tuple[str, ...], out_dir: str | None, open_page: bool) -> None:
    """Write an interactive page of RUNS: the route with each query's outcome, the selected frame beside its top-K
    (every run side by side), the distances or the timeline; keyboard stepping through frames and failures."""
    from seqvpr.viewer import view_page

    out = Path(out_dir) if out_dir else default_out(Path(runs[0]))
    page = view_page([Path(r) for r in runs], out, progress=tqdm_progress)
    click.echo(f"wrote {page}")
    if open_page:
        click.launch(str(page))


def default_out(run: Path) -> Path:
    """A run's page goes inside it (``RUN/view``); a map's beside it (a map folder holds only the map)."""
    return run.with_name(run.name + ".view") if (run / "map.json").is_file() else run / "view"
