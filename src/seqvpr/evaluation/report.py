"""A static, self-contained HTML report: recall table, distance matrices, Recall@K and PR curves, example matches.

The folder opens offline: plots are PNGs (drawn by ``seqvpr.evaluation.plots``), example images are copied in as
small thumbnails, and ``index.html`` uses inline CSS and relative links only. The folder is built under a temporary
sibling name and renamed into place, so an interrupted run never leaves half a report.
"""

from __future__ import annotations

import csv
import html
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from PIL import Image

from seqvpr.errors import SeqvprError
from seqvpr.evaluation.plots import (  # noqa: F401  (re-exported: tests and callers use them from here)
    CORRECT_COLOR,
    DPI,
    DistanceView,
    MethodResult,
    GT_COLOR,
    MAX_DRAWN,
    NO_WINDOW_COLOR,
    WRONG_COLOR,
    block_reduce,
    block_steps,
    check_distance_view,
    color_limits,
    drawable_distances,
    method_colors,
    new_figure,
    plot_distance_view,
    plot_pr_curves,
    plot_recall_at_k,
    save_figure,
)
from seqvpr.io import atomic_folder

THUMB_SIZE = (240, 180)  # bounding box of example thumbnails, in pixels
EXAMPLES_DIR = "examples"


@dataclass(frozen=True)
class QueryExample:
    """A query image and its top matches (paths) by one method (``method``: its name, '' when there is one method),
    with whether each is a correct place. Consecutive examples of one query image share its cell in the grid."""

    query_image: Path
    query_label: str
    match_images: list[Path]
    match_labels: list[str]
    match_correct: list[bool]
    method: str = ""


# ----------------------------------------------------------------------------------------------- validation


def check_example(example: QueryExample) -> None:
    """Raise SeqvprError unless an example has as many match labels and verdicts as match images."""
    n = len(example.match_images)
    if len(example.match_labels) != n or len(example.match_correct) != n:
        raise SeqvprError(
            f"example {example.query_label!r}: {n} match images but {len(example.match_labels)} labels "
            f"and {len(example.match_correct)} verdicts"
        )


# ----------------------------------------------------------------------------------------------- thumbnails


def make_thumbnail(src: Path, dst: Path, size: tuple[int, int] = THUMB_SIZE) -> bool:
    """Write a small JPEG copy of ``src`` at ``dst``; False (and no file) when ``src`` cannot be read."""
    try:
        with Image.open(src) as img:
            img.draft("RGB", size)  # lets JPEG decode at a reduced scale: much faster for large frames
            thumb = img.convert("RGB")
            thumb.thumbnail(size, Image.Resampling.LANCZOS)
            thumb.save(dst, format="JPEG", quality=85)
        return True
    except (OSError, ValueError):
        return False


def copy_thumbnails(examples: Sequence[QueryExample], folder: Path) -> dict[Path, str | None]:
    """Thumbnail each distinct example image once into ``folder``; source path -> relative src (None: unreadable)."""
    folder.mkdir(parents=True, exist_ok=True)
    names: dict[Path, str | None] = {}
    for example in examples:
        for src in [example.query_image, *example.match_images]:
            src = Path(src)
            if src in names:
                continue
            name = f"img{len(names):04d}.jpg"
            names[src] = f"{EXAMPLES_DIR}/{name}" if make_thumbnail(src, folder / name) else None
    return names


# ----------------------------------------------------------------------------------------------- HTML


