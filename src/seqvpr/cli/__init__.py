"""The ``seqvpr`` command: the click group and ``main``. One module per command family (``match``: match, eval,
extract; ``train``: train, ablate; ``experiments``: benchmark, demo; ``published``: import; ``maps``: map build, map info; ``localize``; ``robot``: node, play) parses options, calls
the library and prints; shared options live in ``options`` and progress bars in ``progress``. Importing the CLI
loads no torch, numba, faiss or matplotlib: each command imports what it uses when it runs."""

from __future__ import annotations

import importlib
import logging
import os
import signal
import sys
import warnings

import click

from seqvpr.cli.help import tag
from seqvpr.errors import SeqvprError, SeqvprWarning, SettingError, os_refusal
from seqvpr.io import raise_for_signal

#: command name -> "module:attribute"; a command's module is imported only when that command (or --help) runs
COMMANDS = {
    "match": "seqvpr.cli.match:match", "eval": "seqvpr.cli.match:eval_command", "extract": "seqvpr.cli.extract:extract",
    "train": "seqvpr.cli.train:train", "ablate": "seqvpr.cli.train:ablate",
    "benchmark": "seqvpr.cli.experiments:benchmark", "demo": "seqvpr.cli.experiments:demo",
    "import": "seqvpr.cli.published:import_command", "map": "seqvpr.cli.maps:map_group",
    "localize": "seqvpr.cli.localize:localize", "convert": "seqvpr.cli.convert:convert",
    "doctor": "seqvpr.cli.doctor:doctor", "node": "seqvpr.cli.robot:node", "play": "seqvpr.cli.robot:play",
    "export": "seqvpr.cli.export:export", "loops": "seqvpr.cli.loops:loops", "view": "seqvpr.cli.view:view",
}


class LazyGroup(click.Group):
    """A click group whose commands are imported when used: ``seqvpr match`` loads nothing of training."""

    def list_commands(self, ctx: click.Context) -> list[str]:
        return sorted(COMMANDS)

    def get_command(self, ctx: click.Context, name: str) -> click.Command | None:
        if name not in COMMANDS:
            return None
        module, attribute = COMMANDS[name].split(":")
        return with_threads_option(getattr(importlib.import_module(module), attribute))


def _apply_threads(ctx: click.Context, param: click.Parameter, value: int | None) -> None:
    """The thread policy, applied before any other option is read and before any library starts a pool."""
    from seqvpr.threads import use_threads

    if not ctx.resilient_parsing:
        use_threads(value)


THREADS_OPTION = tag(click.Option(
    ["--threads"], type=click.IntRange(min=1), is_eager=True, expose_value=False, callback=_apply_threads,
    help="Threads for torch, numba and faiss together [default: $SEQVPR_THREADS, else $OMP_NUM_THREADS, else the "
         "cores no other process is busy on at start]."), "Compute")


def with_threads_option(command: click.Command) -> click.Command:
    """``command`` (and every command of a group) taking ``--threads``: every command applies the one policy."""
    if isinstance(command, click.Group):
        for sub in command.commands.values():
            with_threads_option(sub)
    elif THREADS_OPTION not in command.params:
        command.params.append(THREADS_OPTION)
    return command


@click.group(cls=LazyGroup, context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 110})
@click.version_option(package_name="seqvpr")
def cli() -> None:
    """Sequence-based visual place recognition: match a query traversal against a reference traversal.

    Under torchrun a rank waits at most $SEQVPR_RANK_TIMEOUT seconds (default 300) for the others."""


def _command_path(ctx: click.Context | None) -> str:
    """``seqvpr`` and the subcommands of ``ctx``, whatever the program was started as."""
    names = []
    while ctx is not None:
        names.append(ctx.info_name if ctx.parent is not None else "seqvpr")
        ctx = ctx.parent
    return " ".join(reversed(names))


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """A SeqvprWarning as one line on stderr; any other warning as Python shows it."""
    if issubclass(category, SeqvprWarning):
        click.echo(f"seqvpr: warning: {message}", err=True)
    else:
        sys.stderr.write(warnings.formatwarning(message, category, filename, lineno, line))


class Terminated(BaseException):
    """Raised by SIGTERM so the work unwinds like Ctrl-C: temporary files are removed and locks released."""


def _terminated(signum, frame) -> None:
    raise_for_signal(Terminated())


def _interrupted(signum, frame) -> None:
    raise_for_signal(KeyboardInterrupt())


INTERRUPTED = "nothing half-written is left under an output's name"


class EchoHandler(logging.Handler):
    """The ``seqvpr`` logger's lines on the current stderr as ``seqvpr: ...`` (what the library reports of long
    work that no progress bar covers)."""

    def emit(self, record: logging.LogRecord) -> None:
        click.echo(f"seqvpr: {record.getMessage()}", err=True)


def flagged(error: SeqvprError) -> str:
    """An error's message as a command-line user reads it: the settings it names, as flags (``options.FLAGS``)."""
    if isinstance(error, SettingError):
        from seqvpr.cli.options import FLAGS

        return error.naming(FLAGS)
    return str(error)


def show_library_log() -> None:
    """Route the library's progress lines to stderr, once per process; only rank 0 of a torchrun run reports."""
    logger = logging.getLogger("seqvpr")
    if not any(isinstance(h, EchoHandler) for h in logger.handlers):
        logger.addHandler(EchoHandler())
        logger.propagate = False
    logger.setLevel(logging.INFO if os.environ.get("RANK", "0") == "0" else logging.WARNING)


def main() -> None:
    """Entry point: run the CLI; a SeqvprError becomes one line on stderr and exit status 2."""
    warnings.showwarning = _show_warning
    show_library_log()
    signal.signal(signal.SIGTERM, _terminated)
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:  # not where a shell made a job ignore it
        signal.signal(signal.SIGINT, _interrupted)
    if hasattr(signal, "SIGXFSZ"):  # past ``ulimit -f`` a write fails with EFBIG (one line) rather than a kill
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    try:
        cli.main(standalone_mode=False)
    except click.exceptions.Abort as abort:
        if isinstance(abort.__cause__, EOFError):  # click turns an EOFError into Abort: a truncated input, not Ctrl-C
            click.echo(f"seqvpr: error: an input file ended early (empty or truncated): {abort.__cause__}", err=True)
            sys.exit(2)
        click.echo(f"seqvpr: interrupted (SIGINT); {INTERRUPTED}", err=True)
        sys.exit(130)
    except Terminated:
        from seqvpr.distributed import sigterm_reported

        sigterm_reported.set()
        click.echo(f"seqvpr: terminated (SIGTERM); {INTERRUPTED}", err=True)
        sys.exit(143)
    except click.UsageError as error:  # a bad option or value: one line naming it, as every bad input gets
        message = " ".join(error.format_message().split())
        command = f" ({_command_path(error.ctx)} --help)" if error.ctx else ""
        click.echo(f"seqvpr: error: {message}{command}", err=True)
        sys.exit(2)
    except click.ClickException as error:
        error.show()
        sys.exit(error.exit_code)
    except SeqvprError as error:
        click.echo(f"seqvpr: error: {flagged(error)}", err=True)
        sys.exit(2)
    except OSError as error:  # the system said no (no space, read-only, permission...): one line, when we know it
        refusal = os_refusal(error)
        if refusal is None:
            raise
        click.echo(f"seqvpr: error: {refusal}", err=True)
        sys.exit(2)
    except KeyboardInterrupt:
        click.echo(f"seqvpr: interrupted (SIGINT); {INTERRUPTED}", err=True)
        sys.exit(130)
