"""The HTML report: self-contained folder, escaped text, atomic replacement, thumbnails and framing, big matrices."""

from __future__ import annotations
import csv

import dataclasses
import time
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest

from tests.helpers import raises_one_line
from PIL import Image

from seqvpr.evaluation import report
from seqvpr.errors import SeqvprError
from seqvpr.evaluation.report import DistanceView, MethodResult, QueryExample, write_report


class PageParser(HTMLParser):
    """Collects src/href links, class tokens and the text of each recall-table row."""

    def __init__(self) -> None:
        super().__init__()
        self.links: list[str] = []
        self.classes: list[str] = []
        self.tags: list[str] = []
        self.rows: list[list[str]] = []
        self._in_table = False
        self._cell: list[str] | None = None

    def handle_starttag(self, tag, attrs):
        self.tags.append(tag)
        attrs = dict(attrs)
        for key in ("src", "href"):
            if attrs.get(key) is not None:
                self.links.append(attrs[key])
        self.classes.extend((attrs.get("class") or "").split())
        if tag == "table" and "recall" in (attrs.get("class") or ""):
            self._in_table = True
        elif self._in_table and tag == "tr":
            self.rows.append([])
        elif self._in_table and tag in ("td", "th"):
            self._cell = []

    def handle_endtag(self, tag):
        if tag == "table":
            self._in_table = False
        elif tag in ("td", "th") and self._cell is not None:
            self.rows[-1].append("".join(self._cell).strip())
            self._cell = None

    def handle_data(self, data):
        if self._cell is not None:
            self._cell.append(data)


def parse(index: Path) -> PageParser:
    parser = PageParser()
    parser.feed(index.read_text(encoding="utf-8"))
    return parser


def make_method(name: str, r1: float, k_max: int = 20, frames: float = float("nan")) -> MethodResult:
    recall = {k: min(1.0, r1 + 0.02 * (k - 1)) for k in range(1, k_max + 1)}
    rec = np.linspace(0.05, r1, 30)
    prec = np.linspace(1.0, 0.7, 30)
    return MethodResult(name, recall, prec, rec, pr_auc=0.61234, recall_at_100_precision=0.2, frame_precision=frames)


def make_view(n_q: int = 60, n_r: int = 50, seed: int = 0) -> DistanceView:
    rng = np.random.default_rng(seed)
    q, r = np.arange(n_q)[:, None], np.arange(n_r)[None, :]
    band = np.abs(r - q * n_r / n_q)
    distances = band / n_r + 0.1 * rng.random((n_q, n_r))
    positives = band <= 3
    top1 = np.argmin(distances, axis=1)
    return DistanceView("view", distances, positives, top1, positives[np.arange(n_q), top1])


def make_images(folder: Path) -> list[Path]:
    folder.mkdir()
    paths = []
    for i in range(8):
        path = folder / f"frame{i}.png"
        Image.new("RGB", (320, 240), (30 * i, 200 - 20 * i, 90)).save(path)
        paths.append(path)
    return paths


@pytest.fixture
def images(tmp_path: Path) -> list[Path]:
    return make_images(tmp_path / "frames")


@pytest.fixture(scope="module")
def built(tmp_path_factory) -> tuple[Path, list[QueryExample]]:
    """One complete report (methods, a distance view, examples) shared by the tests that only read it."""
    root = tmp_path_factory.mktemp("built")
    images = make_images(root / "frames")
    examples = make_examples(images)
    full_report(root / "report", images, distance_views=[make_view()], examples=examples)
    return root / "report", examples


def make_examples(images: list[Path]) -> list[QueryExample]:
    verdicts = [[True, False, True], [False, False, True]]
    return [
        QueryExample(
            images[i],
            f"frame {i}",
            [images[2 + i], images[4 + i], images[6 + i]],
            [f"ref {j} d=0.{j}" for j in range(3)],
            verdicts[i],
        )
        for i in range(2)
    ]


def full_report(out: Path, images: list[Path], **overrides) -> Path:
    kwargs = dict(
        title="Demo",
        summary="Nordland, winter vs summer.",
        methods=[make_method("SeqMatchNet", 0.81234, frames=0.79876), make_method("SeqSLAM", 0.6)],
        table_ks=(1, 5, 20),
        distance_views=[],
        examples=make_examples(images),
        example_title="Examples",
    )
    kwargs.update(overrides)
    return write_report(out, **kwargs)


def leftovers(parent: Path) -> list[Path]:
    return [p for p in parent.iterdir() if p.name.startswith(".")]


def test_write_report_returns_index(tmp_path, images):
    out = tmp_path / "report"
    assert full_report(out, images) == out / "index.html"