CSS = """
body { font-family: -apple-system, "Segoe UI", Roboto, "Helvetica Neue", Arial, sans-serif; color: #222;
       background: #f6f7f9; margin: 0; }
main { max-width: 1200px; margin: 0 auto; padding: 24px 32px 48px; background: #fff; }
h1 { font-size: 1.7em; margin: 0.2em 0 0.4em; }
h2 { font-size: 1.25em; margin: 1.8em 0 0.6em; padding-bottom: 0.2em; border-bottom: 1px solid #e2e4e8; }
p.summary { line-height: 1.5; max-width: 60em; margin: 0.4em 0; }
table.recall { border-collapse: collapse; font-variant-numeric: tabular-nums; }
table.recall th, table.recall td { padding: 6px 14px; border-bottom: 1px solid #e2e4e8; text-align: right; }
table.recall th:first-child, table.recall td:first-child { text-align: left; }
table.recall thead th { background: #f0f2f5; border-bottom: 2px solid #c9cdd3; }
table.recall td.best { font-weight: 700; }
span.swatch { display: inline-block; width: 12px; height: 12px; border-radius: 2px; margin-right: 8px;
              vertical-align: -1px; }
.plots { display: flex; flex-wrap: wrap; gap: 16px; }
.plots figure { margin: 0; flex: 1 1 520px; max-width: 560px; }
.plots figure.wide { flex: 1 1 540px; max-width: 720px; }
.plots img { width: 100%; height: auto; border: 1px solid #e2e4e8; }
figcaption { font-size: 0.85em; color: #555; margin-top: 4px; }
.examples { display: grid; gap: 14px 10px; align-items: start; }
.cell { margin: 0; }
.cell .frame { border: 4px solid #555; border-radius: 3px; line-height: 0; background: #eee; }
.cell.query .frame { border-color: #444; border-style: double; border-width: 5px; }
.cell.correct .frame { border-color: """ + CORRECT_COLOR + """; }
.cell.wrong .frame { border-color: """ + WRONG_COLOR + """; }
.cell img { width: 100%; height: auto; display: block; }
.cell .missing { display: block; line-height: 1.3; padding: 28px 6px; text-align: center; color: #777;
                 font-size: 0.8em; }
.cell figcaption { font-size: 0.8em; line-height: 1.3; margin-top: 3px; word-break: break-word; }
.cell.query figcaption { font-weight: 600; }
.cell.method { align-self: center; font-size: 0.85em; font-weight: 600; line-height: 1.3; word-break: break-word; }
.cell.correct figcaption .mark { color: """ + CORRECT_COLOR + """; font-weight: 700; }
.cell.wrong figcaption .mark { color: """ + WRONG_COLOR + """; font-weight: 700; }
.legend { font-size: 0.9em; color: #444; margin: 0 0 10px; }
.legend .box { display: inline-block; width: 14px; height: 10px; border: 3px solid; margin: 0 6px 0 14px;
               vertical-align: -2px; }
.legend .box.query-box { border-color: #444; margin-left: 0; }
.legend .box.ok-box { border-color: """ + CORRECT_COLOR + """; }
.legend .box.bad-box { border-color: """ + WRONG_COLOR + """; }
ul.files { font-family: ui-monospace, Menlo, Consolas, monospace; font-size: 0.9em; }
ul.files span { font-family: -apple-system, "Segoe UI", Roboto, Arial, sans-serif; color: #555; }
"""


def format_value(value: float | None) -> str:
    """A figure of the table: three decimals, or 'n/a' when missing or not a number."""
    if value is None or not math.isfinite(value):
        return "n/a"
    return f"{value:.3f}"


def recall_table_html(methods: Sequence[MethodResult], table_ks: Sequence[int], colors: dict[str, str]) -> str:
    """The methods × (R@K…, PR-AUC, R@100%P, frame precision) table, best value of each column in bold."""
    columns = [(f"R@{k}", [m.recall_at_k.get(k) for m in methods]) for k in table_ks]
    columns.append(("PR-AUC", [m.pr_auc for m in methods]))
    columns.append(("R@100%P", [m.recall_at_100_precision for m in methods]))
    columns.append(("frames", [m.frame_precision for m in methods]))
    head = "".join(f"<th>{html.escape(name)}</th>" for name, _ in columns)
    best = [_best_index(values) for _, values in columns]
    rows = []
    for i, m in enumerate(methods):
        cells = "".join(
            ('<td class="best">' if best[c] == i else "<td>") + f"{format_value(values[i])}</td>"
            for c, (_, values) in enumerate(columns)
        )
        swatch = f'<span class="swatch" style="background:{colors[m.name]}"></span>'
        rows.append(f"<tr><td>{swatch}{html.escape(m.name)}</td>{cells}</tr>")
    return (
        f'<table class="recall"><thead><tr><th>Method</th>{head}</tr></thead>\n'
        f"<tbody>\n{chr(10).join(rows)}\n</tbody></table>"
    )


