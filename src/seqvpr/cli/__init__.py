"""The ``seqvpr`` command: the click group and ``main``. One module per command family (``match``: match, eval,
extract; ``train``: train, ablate; ``experiments``: benchmark, demo) parses options, calls the library and prints;
shared options live in ``options`` and progress bars in ``progress``. Importing the CLI loads no torch, numba,
faiss or matplotlib: each command imports what it uses when it runs."""

from __future__ import annotations

import sys

import click

from seqvpr.cli.experiments import benchmark, demo
from seqvpr.cli.match import eval_command, extract, match
from seqvpr.cli.train import ablate, train
from seqvpr.errors import SeqvprError


@click.group(context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 110})
@click.version_option(package_name="seqvpr")
def cli() -> None:
    """Sequence-based visual place recognition: match a query traversal against a reference traversal."""


for command in (match, eval_command, demo, extract, benchmark, train, ablate):
    cli.add_command(command)


def main() -> None:
    """Entry point: run the CLI; a SeqvprError becomes one line on stderr and exit status 2."""
    try:
        cli.main(standalone_mode=False)
    except click.exceptions.Abort:
        click.echo("aborted", err=True)
        sys.exit(130)
    except click.ClickException as error:
        error.show()
        sys.exit(error.exit_code)
    except SeqvprError as error:
        click.echo(f"seqvpr: error: {error}", err=True)
        sys.exit(2)
    except KeyboardInterrupt:
        sys.exit(130)


if __name__ == "__main__":
    main()
