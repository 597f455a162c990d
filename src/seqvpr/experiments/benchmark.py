"""`seqvpr benchmark CONFIG`: every method on every dataset's test split, as the papers' comparison tables.

A config (TOML) names datasets (reference, query, ground-truth radius, train/select/test frame ranges) and methods.
Methods that learn are trained on the train split and selected on the select split; every method is scored on the
test split at the config's sequence length, and the length-capable ones again at each length of the length table.
A method that fails is reported in its row and the others go on.

    [benchmark]
    methods = ["single", "matching", "seqmatchnet", "smoothing", "delta", "seqnet", "seqgem", "jist", "hvpr"]
    seq_len = 5
    lengths = [5, 10, 20]
    ks = [1, 5, 20]
    hvpr_shortlist = "seqnet"   # HVPR's shortlist: the trained SeqNet S_L, or "seqgem" (untrained)

    [training]            # SeqMatchNet settings (SeqMatchNetSettings fields), optional
    epochs = 10
    lr = 0.01

    [seqnet]              # SeqNet settings (SeqNetSettings fields), optional
    epochs = 50

    [match]               # match settings for every method, optional: velocities ("1", "0.8,1,1.2" or
    velocities = "1"      # "MIN:MAX:STEP"), steps (adaptive, casevpr, graph: "MIN:MAX"), contrast_window (seqslam)
    [match.seqslam-hybrid]  # the same keys for one method only
    velocities = "0.8:1.2:0.1"

    [jist]                # JIST model and run (``training.jist.jist_setup`` keys: JistConfig and
                          # JistTrainSettings fields, cell_m, min_images)
    backbone = "efficientnet-lite0"
    weights = "imagenet"

    [[dataset]]
    name = "nordland"
    reference = "nordland_64x32/summer"
    query = "nordland_64x32/winter"
    radius = "1f"
    train = "17:1200"
    select = "1200:1600"
    test = "1600:2000"
"""

from __future__ import annotations

import json
import shutil
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

from seqvpr.data.ground_truth import Radius, ground_truth_within_radius, parse_radius
from seqvpr.data.sources import load_traversal
from seqvpr.data.traversal import Traversal, parse_frame_range
from seqvpr.errors import SeqvprError, SeqvprWarning, reading
from seqvpr.evaluation.metrics import Evaluation
from seqvpr.methods import METHODS
from seqvpr.evaluation.scoring import evaluate_match
from seqvpr.features.describe import describe
from seqvpr.io import check_output_apart
from seqvpr.results import MatchResult
from seqvpr.sequences.match_settings import MatchSettings
from seqvpr.sequences.windows import SequenceSpec
from seqvpr.threads import ensure_policy

DEFAULT_METHODS = ("single", "matching", "seqmatchnet", "smoothing", "delta", "seqnet", "seqgem", "jist", "hvpr")
SHORTLISTS = ("seqnet", "seqgem")
MonitorFactory = Callable[[str], Any]  # model kind -> its training monitor


class NotApplicable(SeqvprError):
    """A method that cannot run on a dataset by its nature (JIST on descriptor files): ``n/a`` in the table."""


@dataclass(frozen=True)
class DatasetSpec:
    """One dataset of the config: traversals, ground-truth radius, and the train/select/test frame ranges."""

    name: str
    reference: str
    query: str
    radius: str
    train: str
    select: str
    test: str
    descriptor: str = "patchnorm"


@dataclass(frozen=True)
class BenchmarkConfig:
    """The whole benchmark: datasets, methods, the main sequence length, the length table's lengths, K values."""

    datasets: tuple[DatasetSpec, ...]
    methods: tuple[str, ...] = DEFAULT_METHODS
    seq_len: int = 5
    lengths: tuple[int, ...] = (5, 10, 20)
    ks: tuple[int, ...] = (1, 5, 20)
    training: dict[str, Any] = field(default_factory=dict)
    seqnet: dict[str, Any] = field(default_factory=dict)
    jist: dict[str, Any] = field(default_factory=dict)
    hvpr_shortlist: str = "seqnet"
    match: dict[str, Any] = field(default_factory=dict)  # MatchSettings fields (and velocities) for every method
    method_match: dict[str, dict[str, Any]] = field(default_factory=dict)  # the same, per method

    def match_settings(self, method: str, length: int, k: int) -> tuple[MatchSettings, dict[str, Any]]:
        """The settings ``method`` runs with at ``length`` and its own (steps, contrast window): the ``[match]``
        table, then the method's own."""
        chosen = {**self.match, **self.method_match.get(method, {})}
        velocities = chosen.pop("velocities", (1.0,))
        return MatchSettings(SequenceSpec(length, velocities=velocities), k=k), chosen