def _best_index(values: Sequence[float | None]) -> int | None:
    """Index of the largest finite value, or None when there are fewer than two methods to compare."""
    finite = [(v, i) for i, v in enumerate(values) if v is not None and math.isfinite(v)]
    return max(finite)[1] if len(values) > 1 and finite else None


def example_cell_html(src: str | None, label: str, kind: str, caption_prefix: str) -> str:
    """One framed thumbnail with its caption; ``kind`` is the CSS class: query, correct or wrong."""
    alt = html.escape(f"{caption_prefix} {label}".strip(), quote=True)
    if src:
        body = f'<img src="{html.escape(src, quote=True)}" alt="{alt}" loading="lazy">'
    else:
        body = '<span class="missing">image missing</span>'
    mark = {"correct": '<span class="mark">✓</span> ', "wrong": '<span class="mark">✗</span> '}.get(kind, "")
    return (
        f'<figure class="cell {kind}"><div class="frame">{body}</div>'
        f"<figcaption>{mark}{html.escape(caption_prefix)} {html.escape(label)}</figcaption></figure>"
    )


def examples_html(examples: Sequence[QueryExample], thumbs: dict[Path, str | None], colors: dict[str, str]) -> str:
    """The grid: one row per example, the query first (one cell for the consecutive examples of one query), then
    the method's name when examples name one, then its ranked matches framed green or red."""
    with_method = any(e.method for e in examples)
    n_matches = max((len(e.match_images) for e in examples), default=0)
    cells = []
    for group in _query_groups(examples):
        cells.append(_query_cell(group, thumbs))
        for e in group:
            if with_method:
                cells.append(_method_cell(e.method, colors))
            for rank, (img, label, ok) in enumerate(zip(e.match_images, e.match_labels, e.match_correct), start=1):
                cells.append(example_cell_html(thumbs[Path(img)], label, "correct" if ok else "wrong", f"#{rank}"))
            cells.extend('<div class="cell"></div>' for _ in range(n_matches - len(e.match_images)))
    legend = (
        '<p class="legend"><span class="box query-box"></span>query'
        '<span class="box ok-box"></span>correct place<span class="box bad-box"></span>wrong place</p>'
    )
    columns = "minmax(0, 1fr) " + ("minmax(6em, 0.6fr) " if with_method else "") + f"repeat({n_matches}, minmax(0, 1fr))"
    grid = f'<div class="examples" style="grid-template-columns: {columns};">\n'
    return legend + grid + "\n".join(cells) + "\n</div>"


def _query_groups(examples: Sequence[QueryExample]) -> list[list[QueryExample]]:
    """Consecutive examples of the same query image, grouped: they share one query cell."""
    groups: list[list[QueryExample]] = []
    for e in examples:
        if groups and Path(groups[-1][0].query_image) == Path(e.query_image):
            groups[-1].append(e)
        else:
            groups.append([e])
    return groups


def _query_cell(group: Sequence[QueryExample], thumbs: dict[Path, str | None]) -> str:
    """The query's framed thumbnail, spanning the rows of every method shown for it."""
    first = group[0]
    cell = example_cell_html(thumbs[Path(first.query_image)], first.query_label, "query", "query")
    return cell if len(group) == 1 else cell.replace("<figure ", f'<figure style="grid-row: span {len(group)}" ', 1)


def _method_cell(method: str, colors: dict[str, str]) -> str:
    """The name of the method whose matches follow in the row, with its colour swatch when it has one."""
    color = colors.get(method)
    swatch = f'<span class="swatch" style="background:{color}"></span>' if color else ""
    return f'<div class="cell method">{swatch}{html.escape(method)}</div>'


