"""The viewer's page: one ``index.html`` holding its script, its style and the run's data (``seqvpr.viewer.runs``),
and a ``thumbs/`` folder beside it; it opens from disk with no server and fetches nothing from the network. The
folder is written whole under a temporary name, then renamed (``io.atomic_folder``)."""

from __future__ import annotations

import html
import json
import math
from collections.abc import Callable
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from seqvpr.io import atomic_folder
from seqvpr.viewer.runs import Side, View
from seqvpr.data.thumbnails import page_thumbnails

PAGE_FILE = "index.html"
#: top-K columns a page keeps per method (the panel shows the first of them)
KEPT = 20


def write_view(view: View, out: str | Path, progress: Callable[[int, str], Callable[[int], None]] | None = None
               ) -> Path:
    """``out/index.html`` and its thumbnails for ``view``; the page's path."""
    with atomic_folder(out, PAGE_FILE) as tmp:
        data = view_data(view, tmp, progress)
        (tmp / PAGE_FILE).write_text(page_html(view.title, data), encoding="utf-8")
    return Path(out) / PAGE_FILE


def view_data(view: View, folder: Path, progress=None) -> dict[str, Any]:
    """The page's data: plain lists (NaN and infinity as null), thumbnails linked into ``folder``."""
    data: dict[str, Any] = {"kind": view.kind, "title": view.title, "notes": view.notes,
                            "reference": side_data(view.reference, folder, "reference", progress)}
    if view.query is not None:
        data["query"] = side_data(view.query, folder, "query", progress)
    data["methods"] = [{"name": m.name, "refs": m.refs[:, :KEPT].tolist(),
                        "distances": _finite(m.distances[:, :KEPT]), "correct": m.correct.tolist()}
                       for m in view.methods]
    data["positives"] = view.positives
    data["stream"] = view.stream
    data["facts"] = view.facts
    return data


def side_data(side: Side, folder: Path, role: str, progress=None) -> dict[str, Any]:
    """A side's names, positions (None: the page lays frames out in order) and thumbnail sources."""
    tick = progress(len(side.images), f"thumbnails {role}") if progress and side.images else None
    return {"name": side.name, "names": side.names,
            "xy": None if side.positions is None else np.round(side.positions, 3).tolist(),
            "thumbs": page_thumbnails(side.images, folder, tick=tick)}


def _finite(values: np.ndarray) -> list:
    """Rows of numbers with non-finite values as None (JSON has no infinity)."""
    return [[round(float(v), 6) if math.isfinite(v) else None for v in row] for row in values.tolist()]


def page_html(title: str, data: dict[str, Any]) -> str:
    """The whole page: style, markup, the data as JSON and the script, all inline."""
    style = resources.files("seqvpr.viewer").joinpath("page.css").read_text(encoding="utf-8")
    script = resources.files("seqvpr.viewer").joinpath("page.js").read_text(encoding="utf-8")
    payload = json.dumps(data, separators=(",", ":"), allow_nan=False).replace("</", "<\\/")
    return f"""<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>{html.escape(title)}</title>
<style>{style}</style></head>
<body>
<header><h1>{html.escape(title)}</h1><div id="notes"></div></header>
<main>
<section id="left"><h2>Route</h2><canvas id="route" width="640" height="420"></canvas>
<div id="legend"></div>
<h2 id="second-title">Distances</h2><canvas id="second" width="640" height="420"></canvas>
<div class="hint" id="hint"></div></section>
<section id="right"><div id="selected"></div><div id="facts"></div></section>
</main>
<script id="data" type="application/json">{payload}</script>
<script>{script}</script>
</body></html>
"""