@dataclass(frozen=True)
class Row:
    """One table cell group: a method on a dataset at a length, with its evaluation or why it failed."""

    dataset: str
    method: str
    length: int
    evaluation: Evaluation | None
    error: str = ""
    applicable: bool = True


def read_config(path: str | Path) -> BenchmarkConfig:
    """Parse and check a benchmark TOML file; paths inside are relative to the file's folder."""
    with reading(path, "a benchmark config"):
        return _read_config(Path(path))


def _whole_numbers(path: Path, key: str, values: Any, single: bool = False) -> tuple[int, ...]:
    """``[benchmark] key``: positive integers (one when ``single``), else one line naming the key."""
    items = (values,) if single else values
    if not isinstance(items, (list, tuple)) or not items or \
            not all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in items):
        raise SeqvprError(f"{path}: [benchmark] {key} must be {'a positive integer' if single else 'a list of positive integers'}, got {values!r}")
    return tuple(items)


def _read_config(path: Path) -> BenchmarkConfig:
    try:
        import tomllib
    except ModuleNotFoundError:  # Python 3.10
        import tomli as tomllib
    from seqvpr.arrays import check_regular_file

    path = Path(path)
    if path.exists():  # a FIFO or a device is one line, never a wait
        check_regular_file(path, "a benchmark description")
    try:
        raw = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise SeqvprError(f"{path}: no such benchmark config") from None
    except tomllib.TOMLDecodeError as error:
        raise SeqvprError(f"{path}: not valid TOML ({error})") from None
    specs = _dataset_specs(raw, path)
    tables = {"dataset", "benchmark", "training", "seqnet", "jist", "match"}
    if set(raw) - tables:
        raise SeqvprError(f"{path}: unknown table(s) {', '.join(sorted(set(raw) - tables))} (known: "
                          f"{', '.join(sorted(tables))})")
    settings = raw.get("benchmark", {})
    _check_keys(settings, {"methods", "hvpr_shortlist", "seq_len", "lengths", "ks"}, "benchmark", path)
    methods = settings.get("methods", DEFAULT_METHODS)
    if isinstance(methods, str) or not methods:
        raise SeqvprError(f"{path}: [benchmark] methods must be a non-empty list of methods, got {methods!r}")
    methods = tuple(methods)
    bad = [m for m in methods if m not in METHODS]
    if bad:
        raise SeqvprError(f"{path}: unknown methods {', '.join(bad)} (choose from: {', '.join(METHODS)})")
    shortlist = str(settings.get("hvpr_shortlist", "seqnet"))
    if shortlist not in SHORTLISTS:
        raise SeqvprError(f"{path}: hvpr_shortlist {shortlist!r} is not one of {', '.join(SHORTLISTS)}")
    return BenchmarkConfig(
        tuple(specs), methods, _whole_numbers(path, "seq_len", settings.get("seq_len", 5), single=True)[0],
        _whole_numbers(path, "lengths", settings.get("lengths", (5, 10, 20))),
        _whole_numbers(path, "ks", settings.get("ks", (1, 5, 20))), _training_table(raw, "training", path),
        _training_table(raw, "seqnet", path), _jist_table(raw, path), shortlist, *_match_tables(raw, methods, path),
    )


def _dataset_specs(raw: dict, path: Path) -> list[DatasetSpec]:
    """The ``[[dataset]]`` tables, checked: every key present and known, the name a plain folder name."""
    datasets = raw.get("dataset")
    if not datasets:
        raise SeqvprError(f"{path}: no [[dataset]] tables")
    known = {f.name for f in fields(DatasetSpec)}
    specs = []
    for number, table in enumerate(datasets, start=1):
        missing = [name for name in ("name", "reference", "query", "radius", "train", "select", "test") if name not in table]
        if missing:
            raise SeqvprError(f"{path}: dataset {number} lacks {', '.join(missing)}")
        unknown = sorted(set(table) - known)
        if unknown:
            raise SeqvprError(f"{path}: dataset {number} has unknown keys {', '.join(unknown)}")
        name = str(table["name"])
        if not name.replace("-", "").replace("_", "").replace(".", "").isalnum() or set(name) <= {"."}:
            raise SeqvprError(f"{path}: dataset {number} name {name!r} must be a plain name (letters, digits, - _ .): "
                              "it names a folder under --out")
        values = {k: str(v) for k, v in table.items()}
        for key in ("reference", "query"):
            values[key] = str((path.parent / values[key]).resolve()) if not Path(values[key]).is_absolute() else values[key]
        specs.append(DatasetSpec(**values))
    return specs