def summary_html(summary: str) -> str:
    """The caller's setting text, escaped, one paragraph per blank-line-separated block."""
    blocks = [b.strip() for b in summary.split("\n\n") if b.strip()]
    return "\n".join(f'<p class="summary">{html.escape(b)}</p>' for b in blocks)


def files_html(files: Sequence[tuple[str, str]], n_thumbnails: int) -> str:
    """The list of files in the report folder, each linked relatively, with what it holds."""
    items = [
        f'<li><a href="{html.escape(name, quote=True)}">{html.escape(name)}</a> <span>— {html.escape(what)}</span></li>'
        for name, what in files
    ]
    if n_thumbnails:
        items.append(f"<li>{EXAMPLES_DIR}/ <span>— {n_thumbnails} example thumbnails</span></li>")
    return '<ul class="files">\n' + "\n".join(items) + "\n</ul>"


def figure_html(src: str, alt: str, caption: str) -> str:
    """One full-width figure with its caption."""
    return (f'<figure class="wide"><img src="{src}" alt="{html.escape(alt, quote=True)}" style="max-width:100%">'
            f"<figcaption>{html.escape(caption)}</figcaption></figure>")


def page_html(title: str, sections: Sequence[str]) -> str:
    """The whole page around the sections: inline CSS only, no scripts, nothing fetched from the network."""
    body = "\n".join(sections)
    return (
        "<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n"
        '<meta name="viewport" content="width=device-width, initial-scale=1">\n'
        f"<title>{html.escape(title)}</title>\n<style>{CSS}</style>\n</head>\n"
        f"<body>\n<main>\n{body}\n</main>\n</body>\n</html>\n"
    )


def write_results_csv(methods: Sequence[MethodResult], path: Path) -> None:
    """The table's numbers for machines: every K that any method has, PR-AUC, recall at 100 % precision and
    frame-level precision (empty where a method has no per-frame correspondences)."""
    ks = sorted({k for m in methods for k in m.recall_at_k})
    with open(path, "w", newline="", encoding="utf-8") as handle:
        writer = csv.writer(handle)
        writer.writerow(["method", *(f"R@{k}" for k in ks), "PR-AUC", "R@100%P", "frame_precision"])
        for m in methods:
            values = [*(m.recall_at_k.get(k, float("nan")) for k in ks), m.pr_auc, m.recall_at_100_precision]
            frames = f"{m.frame_precision:.6f}" if math.isfinite(m.frame_precision) else ""
            writer.writerow([m.name, *(f"{v:.6f}" for v in values), frames])


# ----------------------------------------------------------------------------------------------- the report


def build_report(
    folder: Path,
    *,
    title: str,
    summary: str,
    methods: Sequence[MethodResult],
    table_ks: Sequence[int],
    distance_views: Sequence[DistanceView],
    examples: Sequence[QueryExample],
    example_title: str,
) -> None:
    """Write every file of the report into the (empty) ``folder``."""
    colors = method_colors([m.name for m in methods])
    files: list[tuple[str, str]] = [("results.csv", "the numbers of the table, every K")]
    write_results_csv(methods, folder / "results.csv")
    sections = [f"<h1>{html.escape(title)}</h1>", summary_html(summary)]
    sections += _recall_sections(methods, table_ks, colors)
    sections += _curve_sections(methods, colors, folder, files)
    sections += _distance_sections(distance_views, folder, files)
    example_parts, n_thumbs = _example_sections(examples, example_title, folder, colors)
    sections += example_parts
    sections.append("<h2>Files</h2>")
    sections.append(files_html([("index.html", "this page"), *files], n_thumbs))
    (folder / "index.html").write_text(page_html(title, sections), encoding="utf-8")


