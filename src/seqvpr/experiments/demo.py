"""The end-to-end demo on the rendered synthetic world: render, describe, match, train SeqMatchNet, report.

Stage functions in data-flow order; ``run_demo`` strings them together and the CLI's ``seqvpr demo`` is a thin
layer over it. The world is a demo and test fixture, not a benchmark: its figures only show the pipeline working.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from seqvpr.data.ground_truth import GroundTruth, Radius
from seqvpr.data.sources import load_traversal
from seqvpr.data.traversal import Traversal
from seqvpr.evaluation.metrics import Evaluation
from seqvpr.features.extraction import ExtractorConfig
from seqvpr.errors import SettingError
from seqvpr.api import match
from seqvpr.evaluation.ground_truth import ground_truth
from seqvpr.evaluation.scoring import evaluate_match
from seqvpr.features.describe import describe
from seqvpr.results import MatchResult
from seqvpr.matchers.rows import distance_matrix
from seqvpr.sequences.match_settings import MatchSettings
from seqvpr.progress import ProgressFactory
from seqvpr.evaluation.report import DistanceView, MethodResult, QueryExample, write_report
from seqvpr.sequences.windows import SequenceSpec
from seqvpr.progress import LOGGER, progress_or_log
from seqvpr.threads import ensure_policy

if TYPE_CHECKING:
    from seqvpr.models.registry import TrainedModel

TRAVERSALS = ("train_reference", "train_query", "test_reference", "test_query")
CURVE_KS = tuple(range(1, 21))
SEQSLAM_VELOCITIES = (0.8, 0.9, 1.0, 1.1, 1.2)  # OpenSeqSLAM2's v_min:v_step:v_max
MAX_DEMO_FRAMES = 20_000  # frames a traversal of the demo world may have: rendering is the cost


@dataclass(frozen=True)
class DemoSettings:
    """The demo's choices: world size and look, descriptor input size, sequence lengths, training budget."""

    frames: int = 600
    width: int = 320
    height: int = 240
    condition: str = "night"
    seed: int = 0
    radius_m: float = 10.0
    lengths: tuple[int, ...] = (1, 5, 10)
    train: bool = True
    train_length: int = 5
    epochs: int = 30
    lr: float = 1e-2
    device: str = "cpu"
    examples: int = 6
    engine: str = "auto"  # how Lite0 runs (seqvpr.features.engines)

    def __post_init__(self) -> None:
        if not 50 <= self.frames <= MAX_DEMO_FRAMES:  # each frame is two rendered images
            raise SettingError(f"{{frames}} must be at least 50 and at most {MAX_DEMO_FRAMES}, got {self.frames}")
        if self.epochs < 1:
            raise SettingError(f"{{epochs}} must be at least 1, got {self.epochs}")
        from seqvpr.features.engines import check_engine

        check_engine(self.engine)

    @classmethod
    def quick(cls, **changes) -> DemoSettings:
        """A smaller world and shorter training: the whole demo in well under a minute on 2 cores."""
        return replace(cls(frames=200, lengths=(1, 5), epochs=10), **changes)


@dataclass(frozen=True)
class MethodRun:
    """One method's evaluation on the test route, with the match it came from."""

    name: str
    result: MatchResult
    evaluation: Evaluation


@dataclass(frozen=True)
class LoopRun:
    """Loop closures over the test route driven twice (by day, then under the query's condition) as two sessions of
    one drive: the settings and the figures (``seqvpr.localization.loop_files.loop_summary``)."""

    summary: dict

    def text(self) -> str:
        """The demo's loop row."""
        s = self.summary
        return (f"loop closures (day drive, then {s['drive']} drive, L={s['seq_len']}, exclude {s['exclude']}): "
                f"{s['true_revisits']} of {s['frames']} frames revisit, {s['accepted']} loop"
                f"{'' if s['accepted'] == 1 else 's'} accepted, "
                f"{s['accepted_correct']} right; recall at 100% precision {s['recall_at_100_precision']:.3f}, "
                f"PR-AUC {s['pr_auc']:.3f}")