def _training_table(raw: dict, name: str, path: Path) -> dict[str, Any]:
    """A ``[training]`` (SeqMatchNet) or ``[seqnet]`` table, checked against its settings' fields."""
    from seqvpr.training.seqmatchnet import SeqMatchNetSettings
    from seqvpr.training.seqnet import SeqNetSettings

    table = dict(raw.get(name, {}))
    allowed = {f.name for f in fields(SeqMatchNetSettings if name == "training" else SeqNetSettings)} - {"sequence"}
    _check_keys(table, allowed, name, path)
    if "ks" in table:
        table["ks"] = tuple(table["ks"])
    return table


def _jist_table(raw: dict, path: Path) -> dict[str, Any]:
    """The ``[jist]`` table: the keys ``jist_setup`` takes (JistConfig and JistTrainSettings fields, ``cell_m``,
    ``min_images``), but not ``seq_length`` (the benchmark's ``seq_len``)."""
    from seqvpr.training.jist import JIST_KEYS

    table = dict(raw.get("jist", {}))
    _check_keys(table, set(JIST_KEYS) - {"seq_length"}, "jist", path)
    return table


MATCH_KEYS = {"velocities", "steps", "contrast_window"}


def _match_tables(raw: dict, methods: Sequence[str], path: Path) -> tuple[dict[str, Any], dict[str, dict[str, Any]]]:
    """``[match]`` (every method) and its ``[match.METHOD]`` sub-tables (one method), checked and parsed."""
    table = dict(raw.get("match", {}))
    per_method = {name: value for name, value in table.items() if isinstance(value, dict)}
    unknown = sorted(set(per_method) - set(methods))
    if unknown:
        raise SeqvprError(f"{path}: [match] has tables for {', '.join(unknown)}, which [benchmark] methods does not "
                          f"list")
    shared = {key: value for key, value in table.items() if key not in per_method}
    return (_match_values(shared, "match", path),
            {name: _match_values(values, f"match.{name}", path) for name, values in per_method.items()})


def _match_values(table: dict[str, Any], name: str, path: Path) -> dict[str, Any]:
    """One match table's values as MatchSettings takes them (velocities a tuple, steps a pair)."""
    from seqvpr.sequences.windows import parse_steps, parse_velocities

    _check_keys(table, MATCH_KEYS, name, path)
    parsed: dict[str, Any] = {}
    if "velocities" in table:
        parsed["velocities"] = parse_velocities(str(table["velocities"]), f"{path}: [{name}] velocities")
        if not all(0 < v < float("inf") for v in parsed["velocities"]):
            raise SeqvprError(f"{path}: [{name}] velocities must be positive numbers, got {table['velocities']!r}")
    if "steps" in table:
        parsed["steps"] = parse_steps(str(table["steps"]), f"{path}: [{name}] steps")
    if "contrast_window" in table:
        window = table["contrast_window"]
        if not isinstance(window, int) or isinstance(window, bool) or window < 2:
            raise SeqvprError(f"{path}: [{name}] contrast_window must be a whole number of at least 2, got {window!r}")
        parsed["contrast_window"] = window
    return parsed


def _check_keys(table: dict, allowed: set[str], name: str, path: Path) -> None:
    unknown = sorted(set(table) - allowed)
    if unknown:
        raise SeqvprError(f"{path}: [{name}] has unknown keys {', '.join(unknown)} (known: {', '.join(sorted(allowed))})")


@dataclass
class Splits:
    """A dataset's described traversals cut into train, select and test pairs, and its radius."""

    train: tuple[Traversal, Traversal]
    select: tuple[Traversal, Traversal]
    test: tuple[Traversal, Traversal]
    radius: Radius


def load_splits(spec: DatasetSpec, progress=None) -> Splits:
    """Load and describe a dataset's traversals and cut them into its three splits."""
    reference = describe(load_traversal(spec.reference, "reference"), spec.descriptor, progress=progress)
    query = describe(load_traversal(spec.query, "query"), spec.descriptor, progress=progress)

    def cut(text: str, what: str) -> tuple[Traversal, Traversal]:
        start, stop = parse_frame_range(text, f"{spec.name}: {what}")
        return reference.slice_frames(start, stop), query.slice_frames(start, stop)

    return Splits(cut(spec.train, "train"), cut(spec.select, "select"), cut(spec.test, "test"), parse_radius(spec.radius))


