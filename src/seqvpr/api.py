"""seqvpr in a few calls: load traversals, match a query against any reference by a method's name, evaluate.

    import seqvpr
    reference = seqvpr.load_traversal("day.npz", "reference")
    query = seqvpr.load_traversal("night.npz", "query")
    result = seqvpr.match(reference, query, "matching", seq_len=5)
    print(seqvpr.evaluate(result, radius="2f").recall)

``seqvpr match`` on the command line is these calls plus reading options and writing files.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any, get_args

from seqvpr import checks
from seqvpr.errors import SeqvprError, SettingError

if TYPE_CHECKING:
    from seqvpr.data.traversal import Traversal
    from seqvpr.evaluation.metrics import Evaluation
    from seqvpr.results import MatchResult
    from seqvpr.sequences.match_settings import MatchSettings
    from seqvpr.models.registry import TrainedModel
    from seqvpr.progress import ProgressFactory

from seqvpr.sequences.match_settings import DEFAULT_BUDGET  # noqa: E402  (re-exported: the API's default)
#: the match settings ``match`` takes by name (``match_settings``)
SETTING_NAMES = ("k", "align", "boundary", "velocities", "normalize", "dtype", "device", "memory_budget")


def load_models(models: Iterable[str | Path] | Mapping[str, TrainedModel] | None,
                device: str = "cpu") -> dict[str, TrainedModel]:
    """Models by kind: model folders loaded (``models.registry.load_models``: one per kind), or a mapping of loaded
    ones as given."""
    from seqvpr.models.registry import load_models as load_folders

    if models is None:
        return {}
    if isinstance(models, Mapping):
        from seqvpr.models.registry import TrainedModel

        for model in models.values():
            checks.instance(model, "models", TrainedModel, "model folders or loaded models by kind")
        return dict(models)
    return load_folders(checks.paths(models, "models"), device)


def open_reference(reference: Any) -> Any:
    """A reference as the matchers take it: a traversal, a saved map or a sharded map as given, else the path of
    one (a sharded map's folder, a map's folder, or a traversal file or folder, which is loaded)."""
    if not isinstance(reference, (str, Path)):
        return reference
    from seqvpr.data.sources import load_traversal
    from seqvpr.maps.files import INFO_FILE, is_sharded_map, open_map, open_sharded_map

    if is_sharded_map(reference):
        return open_sharded_map(reference)
    if (Path(reference) / INFO_FILE).is_file():
        return open_map(reference)
    return load_traversal(str(reference), "reference")


def match_settings(method: str, models: Mapping[str, TrainedModel], seq_len: int | None = None, *, k: int = 20,
                   align: str = "centered", boundary: str = "drop", velocities: Iterable[float] = (1.0,),
                   normalize: bool = True, dtype: str = "float32", device: str = "cpu",
                   memory_budget: int | None = DEFAULT_BUDGET) -> MatchSettings:
    """The settings of a match: windows of ``seq_len`` frames (the method's or its model's length when None; a method
    of fixed length refuses another), checked before any data is read."""
    from seqvpr.sequences.match_settings import MatchSettings
    from seqvpr.methods import check_run, run_length
    from seqvpr.sequences.windows import SequenceSpec

    chosen = check_run(method, models, 0, seq_len)
    length = seq_len if seq_len is not None else run_length(chosen, models)
    spec = SequenceSpec(length, align, boundary, velocities)  # type: ignore[arg-type]  (text, one number or several)
    return MatchSettings(spec, k, normalize, dtype, device, memory_budget)


def match(
    reference: Any,
    query: Traversal | str | Path,
    method: str = "matching",
    *,
    seq_len: int | None = None,
    models: Iterable[str | Path] | Mapping[str, TrainedModel] | None = None,
    settings: MatchSettings | None = None,
    shortlist: int = 0,
    history: int = 0,
    nprobe: int = 16,
    rerank: int = 0,
    index: str = "flat",
    steps: tuple[int, int] | None = None,
    contrast_window: int | None = None,
    proposer: str | None = None,
    progress: ProgressFactory | None = None,
    **conf: Any,
) -> MatchResult | None:
    """The K best reference frames of every query frame by ``method`` (any name in ``seqvpr.methods.METHODS``).

    ``reference``: a traversal with descriptors, a saved map, a sharded map, or the path of one; ``query``: a
    traversal or its file (described as a map's frames were, against a map). ``models``: model folders or loaded
    models by kind. ``settings`` (``MatchSettings``), or its fields in ``conf`` (``k``, ``align``, ``boundary``,
    ``velocities``, ``normalize``, ``dtype``, ``device``, ``memory_budget``); the method's own: ``steps``,
    ``contrast_window``, ``rerank`` N, ``index``, ``proposer`` (hvpr's retrieval method); against a map with an index, ``shortlist`` S a frame with
    ``history`` H. Under ``torchrun`` over a sharded map, ranks other than 0 get None.
    """
    from seqvpr.features.describe import check_extraction_settings
    from seqvpr.methods import check_run

    extraction = {key: conf.pop(key) for key in ("cache_dir", "skip_bad", "engine") if key in conf}
    check_extraction_settings(**extraction)
    check_setting_names(conf)
    search = check_match_arguments(method, settings, shortlist=shortlist, history=history, nprobe=nprobe,
                                   rerank=rerank, index=index, steps=steps, contrast_window=contrast_window,
                                   proposer=proposer, progress=progress)
    device = (settings.device if settings else conf.get("device")) or "cpu"
    models = load_models(models, device)
    check_run(method, models, rerank, seq_len)
    settings = settings or match_settings(method, models, seq_len, **conf)
    reference, query = opened_sides(reference, query)
    options = {"shortlist": shortlist, "history": history, "nprobe": nprobe, "rerank": rerank, "index": index,
               "progress": progress, "search": search}
    return match_reference(reference, query, method, settings, models, **options, **extraction)


def check_match_arguments(method: Any, settings: Any, *, shortlist: Any, history: Any, nprobe: Any, rerank: Any,
                          index: Any, steps: Any, contrast_window: Any, proposer: Any,
                          progress: Any) -> dict[str, Any]:
    """``match``'s own arguments checked (types and ranges, one line naming the argument); the method's search
    options returned as its matcher takes them."""
    from seqvpr.sequences.retrieval import INDEX_KINDS
    from seqvpr.methods import get_method
    from seqvpr.sequences.match_settings import MatchSettings
    from seqvpr.sequences.windows import check_steps

    checks.text(method, "method")
    if settings is not None:
        checks.instance(settings, "settings", MatchSettings, "a MatchSettings (or None)")
    for name, value in (("shortlist", shortlist), ("history", history), ("rerank", rerank)):
        checks.whole(value, name, 0)
    checks.whole(nprobe, "nprobe", 1)
    checks.text(index, "index", INDEX_KINDS)
    checks.function(progress, "progress")
    if history and not shortlist:
        raise SettingError(f"{{history}} H needs a {{shortlist}} S >= 1 (got S = {shortlist}, H = {history})")
    search: dict[str, Any] = {"steps": None if steps is None else check_steps(steps),
                              "contrast_window": checks.optional_whole(contrast_window, "contrast_window", 2)}
    if proposer is not None:
        try:
            search["proposer"] = get_method(checks.text(proposer, "proposer")).name
        except SeqvprError as error:
            raise SettingError(f"{{proposer}}: {error}") from None
    return search


def check_setting_names(conf: Mapping[str, Any]) -> None:
    """A setting ``match`` does not know is a one-line error naming it and the ones it knows."""
    unknown = sorted(set(conf) - set(SETTING_NAMES))
    if unknown:
        raise SeqvprError(f"seqvpr.match: no setting {unknown[0]!r} (settings: {', '.join(SETTING_NAMES)}, "
                          "shortlist, history, nprobe, rerank, index, steps, contrast_window, proposer, cache_dir, "
                          "skip_bad, engine)")


def opened_sides(reference: Any, query: Any) -> tuple[Any, Traversal]:
    """Both sides opened from their paths, each checked to be what a match takes (one line otherwise)."""
    from seqvpr.data.sources import load_traversal

    reference = open_reference(reference)
    if isinstance(query, (str, Path)):
        query = load_traversal(str(query), "query")
    for side, given in (("reference", reference), ("query", query)):
        shaped = hasattr(given, "segment_ids") or (side == "reference" and hasattr(given, "shards"))
        if not shaped or (side == "query" and not hasattr(given, "descriptors")):
            raise SeqvprError(f"seqvpr.match: the {side} must be a traversal{', a map' if side == 'reference' else ''}"
                              f" or the path of one, not {type(given).__name__}")
    return reference, query


def match_reference(reference: Any, query: Traversal, method: str, settings: MatchSettings,
                    models: Mapping[str, TrainedModel], *, shortlist: int, history: int, nprobe: int, rerank: int,
                    index: str, progress: ProgressFactory | None, search: Mapping[str, Any],
                    **extraction: Any) -> MatchResult | None:
    """``match`` once its inputs are opened. A saved or sharded map describes the query as it described its frames
    and checks the models it was built through (``maps.match.match_map``); a traversal is matched as it is. Either
    way the method's matcher is stacked for the reference by ``matchers.assemble``."""
    from seqvpr.maps.match import is_map, match_map
    from seqvpr.matchers.stack import assemble
    from seqvpr.methods import build_matcher

    if is_map(reference):
        return match_map(reference, query, method, settings, models, index=index, rerank=rerank,
                         shortlist=shortlist, history=history, nprobe=nprobe, progress=progress, search=search,
                         **extraction)
    if shortlist:
        raise SettingError(f"{{shortlist}} S needs a map with an index (seqvpr map build --index), not the traversal "
                          f"{reference.source or reference.name}")
    matcher = build_matcher(method, settings, models, index=index, rerank=rerank, progress=progress, **search)
    return assemble(matcher, reference).topk(reference, query)


def evaluate(result: MatchResult, radius: str | None = None, ground_truth: str | Path | None = None,
             ks: Iterable[int] = (1, 5, 10, 20), no_positive: str = "exclude",
             uniqueness: int | None = None) -> Evaluation:
    """Recall@K (and precision-recall) of a match against ground truth: within ``radius`` (``25m`` or ``2f``) of
    the positions, or from a ground-truth file."""
    from seqvpr.evaluation.ground_truth import resolve_ground_truth
    from seqvpr.evaluation.metrics import NoPositivePolicy
    from seqvpr.evaluation.scoring import evaluate_match
    from seqvpr.results import MatchResult

    checks.instance(result, "result", MatchResult, "a MatchResult (what seqvpr.match returns)")
    if radius is not None and (isinstance(radius, bool) or not isinstance(radius, (str, int, float))):
        raise SettingError(f"{{radius}} must be text such as '25m' or '2f', got {checks.shown(radius)}")
    ground_truth = None if ground_truth is None else str(checks.a_path(ground_truth, "ground_truth"))
    ks = checks.whole_numbers(ks, "ks")
    checks.text(no_positive, "no_positive", get_args(NoPositivePolicy))
    uniqueness = checks.optional_whole(uniqueness, "uniqueness", 0)
    gt = resolve_ground_truth(result.reference, result.query, radius, ground_truth)
    return evaluate_match(result, gt, ks, no_positive, uniqueness)