@dataclass
class DemoResult:
    """What the demo produced: the method runs, the loop closures, the report page, and seconds per stage."""

    runs: list[MethodRun]
    report: Path
    seconds: dict[str, float] = field(default_factory=dict)
    loops: LoopRun | None = None


def render_world(out: Path, settings: DemoSettings, progress: ProgressFactory | None = None) -> dict[str, Path]:
    """The four image folders (train/test route x reference/query) of the seeded world, under ``out``."""
    from seqvpr.synthetic.world import write_demo_world

    return write_demo_world(out, frames=settings.frames, width=settings.width, height=settings.height,
                            seed=settings.seed, query_condition=settings.condition, progress_factory=progress)


def describe_world(
    folders: dict[str, Path], settings: DemoSettings, cache_dir: Path | None, progress: ProgressFactory | None = None
) -> dict[str, Traversal]:
    """EfficientNet-Lite0 + GeM descriptors (packaged ImageNet weights) of every traversal of the world."""
    config = ExtractorConfig(width=settings.width, height=settings.height)
    described = {}
    for name in TRAVERSALS:
        traversal = replace(load_traversal(str(folders[name]), "reference"), name=name)
        described[name] = describe(traversal, "efficientnet-lite0", progress=progress, extractor=config,
                                   device=settings.device, cache_dir=cache_dir, engine=settings.engine)
    return described


def match_and_score(
    name: str, method: str, reference: Traversal, query: Traversal, gt: GroundTruth, length: int,
    device: str = "cpu", models: dict | None = None, velocities: tuple[float, ...] = (1.0,),
) -> MethodRun:
    """One method at one length, scored at every K of the curves."""
    settings = MatchSettings(SequenceSpec(length, velocities=velocities), k=max(CURVE_KS), device=device)
    result = match(reference, query, method, models=models, settings=settings)
    return MethodRun(name, result, evaluate_match(result, gt, CURVE_KS))


def train_transform(world: dict[str, Traversal], settings: DemoSettings, out: Path, monitor=None) -> TrainedModel:
    """SeqMatchNet on the training route (first 75 % of frames train, the rest validate); returns the best model."""
    from seqvpr.models.registry import load_trained_model
    from seqvpr.training.seqmatchnet import TrainingData, SeqMatchNetSettings, train_seqmatchnet

    reference, query = world["train_reference"], world["train_query"]
    cut_ref, cut_qry = int(0.75 * len(reference)), int(0.75 * len(query))
    radius = Radius(settings.radius_m, "m")
    data = TrainingData(
        reference.select(np.arange(cut_ref)), query.select(np.arange(cut_qry)),
        reference.select(np.arange(cut_ref, len(reference))), query.select(np.arange(cut_qry, len(query))),
        radius, Radius(4 * settings.radius_m, "m"), radius,
    )
    train = SeqMatchNetSettings(sequence=SequenceSpec(settings.train_length), epochs=settings.epochs, lr=settings.lr,
                          refresh_every=250, seed=settings.seed, device=settings.device)
    result = train_seqmatchnet(data, settings=train, out_dir=out, monitor=monitor)
    return load_trained_model(result.folder, settings.device)


def method_result(run: MethodRun) -> MethodResult:
    """The report's row of one method."""
    pr = run.evaluation.pr
    return MethodResult(run.name, dict(run.evaluation.recall), pr.precision, pr.recall, pr.auc,
                        pr.recall_at_100_precision, run.evaluation.frame_precision)


def distance_view(run: MethodRun, gt: GroundTruth) -> DistanceView:
    """The method's full query x reference distance matrix with the ground-truth band and its top-1 path."""
    result = run.result
    distances = distance_matrix(result.reference, result.query, result.settings)
    top1 = result.topk.indices[:, 0]
    correct = gt.contains(np.arange(len(top1)), top1)
    return DistanceView(run.name, distances, gt.positives.toarray(), top1, correct,
                        distance_label=distance_label(result.settings.sequence.length),
                        query_label=f"query frame ({result.query.name})",
                        reference_label=f"reference frame ({result.reference.name})")