class MethodRunner:
    """Runs the methods on one dataset through ``seqvpr.match``; each model kind a method uses is trained once on the
    train split (selected on the select split) and shared (SeqMatchNet and SeqNet also feed HVPR); a re-run into
    the same folder reuses the finished runs trained on the same data and split (``drop_stale_run``)."""

    def __init__(self, splits: Splits, config: BenchmarkConfig, out: Path, monitors: MonitorFactory | None = None) -> None:
        self.splits, self.config, self.out, self.monitors = splits, config, out, monitors
        self._cache: dict[str, Any] = {}
        self.models_used: dict[str, dict[str, Any]] = {}  # kind -> folder and weights' digest

    def _once(self, name: str, make: Callable[[], Any]) -> Any:
        if name not in self._cache:
            self._cache[name] = make()
        return self._cache[name]

    def model(self, kind: str):
        """The trained model of ``kind`` (its best epoch), trained or resumed into ``out/<kind>``."""
        def make():
            from seqvpr.models.registry import load_trained_model

            monitor = self.monitors(kind) if self.monitors else None
            folder = train_kind(kind, self.splits, self.config, self.out / kind, monitor)
            self.models_used[kind] = model_identity(folder)
            return load_trained_model(folder, _device(self.config, kind))

        return self._once(kind, make)

    def test_frames(self, models: dict) -> tuple[Traversal, Traversal]:
        """The test split's frames for these models: JIST's encoder describes the images (once, pooled at every
        length); otherwise the dataset's descriptors."""
        if "jist" not in models:
            return self.splits.test
        from seqvpr.methods import describe_for_models

        return self._once("jist-test", lambda: describe_for_models(
            *self.splits.test, models, lambda r, q: (r, q), _device(self.config, "jist")))

    def run(self, method: str, length: int) -> MatchResult:
        """The method's top-K on the test split at sequence length ``length``."""
        from seqvpr.matchers.hierarchical import HVPR_SHORTLIST
        from seqvpr.api import match
        from seqvpr.methods import models_used

        shortlist = self.config.hvpr_shortlist
        models = {kind: self.model(kind) for kind in models_used(method, shortlist)}
        settings, search = self.config.match_settings(method, length, max(max(self.config.ks), HVPR_SHORTLIST))
        reference, query = self.test_frames(models)
        return match(reference, query, method, models=models, settings=settings,
                     proposer=shortlist if method == "hvpr" else None, **search)


def train_kind(kind: str, splits: Splits, config: BenchmarkConfig, out: Path, monitor=None) -> Path:
    """Train (or resume, or reuse a finished run of) ``kind`` on the train split at the config's length, selecting
    on the select split with the kind's training defaults; returns the model folder."""
    from seqvpr.training.data import training_data

    if kind == "jist" and any(t.image_paths is None for t in splits.train):
        raise NotApplicable("needs images (this dataset has descriptor files only)")
    data = training_data(kind, splits.train, splits.select, splits.radius)
    drop_stale_run(out, data)
    spec = SequenceSpec(config.seq_len)
    if kind == "seqmatchnet":
        from seqvpr.models.seqmatchnet import TransformConfig
        from seqvpr.training.seqmatchnet import SeqMatchNetSettings, train_seqmatchnet

        settings = SeqMatchNetSettings(**{**config.training, "sequence": spec})
        return train_seqmatchnet(data, TransformConfig(data.dim), settings, out, resume=True, monitor=monitor).folder
    if kind == "seqnet":
        from seqvpr.training.seqnet import SeqNetSettings, train_seqnet

        settings = SeqNetSettings(**{**config.seqnet, "sequence": spec})
        return train_seqnet(data, settings, out, resume=True, monitor=monitor).folder
    from seqvpr.training.jist import frame_size, jist_setup, train_jist
    from seqvpr.training.settings import with_recipe

    model_config, settings = jist_setup(with_recipe(config.jist, frame_size(splits.train[0])), config.seq_len)
    return train_jist(data, model_config, settings, out, resume=True, monitor=monitor).folder


def drop_stale_run(out: Path, data) -> None:
    """A run in ``out`` trained on other data (another file, other content, another train/select split) is not
    reused: a warning says why, the run is removed and the model trained again. Runs from before the data was
    recorded are reused as they are."""
    from seqvpr.training.resume import check_same_data, data_records, recorded_data
    from seqvpr.training.state import STATE_JSON

    recorded = recorded_data(out)
    if recorded is None:
        return
    try:
        check_same_data(recorded, data_records(data), out / STATE_JSON)
    except SeqvprError as error:
        warnings.warn(f"{error}; training it again", SeqvprWarning)
        shutil.rmtree(out)