def _recall_sections(methods: Sequence[MethodResult], table_ks: Sequence[int], colors: dict[str, str]) -> list[str]:
    """The 'Recall' heading, the recall table and the line explaining its columns."""
    return [
        "<h2>Recall</h2>",
        recall_table_html(methods, table_ks, colors),
        '<p class="legend">R@K: share of queries with a correct place among the K nearest references. '
        "PR-AUC and R@100%P: precision–recall of accepting the top-1 match below a distance threshold. "
        "frames: share of the top-1 matches' per-frame correspondences that fall on a correct place "
        "(n/a where a method pairs no frames). Best value per column in bold.</p>",
    ]


def _curve_sections(
    methods: Sequence[MethodResult], colors: dict[str, str], folder: Path, files: list[tuple[str, str]]
) -> list[str]:
    """Draw the Recall@K and PR plots into ``folder``, listed in ``files``; their section (none without methods)."""
    if not methods:
        return []
    plot_recall_at_k(methods, colors, folder / "recall_at_k.png")
    plot_pr_curves(methods, colors, folder / "pr_curves.png")
    files += [("recall_at_k.png", "Recall@K curves"), ("pr_curves.png", "precision–recall curves")]
    return [
        "<h2>Curves</h2>",
        '<div class="plots">'
        '<figure><img src="recall_at_k.png" alt="Recall@K curves"><figcaption>Recall@K against K.</figcaption></figure>'
        '<figure><img src="pr_curves.png" alt="Precision-recall curves">'
        "<figcaption>Precision against recall of the top-1 match, over all distance thresholds.</figcaption></figure>"
        "</div>",
    ]


def _distance_sections(views: Sequence[DistanceView], folder: Path, files: list[tuple[str, str]]) -> list[str]:
    """Draw each view as ``distance_<i>.png`` in ``folder``, listed in ``files``; their section (none without views)."""
    if not views:
        return []
    figures = []
    for i, view in enumerate(views):
        name = f"distance_{i}.png"
        plot_distance_view(view, folder / name)
        files.append((name, f"distance matrix: {view.title}"))
        figures.append(
            f'<figure class="wide"><img src="{name}" alt="{html.escape(view.title, quote=True)}">'
            f"<figcaption>{html.escape(view.title)}: each cell's colour is the {html.escape(view.distance_label)} "
            f"between {html.escape(view.query_label)} (row) and {html.escape(view.reference_label)} (column), darker "
            "is closer; the blue band marks the ground-truth positives; dots are each query's top-1 reference, green "
            "when correct, red when wrong.</figcaption></figure>"
        )
    return ["<h2>Distance matrices</h2>", '<div class="plots">' + "".join(figures) + "</div>"]


def _example_sections(
    examples: Sequence[QueryExample], example_title: str, folder: Path, colors: dict[str, str]
) -> tuple[list[str], int]:
    """Thumbnail the example images into ``folder``; their section and how many thumbnails were written."""
    if not examples:
        return [], 0
    thumbs = copy_thumbnails(examples, folder / EXAMPLES_DIR)
    n_thumbs = sum(1 for v in thumbs.values() if v)
    return [f"<h2>{html.escape(example_title or 'Example queries')}</h2>", examples_html(examples, thumbs, colors)], n_thumbs


def write_report(
    out_dir: Path,
    *,
    title: str,
    summary: str,
    methods: list[MethodResult],
    table_ks: Sequence[int] = (1, 5, 20),
    distance_views: Sequence[DistanceView] = (),
    examples: Sequence[QueryExample] = (),
    example_title: str = "",
) -> Path:
    """Write the report folder ``out_dir`` atomically (built aside, then renamed in); returns its index.html."""
    out_dir = Path(out_dir)
    for view in distance_views:
        check_distance_view(view)
    for example in examples:
        check_example(example)
    with atomic_folder(out_dir, "index.html") as tmp:
        build_report(
            tmp, title=title, summary=summary, methods=methods, table_ks=table_ks,
            distance_views=distance_views, examples=examples, example_title=example_title,
        )
    return out_dir / "index.html"