def distance_label(length: int) -> str:
    """What a cell of the drawn matrix is: one image distance, or the mean of L of them along a window."""
    image = "Euclidean distance of L2-normalised descriptors"
    return f"image distance ({image})" if length == 1 else f"sequence distance (mean of {length} frame distances)"


def query_examples(runs: Sequence[MethodRun], gt: GroundTruth, count: int, shown: int = 5) -> list[QueryExample]:
    """``count`` evenly spaced queries that every run scored, each with its top ``shown`` matches by every run in
    turn (named, marked correct or not), so the grid compares the methods on the same queries."""
    scored = np.logical_and.reduce([run.result.topk.has_window for run in runs]) & gt.has_positive()
    candidates = np.flatnonzero(scored)
    chosen = candidates[np.linspace(0, len(candidates) - 1, min(count, len(candidates))).astype(int)] \
        if len(candidates) else []
    return [run_example(run, gt, int(row), shown, len(runs) > 1) for row in chosen for run in runs]


def run_example(run: MethodRun, gt: GroundTruth, row: int, shown: int, named: bool) -> QueryExample:
    """Query ``row`` of ``run`` with its top ``shown`` matches and their distances (named by the run if ``named``)."""
    result = run.result
    ref_paths, qry_paths = result.reference.image_paths, result.query.image_paths
    assert ref_paths is not None and qry_paths is not None
    picks = [int(j) for j in result.topk.indices[row, :shown] if j >= 0]
    correct = gt.contains(np.full(len(picks), row), np.asarray(picks, dtype=np.int64))
    return QueryExample(
        qry_paths[row], f"frame {int(result.query.frame_index[row])}",
        [ref_paths[j] for j in picks],
        [f"ref {int(result.reference.frame_index[j])} ({result.topk.distances[row, k]:.2f})" for k, j in enumerate(picks)],
        [bool(c) for c in correct], run.name if named else "",
    )


def report_summary(settings: DemoSettings, world: dict[str, Traversal]) -> str:
    """The report's paragraph on what was run."""
    test_ref, test_qry = world["test_reference"], world["test_query"]
    return (
        f"Synthetic world (seed {settings.seed}): test route reference by day ({len(test_ref)} frames), query under "
        f"'{settings.condition}' with a lateral offset, speed changes and stops ({len(test_qry)} frames). "
        f"Descriptors: EfficientNet-Lite0 (ImageNet weights) + GeM at {settings.width}x{settings.height}. "
        f"A query is correct when a match lies within {settings.radius_m:g} m. "
        "Sequence matching averages order-aligned frame distances over a window of L frames; SeqMatchNet "
        "learns a per-frame transform on the training route (a separate part of the world).\n\n"
        "The world is a demo fixture, not a benchmark: its figures show the pipeline working, nothing more."
    )


def run_demo(
    out: Path,
    settings: DemoSettings = DemoSettings(),
    *,
    progress: ProgressFactory | None = None,
    monitor=None,
    echo: Callable[[str], None] = LOGGER.info,
) -> DemoResult:
    """Render, describe, match at every L, train and apply SeqMatchNet, and write ``out/report``."""
    ensure_policy()  # the one thread policy (seqvpr.threads)
    progress = progress_or_log(progress)  # a Python caller's progress goes to the seqvpr logger
    seconds: dict[str, float] = {}
    clock = time.perf_counter()

    def lap(stage: str) -> None:
        nonlocal clock
        now = time.perf_counter()
        seconds[stage] = now - clock
        clock = now

    folders = render_world(out / "world", settings, progress)
    lap("render")
    world = describe_world(folders, settings, out / "cache", progress)
    lap("describe")
    reference, query = world["test_reference"], world["test_query"]
    gt = ground_truth(reference, query, Radius(settings.radius_m, "m"))
    runs = untrained_runs(reference, query, gt, settings)
    loops = loop_run(reference, query, settings)
    lap("match")
    if settings.train:
        echo(f"training SeqMatchNet on the training route ({settings.epochs} epochs)...")
        model = train_transform(world, settings, out / "seqmatchnet", monitor)
        runs.append(match_and_score(f"SeqMatchNet L={settings.train_length}", "seqmatchnet", reference, query, gt,
                                    settings.train_length, settings.device, {"seqmatchnet": model}))
        lap("train")
    best = max(runs[1:] or runs, key=lambda run: run.evaluation.recall[1])
    page = write_report(
        out / "report",
        title="seqvpr demo: sequence-based place recognition on a synthetic route",
        summary=report_summary(settings, world) + "\n\n" + loops.text(),
        methods=[method_result(run) for run in runs],
        distance_views=[distance_view(runs[0], gt), distance_view(best, gt)],
        examples=query_examples([runs[0], best], gt, settings.examples),
        example_title=f"Top 5 reference frames per query by {runs[0].name} and by {best.name}, the best sequence "
                      f"method by R@1 (green: within {settings.radius_m:g} m)",
    )
    lap("report")
    return DemoResult(runs, page, seconds, loops)