def test_folder_is_self_contained(built):
    out, _ = built
    index = out / "index.html"
    assert index.is_file()
    page = parse(index)
    assert page.links, "the page links its plots and thumbnails"
    assert "script" not in page.tags
    for link in page.links:
        assert not link.startswith(("http:", "https:", "//", "/")) and ":" not in link, link
        target = (out / link).resolve()
        assert target.is_file(), link
        assert target.is_relative_to(out.resolve()), link
    assert {"recall_at_k.png", "pr_curves.png", "distance_0.png"} <= set(page.links)


def test_table_holds_names_and_recall_at_1(built):
    rows = parse(built[0] / "index.html").rows
    assert rows[0][:4] == ["Method", "R@1", "R@5", "R@20"]
    by_name = {row[0]: row for row in rows[1:]}
    assert by_name["SeqMatchNet"][1] == "0.812"
    assert by_name["SeqSLAM"][1] == "0.600"
    assert by_name["SeqMatchNet"][4] == "0.612"  # PR-AUC


def test_frame_precision_is_a_column_and_n_a_where_a_method_pairs_no_frames(built):
    rows = parse(built[0] / "index.html").rows
    assert rows[0][-1] == "frames"
    by_name = {row[0]: row for row in rows[1:]}
    assert by_name["SeqMatchNet"][-1] == "0.799" and by_name["SeqSLAM"][-1] == "n/a"
    with open(built[0] / "results.csv", newline="") as handle:
        csv_rows = {row["method"]: row for row in csv.DictReader(handle)}
    assert float(csv_rows["SeqMatchNet"]["frame_precision"]) == pytest.approx(0.79876)
    assert csv_rows["SeqSLAM"]["frame_precision"] == ""


def test_caller_text_is_escaped(tmp_path, images):
    evil = "<script>alert('x')</script>"
    examples = make_examples(images)
    examples[0] = QueryExample(images[0], evil, examples[0].match_images, [evil] * 3, examples[0].match_correct)
    index = full_report(
        tmp_path / "report", images, title=evil, summary=evil, methods=[make_method(evil, 0.5)],
        distance_views=[dataclasses.replace(make_view(), title=evil)], examples=examples,
        example_title=evil,
    )
    text = index.read_text(encoding="utf-8")
    assert "<script" not in text
    assert "&lt;script&gt;" in text


def test_existing_report_is_replaced_without_leftovers(tmp_path, images):
    out = tmp_path / "report"
    out.mkdir()
    (out / "index.html").write_text("an old report")
    (out / "stale.txt").write_text("old")
    full_report(out, images)
    assert not (out / "stale.txt").exists()
    assert (out / "index.html").read_text() != "an old report"
    assert leftovers(tmp_path) == []


def test_a_folder_of_other_files_is_never_replaced(tmp_path, images):
    out = tmp_path / "notes"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    raises_one_line("holds other files and no index.html", full_report, out, images)
    assert (out / "notes.txt").read_text() == "mine" and leftovers(tmp_path) == []


def test_failed_plot_keeps_the_old_report(tmp_path, images, monkeypatch):
    out = tmp_path / "report"
    full_report(out, images, title="first")
    before = {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()}

    def boom(*args, **kwargs):
        raise RuntimeError("plot failed")

    monkeypatch.setattr(report, "plot_pr_curves", boom)
    with pytest.raises(RuntimeError, match="plot failed"):
        full_report(out, images, title="second")
    after = {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()}
    assert after == before
    assert leftovers(tmp_path) == []


def test_failure_on_first_run_leaves_nothing(tmp_path, images, monkeypatch):
    def boom(*args, **kwargs):
        raise RuntimeError("plot failed")

    monkeypatch.setattr(report, "plot_distance_view", boom)
    with pytest.raises(RuntimeError, match="plot failed"):
        full_report(tmp_path / "report", images, distance_views=[make_view()])
    assert list(tmp_path.iterdir()) == [tmp_path / "frames"]


def test_thumbnails_and_green_red_frames(built):
    out, examples = built
    page = parse(out / "index.html")
    thumbs = sorted((out / "examples").iterdir())
    assert len(thumbs) == 8  # every distinct image once
    for thumb in thumbs:
        with Image.open(thumb) as img:
            assert img.width <= report.THUMB_SIZE[0] and img.height <= report.THUMB_SIZE[1]
    verdicts = [ok for e in examples for ok in e.match_correct]
    assert page.classes.count("wrong") == verdicts.count(False)
    assert page.classes.count("correct") == verdicts.count(True)
    assert page.classes.count("query") == len(examples)
    assert all(link.startswith("examples/") for link in page.links if link.endswith(".jpg"))


def test_unreadable_example_image_shows_a_placeholder(tmp_path, images):
    broken = QueryExample(tmp_path / "missing.png", "frame 9", [images[1]], ["ref 1"], [True])
    index = full_report(tmp_path / "report", images, examples=[broken])
    assert "image missing" in index.read_text(encoding="utf-8")


