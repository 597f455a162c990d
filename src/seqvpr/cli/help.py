"""``--help`` in titled sections: each option is tagged with its section where it is defined (``option``,
``section``), and a ``SectionedCommand`` lists the options section by section, in the order the command names,
without changing the order click parses them in. Imports click only: ``--help`` stays fast."""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any

import click

#: the attribute of a click parameter naming its help section
SECTION_ATTRIBUTE = "help_section"
#: the section of the options no one tagged (click's own --help)
OTHER = "Other"
#: the widest first column (option names and metavar) before the help moves to its own line
COLUMN_MAX = 30


def tag(param: click.Parameter, title: str) -> click.Parameter:
    """``param`` listed under section ``title`` of a ``SectionedCommand``'s help (a tag already given stays)."""
    if getattr(param, SECTION_ATTRIBUTE, None) is None:
        setattr(param, SECTION_ATTRIBUTE, title)
    return param


def section(title: str, *decorators: Callable[[Callable], Callable]) -> Callable[[Callable], Callable]:
    """Apply click option ``decorators`` (in the order ``--help`` shows them) and tag the options they add with
    section ``title``: a shared group of options (e.g. the extraction options) goes under one heading."""

    def decorate(function: Callable) -> Callable:
        before = {id(p) for p in getattr(function, "__click_params__", ())}
        for decorator in reversed(decorators):
            function = decorator(function)
        for param in getattr(function, "__click_params__", ()):
            if id(param) not in before:
                tag(param, title)
        return function

    return decorate


def option(title: str, *decls: str, **attrs: Any) -> Callable[[Callable], Callable]:
    """``click.option(*decls, **attrs)``, listed under section ``title`` of the command's help."""
    return section(title, click.option(*decls, **attrs))


def for_methods(*names: str) -> str:
    """The start of a method-specific option's help line: the methods it applies to ("adaptive, casevpr: ")."""
    return f"{', '.join(names)}: "


class SectionedCommand(click.Command):
    """A command whose ``--help`` lists its options under titled sections (``sections``, in this order; a tag not
    named there follows them, untagged options come last under ``Other``), one column width for all of them.
    ``listings`` adds a table after a section's options: section title -> (heading, [(name, line), ...]), e.g. the
    methods ``--method`` chooses from."""

    def __init__(self, *args: Any, sections: Sequence[str] = (),
                 listings: Mapping[str, tuple[str, Sequence[tuple[str, str]]]] | None = None, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.sections = tuple(sections)
        self.listings = dict(listings or {})

    def format_options(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        grouped = self.sectioned_records(ctx)
        width = min(COLUMN_MAX, max((len(name) for rows in grouped.values() for name, _ in rows), default=0))
        for title, rows in grouped.items():
            with formatter.section(title):
                formatter.write_dl([(name.ljust(width), text) for name, text in rows], col_max=COLUMN_MAX)
                if title in self.listings:
                    _write_listing(formatter, *self.listings[title])

    def sectioned_records(self, ctx: click.Context) -> dict[str, list[tuple[str, str]]]:
        """Section title -> the help records (names, help) of its options, sections in help order."""
        grouped: dict[str, list[tuple[str, str]]] = {title: [] for title in self.sections}
        for param in self.get_params(ctx):
            record = param.get_help_record(ctx)
            if record is not None:
                grouped.setdefault(getattr(param, SECTION_ATTRIBUTE, None) or OTHER, []).append(record)
        if OTHER in grouped:  # the untagged last
            grouped[OTHER] = grouped.pop(OTHER)
        return {title: rows for title, rows in grouped.items() if rows}


def _write_listing(formatter: click.HelpFormatter, heading: str, rows: Sequence[tuple[str, str]]) -> None:
    """A table under a section's options: its heading, then one row per entry, indented."""
    formatter.write_paragraph()
    formatter.write_text(heading)
    with formatter.indentation():
        formatter.write_dl(list(rows))