def loop_run(reference: Traversal, query: Traversal, settings: DemoSettings) -> LoopRun:
    """``seqvpr loops`` over the reference drive and then the query drive as two sessions of one drive (the second
    revisits the first; its own past is excluded as far back as a drive is long, so its loops close on the first);
    a loop is right within the demo's radius."""
    from seqvpr.localization.loop_files import loop_summary
    from seqvpr.localization.loops import LoopSettings, find_loops, make_drive, score_loops

    drive = make_drive([reference, query], ["day", settings.condition])
    found = find_loops(drive, LoopSettings(seq_len=max(settings.lengths), exclude=f"{len(reference)}f"))
    return LoopRun({**loop_summary(found, score_loops(found, f"{settings.radius_m:g}m")), "drive": settings.condition})


#: the other matchers, run at the longest L: (row name, method, velocities); OpenSeqSLAM2's range for its searches
OTHER_MATCHERS = (
    ("adaptive matching", "adaptive", (1.0,)),
    ("SeqSLAM", "seqslam", SEQSLAM_VELOCITIES),
    ("SeqSLAM cone", "seqslam-cone", SEQSLAM_VELOCITIES),
    ("SeqSLAM hybrid", "seqslam-hybrid", SEQSLAM_VELOCITIES),
    ("CaseVPR", "casevpr", (1.0,)),
)


def untrained_runs(reference: Traversal, query: Traversal, gt: GroundTruth, settings: DemoSettings) -> list[MethodRun]:
    """Single-image retrieval and sequence matching at every L, then the other matchers at the longest L (the route
    has stops and speed changes: adaptive matching is made for them) and graph matching over the whole route."""
    runs = [
        match_and_score("single image" if length == 1 else f"sequence matching L={length}",
                        "single" if length == 1 else "matching", reference, query, gt, length, settings.device)
        for length in settings.lengths
    ]
    longest = max(settings.lengths)
    if longest > 1:
        runs += [match_and_score(f"{name} L={longest}", method, reference, query, gt, longest, settings.device,
                                 velocities=velocities) for name, method, velocities in OTHER_MATCHERS]
    runs.append(match_and_score("graph matching", "graph", reference, query, gt, 1, settings.device))
    return runs


def demo_recall_table(runs: Sequence[MethodRun], ks: Sequence[int] = (1, 5, 20)) -> str:
    """The recall table as text: one row per method, R@K columns, PR-AUC and the frame-level precision of the top-1
    matches' correspondences (``frames``)."""
    width = max(len(run.name) for run in runs) + 2
    lines = [f"{'':<{width}}" + "".join(f"{'R@' + str(k):>8}" for k in ks) + f"{'PR-AUC':>8}{'frames':>8}"]
    for run in runs:
        recall = run.evaluation.recall
        frames = run.evaluation.frame_precision
        lines.append(f"{run.name:<{width}}" + "".join(f"{recall[k]:>8.3f}" for k in ks)
                     + f"{run.evaluation.pr.auc:>8.3f}" + (f"{frames:>8.3f}" if frames == frames else f"{'–':>8}"))
    return "\n".join(lines)