def split_records(splits: Splits) -> dict[str, dict[str, Any]]:
    """What a dataset's results rest on: each split's reference and query (source, file digest, frames, content)."""
    from seqvpr.data.traversal_record import traversal_record

    pairs = {"train": splits.train, "select": splits.select, "test": splits.test}
    return {name: {"reference": traversal_record(r), "query": traversal_record(q)} for name, (r, q) in pairs.items()}


def model_identity(folder: Path) -> dict[str, Any]:
    """A trained model's folder and identity (its weights' digest, as its config records it)."""
    from seqvpr.models.files import MODEL_FILE, read_model_config

    return {"folder": str(folder), "weights": (read_model_config(folder).get("files") or {}).get(MODEL_FILE)}


def write_provenance(out: Path, provenance: dict[str, Any]) -> Path:
    """``run.json``: per dataset, the data identities and splits the results rest on, and the models used."""
    from seqvpr.io import atomic_write

    with atomic_write(out / "run.json") as handle:
        json.dump({"datasets": provenance}, handle, indent=2)
    return out / "run.json"


def _device(config: BenchmarkConfig, kind: str) -> str:
    table = {"seqmatchnet": config.training, "seqnet": config.seqnet, "jist": config.jist}[kind]
    return str(table.get("device", "cpu"))


def run_benchmark(
    config: BenchmarkConfig, out: Path, *, progress=None, monitors: MonitorFactory | None = None,
    echo: Callable[[str], None] = lambda t: None,
) -> list[Row]:
    """Every method on every dataset (main length, then the length table); failures become rows, not exceptions.
    ``monitors(method)`` gives each training run its progress monitor."""
    ensure_policy()  # the one thread policy (seqvpr.threads)
    check_output_apart(out, [path for spec in config.datasets for path in (spec.reference, spec.query)], "--out")
    rows: list[Row] = []
    provenance: dict[str, Any] = {}
    for spec in config.datasets:
        try:
            splits = load_splits(spec, progress)
        except Exception as error:  # noqa: BLE001 - a dataset that fails to load fails its rows, not the run
            rows += [Row(spec.name, m, config.seq_len, None, one_line(error)) for m in config.methods]
            echo(f"{spec.name}: failed to load: {one_line(error)}")
            continue
        runner = MethodRunner(splits, config, out / spec.name, monitors)
        provenance[spec.name] = {"splits": split_records(splits), "models": runner.models_used}
        gt = ground_truth_within_radius(splits.test[1], splits.test[0], splits.radius)
        plan = [(m, config.seq_len) for m in config.methods]
        plan += [(m, n) for n in config.lengths for m in config.methods if METHODS[m].length is None and n != config.seq_len]
        for method, length in plan:
            echo(f"{spec.name}: {method} L={length}")
            try:
                result = runner.run(method, length)
                evaluation = evaluate_match(result, gt, config.ks)
                save_viewable_run(out / spec.name / "runs" / f"{method}-L{length}", result, gt, spec, method,
                                  length == config.seq_len)
                rows.append(Row(spec.name, method, length, evaluation))
            except NotApplicable as error:
                rows.append(Row(spec.name, method, length, None, str(error), applicable=False))
            except Exception as error:  # noqa: BLE001 - reported in the method's row
                rows.append(Row(spec.name, method, length, None, one_line(error)))
                echo(f"{spec.name}: {method} L={length} failed: {one_line(error)}")
    write_provenance(out, provenance)
    return rows


def save_viewable_run(folder: Path, result, gt, spec: DatasetSpec, method: str, main: bool) -> None:
    """One method's test-split predictions and the settings that name its traversals, as ``match --out`` writes
    them: ``seqvpr view BENCHMARK`` opens a dataset's runs side by side (``main``: at the benchmark's main L)."""
    import json

    from seqvpr.evaluation.predictions import save_match_predictions
    from seqvpr.io import atomic_folder

    settings = result.settings
    record = {"benchmark_main": main, "settings": {
        "reference": spec.reference, "query": spec.query, "frames": spec.test, "radius": spec.radius,
        "method": method, "descriptor": spec.descriptor,
        "sequence": {"length": settings.sequence.length, "align": settings.sequence.align}}}
    with atomic_folder(folder, "run.json") as tmp:
        save_match_predictions(tmp / "predictions.csv", result, gt)
        (tmp / "run.json").write_text(json.dumps(record, indent=2) + "\n")


def one_line(error: BaseException) -> str:
    text = str(error).strip().splitlines()
    return f"{type(error).__name__}: {text[0] if text else ''}"