def test_mismatched_inputs_are_refused_before_writing(tmp_path, images):
    view = make_view()
    bad_view = DistanceView("bad", view.distances, view.positives[:, :-1], view.top1, view.correct)
    with pytest.raises(SeqvprError, match="positives"):
        full_report(tmp_path / "report", images, distance_views=[bad_view])
    bad_example = QueryExample(images[0], "q", [images[1], images[2]], ["a"], [True, False])
    with pytest.raises(SeqvprError, match="labels"):
        full_report(tmp_path / "report", images, examples=[bad_example])
    assert not (tmp_path / "report").exists()


def test_nan_and_inf_rows_do_not_crash(tmp_path, images):
    view = make_view()
    d = view.distances.copy()
    d[:5] = np.nan
    d[-3:] = np.inf
    d[10, ::2] = np.nan
    top1 = view.top1.copy()
    top1[:5] = -1
    top1[-3:] = -1
    out = tmp_path / "report"
    full_report(out, images, distance_views=[DistanceView("holes", d, view.positives, top1, view.correct)])
    assert (out / "distance_0.png").stat().st_size > 0


def test_all_nan_matrix_draws(tmp_path):
    empty = DistanceView("empty", np.full((4, 6), np.nan), np.zeros((4, 6), bool), np.full(4, -1), np.zeros(4, bool))
    report.plot_distance_view(empty, tmp_path / "empty.png")
    assert (tmp_path / "empty.png").stat().st_size > 0


def test_block_minimum_keeps_a_thin_valley():
    d = np.ones((3000, 2500), dtype=np.float32)
    d[1234, 2001] = 0.0
    d[:7] = np.nan
    steps = report.block_steps(d.shape)
    drawn = report.drawable_distances(d, steps)
    assert drawn.shape[0] <= report.MAX_DRAWN and drawn.shape[1] <= report.MAX_DRAWN
    assert drawn[1234 // steps[0], 2001 // steps[1]] == 0.0
    assert np.isnan(drawn[0]).all()
    assert report.block_reduce(np.eye(5, dtype=bool), (2, 2), False, np.any).tolist() == [
        [True, False, False], [False, True, False], [False, False, True]
    ]


def test_large_matrix_draws_quickly(tmp_path):
    rng = np.random.default_rng(1)
    n_q, n_r = 3000, 2500
    distances = rng.random((n_q, n_r), dtype=np.float32)
    positives = np.abs(np.arange(n_r)[None, :] - np.arange(n_q)[:, None] * n_r / n_q) <= 5
    top1 = rng.integers(-1, n_r, n_q)
    view = DistanceView("big", distances, positives, top1, rng.random(n_q) < 0.8)
    start = time.perf_counter()
    report.plot_distance_view(view, tmp_path / "big.png")
    elapsed = time.perf_counter() - start
    with Image.open(tmp_path / "big.png") as img:
        assert img.width <= 1000 and img.height <= 1000
    assert elapsed < 10.0, f"drawing took {elapsed:.1f} s"


@pytest.mark.parametrize("n", [3, 10, 20, 30])
def test_every_method_gets_its_own_color(n):
    names = [f"method {i}" for i in range(n)]
    colors = report.method_colors(names)
    assert list(colors) == names
    assert len(set(colors.values())) == n


def test_table_swatches_use_the_method_colors(tmp_path, images):
    methods = [make_method(f"m{i}", 0.1 * i) for i in range(10)]
    text = full_report(tmp_path / "report", images, methods=methods).read_text(encoding="utf-8")
    colors = report.method_colors([m.name for m in methods])
    assert all(f"background:{colors[m.name]}" in text for m in methods)


def test_examples_of_two_methods_share_the_query_cell_and_name_the_method(tmp_path, images):
    single, sequence = make_examples(images)
    examples = [dataclasses.replace(single, method="single image"),
                dataclasses.replace(single, match_correct=[True] * 3, method="sequence matching L=5")]
    index = full_report(tmp_path / "report", images, examples=examples,
                        methods=[make_method("single image", 0.3), make_method("sequence matching L=5", 0.6)])
    page = parse(index)
    text = index.read_text(encoding="utf-8")
    assert page.classes.count("query") == 1 and "grid-row: span 2" in text
    assert page.classes.count("method") == 2 and "sequence matching L=5</div>" in text
    assert page.classes.count("correct") == 2 + 3 and page.classes.count("wrong") == 1


def test_distance_views_say_what_their_colors_and_axes_show(tmp_path, images):
    view = dataclasses.replace(make_view(), distance_label="sequence distance (mean of 5 frame distances)",
                               query_label="query frame (night)")
    text = full_report(tmp_path / "report", images, distance_views=[view]).read_text(encoding="utf-8")
    assert "sequence distance (mean of 5 frame distances) between query frame (night) (row)" in text
