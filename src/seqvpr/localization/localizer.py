"""The online localiser: camera frames (or descriptors) in one at a time, an estimate of where on the map out.

    localizer = Localizer.open("maps/route")             # the map's descriptor and calibrated threshold
    for image in camera:
        estimate = localizer.update(image, timestamp=t)
        if estimate.status == "localised":
            use(estimate.index, estimate.position)

Each estimate carries a score (higher: surer), a status (warming up, localised, uncertain, lost) and the time each
stage took. A run of ``lost_after`` frames below the threshold is ``lost``: the localiser then names no map frame
instead of the nearest one, and finds the route again by itself once the frames match it.
"""

from __future__ import annotations

import json
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
import torch

from seqvpr.data.geo import utm_to_latlon
from seqvpr import checks
from seqvpr.errors import SeqvprError, SettingError, reading
from seqvpr.io import atomic_write, check_output_apart
from seqvpr.localization.saved_state import (
    CALIBRATION_FILE, STATE_FORMAT, STATE_VERSION, calibration_file, check_state_arrays, check_state_header, map_record,
    read_calibration_file,
)
from seqvpr.maps.files import SavedMap, open_map
from seqvpr.matchers.rows import frame_row
from seqvpr.sequences.frame_pass import FrameRow
from seqvpr.progress import LOGGER
from seqvpr.methods import METHODS, get_method
from seqvpr.sequences.filter import FilterSettings
from seqvpr.threads import ensure_policy

if TYPE_CHECKING:
    from seqvpr.results import Scored
    from seqvpr.models.registry import TrainedModel

Status = Literal["warming up", "localised", "uncertain", "lost"]
LONG_OPEN = 100_000  # maps from this many frames take seconds to open: say so


def online_methods() -> tuple[str, ...]:
    """The methods a localiser runs: those whose matcher steps exactly, a frame at a time (constant-velocity
    sequence matching, the filter)."""
    return tuple(name for name, m in METHODS.items()
                 if (m.family == "matching" and m.search == "velocity") or m.family == "filter")


@dataclass(frozen=True)
class LocalizerSettings:
    """How the localiser matches (``method``, ``seq_len``, K, an optional shortlist of S per frame with ``history``),
    when a match is localised (``threshold`` on the score; None: the map's calibration, else a default), when it is
    lost (``lost_after`` frames below it), the score's ``exclusion`` (frames around the best that do not count as
    another place), keyframe gating (``keyframe_distance``: skip frames closer than this to the last kept one; 0:
    off) and the filter's settings (``hmm``)."""

    method: str = "matching"
    seq_len: int = 5
    k: int = 20
    shortlist: int = 0
    history: int = 0
    nprobe: int = 16
    threshold: float | None = None
    lost_after: int = 5
    exclusion: int = 10
    keyframe_distance: float = 0.0
    filter: FilterSettings = field(default_factory=FilterSettings)
    seed: int = 0

    def __post_init__(self) -> None:
        online = online_methods()
        if checks.text(self.method, "method") not in online:
            get_method(self.method)  # an unknown name: one line listing the methods
            raise SettingError(f"a localiser runs {', '.join(online)}, not {{method}} {self.method}")
        for name, least in (("seq_len", 1), ("k", 1), ("lost_after", 1), ("shortlist", 0), ("history", 0),
                            ("exclusion", 0), ("nprobe", 1), ("seed", 0)):
            object.__setattr__(self, name, checks.whole(getattr(self, name), name, least))
        if self.threshold is not None:
            object.__setattr__(self, "threshold", checks.finite(self.threshold, "threshold"))
        object.__setattr__(self, "keyframe_distance", checks.finite(self.keyframe_distance, "keyframe_distance", 0.0))
        checks.instance(self.filter, "filter", FilterSettings, "a FilterSettings")
        if self.shortlist and get_method(self.method).family != "matching":
            raise SettingError(f"{{method}} {self.method} keeps a belief over every map frame: it takes no {{shortlist}}")
        if self.history and not self.shortlist:
            raise SettingError(f"{{history}} H needs a {{shortlist}} (got H = {self.history})")

    @property
    def window(self) -> int:
        """Frames a sequence spans: the method's own (1 for single-image retrieval and the filter), else
        ``seq_len``."""
        return get_method(self.method).length or self.seq_len

    def key(self) -> dict[str, Any]:
        """What a calibrated threshold depends on (the score's meaning), as stored in ``localizer.json``."""
        values = {"method": self.method, "length": self.window, "shortlist": self.shortlist, "history": self.history,
                  "exclusion": self.exclusion}
        if self.method == "hmm":
            values["filter"] = self.filter.as_dict()
        return values


@dataclass(frozen=True)
class Estimate:
    """Where the localiser places one query frame.

    ``index``, ``position``, ``latlon`` and ``name`` are the map frame the localiser stands behind: set only when
    ``status`` is ``localised``, None while warming up, uncertain or lost (nothing else can be acted on).
    ``best`` is the best-scoring map frame whatever the status (None while warming up): a diagnostic, not an
    estimate. ``indices``/``distances`` the top-K (sequence distances; 1 - belief mass for the filter);
    ``latency`` milliseconds per stage (describe, distance, sequence, total); ``kept`` False for a frame keyframe
    gating skipped (the previous estimate is repeated)."""

    frame: int
    index: int | None
    best: int | None
    score: float
    status: Status
    indices: np.ndarray
    distances: np.ndarray
    position: tuple[float, ...] | None
    name: str | None
    timestamp: float | None
    latency: dict[str, float]
    kept: bool = True
    latlon: tuple[float, float] | None = None

    @property
    def localized(self) -> bool:
        """Whether the localiser stands behind this estimate (the one word for it: ``localised``)."""
        return self.status == "localised"

    @property
    def localised(self) -> bool:
        """Deprecated (kept one release): ``localized``."""
        import warnings

        warnings.warn("Estimate.localised is deprecated: use Estimate.localized", DeprecationWarning, stacklevel=2)
        return self.localized


class Localizer:
    """A streaming localiser over a saved map (``Localizer.open``); ``update`` per frame, ``reset`` on a restart."""

    def __init__(self, saved: SavedMap, settings: LocalizerSettings, models: Mapping[str, TrainedModel],
                 threshold: float, device: str = "cpu", threshold_source: str = "given", engine: str = "auto") -> None:
        self.saved, self.settings, self.models, self.threshold = saved, settings, dict(models), threshold
        self.threshold_source = threshold_source  # where the threshold came from: given, calibrated on what, default
        self.encoder = _frame_encoder(saved, self.models, device, engine)
        self.transform = self.models.get("seqmatchnet")  # the map holds transformed frames; raw descriptors get it
        self.matcher = method_matcher(saved, settings)
        self.stepper = _stepper(saved, self.matcher, settings)
        self.frame, self.misses, self.since_reset = 0, 0, 0
        self.rows = (FrameRow.empty(saved.info.dim), FrameRow.empty(saved.info.dim))  # each frame's, reused
        self.last_kept: FrameRow | None = None
        self.last: Estimate | None = None

    @classmethod
    def open(cls, map_folder: str | Path | SavedMap, model: str | Path | Sequence[str | Path] | None = None,
             device: str = "cpu", engine: str = "auto", **settings: Any) -> Localizer:
        """A localiser over the map in ``map_folder`` (or the map opened) with ``LocalizerSettings(**settings)``,
        camera frames described by ``engine`` (``features.engines``: torch, onnx or auto);
        ``model`` the folder(s) the map was built through (checked by sha256), or a SeqMatchNet model applied to both
        sides. ``method`` None (or left out): the SeqMatchNet model's method when one is given, else ``matching``."""
        ensure_policy()  # the one thread policy (seqvpr.threads)
        started = time.perf_counter()
        checks.text(engine, "engine", checks.ENGINES)  # whether ONNX Runtime is there: when an encoder is built
        saved = map_folder if isinstance(map_folder, SavedMap) else open_map(checks.a_path(map_folder, "map_folder"))
        models = _load_models(saved, model, checks.device(device))
        unknown = sorted(set(settings) - {f.name for f in fields(LocalizerSettings)})
        if unknown:
            raise SettingError(f"a localiser has no setting {unknown[0]!r} (its settings: "
                               f"{', '.join(f.name for f in fields(LocalizerSettings))})")
        if settings.get("method") is None:  # a SeqMatchNet model's own method, else plain sequence matching
            settings = {**settings, "method": "seqmatchnet" if "seqmatchnet" in models else "matching"}
        chosen = LocalizerSettings(**settings)
        _check_window(saved, chosen)
        _check_index(saved, chosen)
        if saved.info.count >= LONG_OPEN or models:  # seconds to read the map's norms or to build a network
            LOGGER.info(f"localiser: opening {saved.folder} ({saved.info.count} frames, {saved.info.dim}-D), "
                        f"{chosen.method}")
        if "seqmatchnet" in models and "seqmatchnet" not in (saved.info.model or {}):
            raise SeqvprError(f"a localiser compares frames as {saved.folder} stores them: build the map through the "
                              "SeqMatchNet model (seqvpr map build --model) to localise with it")
        if chosen.method == "seqmatchnet" and "seqmatchnet" not in models:
            raise SettingError("{method} seqmatchnet needs its SeqMatchNet {model} (the one the map was built through)")
        threshold, source = ((chosen.threshold, "given") if chosen.threshold is not None
                             else stored_threshold(saved.folder, chosen))
        localizer = cls(saved, chosen, models, threshold, device, source, engine)
        ensure_policy()  # again after building the matcher: numba's launch must not have changed a count
        if time.perf_counter() - started >= 1.0:
            LOGGER.info(f"localiser: ready in {time.perf_counter() - started:.1f} s; threshold {threshold:g}, {source}")
        return localizer

    @property
    def uses_default_threshold(self) -> bool:
        """Whether the threshold is the method's uncalibrated default (worth a warning)."""
        return self.threshold_source == default_source(self.settings.method)

    def reset(self) -> None:
        """Start over: a new drive, a kidnapping, a restart with no trusted state."""
        self.stepper.reset()
        self.misses, self.since_reset, self.last_kept, self.last = 0, 0, None, None

    def update(self, frame: Any, timestamp: float | None = None) -> Estimate:
        """The estimate after one more frame: a camera image (path, PIL image, H x W x 3 uint8 array) or a
        descriptor [D]. A bad frame is a one-line error and leaves the localiser as it was."""
        started = time.perf_counter()
        if timestamp is not None:
            timestamp = checks.finite(timestamp, "timestamp")
        row = self._describe(frame, self.rows[0] if self.last_kept is not self.rows[0] else self.rows[1])
        described = time.perf_counter()
        gate = self.settings.keyframe_distance
        if gate and self.last is not None and self.last_kept is not None \
                and float(torch.linalg.vector_norm(row.vector - self.last_kept.vector)) < gate:
            self.frame += 1
            latency = {**self.last.latency, "describe": (described - started) * 1e3}
            return replace(self.last, frame=self.frame - 1, timestamp=timestamp, latency=latency, kept=False)
        scored = self.stepper.push(row)
        self.last_kept, self.since_reset = row, self.since_reset + 1  # the next frame goes into the other row
        estimate = self._estimate(scored, timestamp, (described - started) * 1e3, started)
        self.frame += 1
        self.last = estimate
        return estimate

    def _describe(self, frame: Any, out: FrameRow) -> FrameRow:
        """The frame as a map frame, in ``out``: described (images), transformed (SeqMatchNet at match time),
        normalised."""
        if isinstance(frame, (list, tuple)):  # a descriptor as numbers
            frame = np.asarray(frame)
        if isinstance(frame, torch.Tensor):
            frame = frame.detach().cpu()
            frame = (frame.float() if frame.dtype == torch.bfloat16 else frame).numpy()
        array = frame if isinstance(frame, np.ndarray) else None
        is_descriptor = array is not None and array.ndim == 1 and array.dtype != np.uint8
        if is_descriptor and not np.issubdtype(array.dtype, np.floating):
            raise SettingError(f"a frame's descriptor must be floating point, got {array.dtype}")
        if is_descriptor:
            vector = array.astype(np.float32, copy=False)
        elif self.encoder is None:
            raise SeqvprError(f"{self.saved.folder} holds descriptor-file frames: update() takes a descriptor [D]")
        else:
            vector = self.encoder.encode(frame)
        wanted = self.saved.info.dim if self.transform is None else self.transform.module.config.in_dim
        if tuple(vector.shape) != (wanted,):
            held = f"{self.saved.info.dim}-D frames" if self.transform is None else \
                f"frames of {wanted}-D descriptors through its SeqMatchNet model"
            raise SeqvprError(f"a frame of shape {tuple(vector.shape)}: {self.saved.folder} holds {held}")
        if self.transform is not None:  # the map holds transformed frames: the one place the transform is applied
            vector = frame_row(vector, self.transform.module, normalize=False).numbers
        row = self.matcher.prepare_frame(vector, out)  # the row a frame never held (``out`` is not ``last_kept``)
        if not row.finite():  # non-finite values stay so through the transform and normalising
            raise SeqvprError("the frame's descriptor holds NaN or infinite values")
        return row

    def _estimate(self, scored: Scored | None, timestamp: float | None, describe_ms: float, started: float) -> Estimate:
        status, self.misses = next_status(None if scored is None else scored.score, self.threshold, self.misses,
                                          self.settings.lost_after)
        if scored is None:
            empty = np.zeros(0, np.int64)
            latency = {"describe": describe_ms, "distance": 0.0, "sequence": 0.0}
            return Estimate(self.frame, None, None, float("nan"), status, empty, empty.astype(float), None, None,
                            timestamp, {**latency, "total": (time.perf_counter() - started) * 1e3})
        best = int(scored.indices[0])
        latency = {"describe": describe_ms, "distance": scored.distance_ms, "sequence": scored.sequence_ms,
                   "total": (time.perf_counter() - started) * 1e3}
        index = best if status == "localised" else None
        position, name, latlon = self._place(index)
        return Estimate(self.frame, index, best, scored.score, status, scored.indices, scored.distances, position,
                        name, timestamp, latency, latlon=latlon)

    def _place(self, row: int | None) -> tuple[tuple[float, ...] | None, str | None, tuple[float, float] | None]:
        """The map frame's position, name and latitude/longitude, where the map has them (none for no frame)."""
        frames = self.saved.frames
        if row is None:
            return None, None, None
        name = frames.names[row] if frames.names is not None else None
        if frames.positions is None:
            return None, name, None
        position = tuple(float(v) for v in frames.positions[row])
        latlon = utm_to_latlon(frames.positions[row], frames.crs)
        return position, name, None if latlon is None else (float(latlon[0, 0]), float(latlon[0, 1]))

    def check_state_path(self, path: str | Path) -> None:
        """A state file may not land on what the localiser reads (its map folder and files, its model folders): one
        line before anything is written (a node checks it at start, not at its last frame)."""
        if checks.a_path(path, "path").is_dir():
            raise SettingError(f"the state file {path} is a folder; give a file name (.npz)")
        check_output_apart(path, [self.saved.folder, *(model.folder for model in self.models.values())],
                           "the state file")

    def save_state(self, path: str | Path, extra: Mapping[str, Any] | None = None) -> None:
        """Everything a restarted robot needs to go on where it stopped (written atomically, ``.npz``); ``extra``
        (JSON values) is what the caller keeps beside it (``restore`` returns it), in the same file."""
        self.check_state_path(path)
        header = {"format": STATE_FORMAT, "version": STATE_VERSION, "map": map_record(self.saved.info),
                  "settings": self.settings.key(), "frame": self.frame, "misses": self.misses,
                  "since_reset": self.since_reset, "extra": _json_extra(extra)}
        arrays = {f"matcher_{k}": v for k, v in self.stepper.state().items()}
        if self.last_kept is not None:
            arrays["last_kept"] = self.last_kept.numbers
        with atomic_write(path, "wb") as handle:
            np.savez(handle, header=np.array(json.dumps(header)), **arrays)

    def restore(self, path: str | Path) -> dict[str, Any]:
        """Go on from a state ``save_state`` wrote, for this map (by its identity) and these settings, its counters
        and arrays sound (``localization.saved``); anything else is one line and leaves the localiser as it was.
        Returns the ``extra`` saved with it ({} if none)."""
        from seqvpr.arrays import open_npz

        checks.a_path(path, "path")
        with reading(path, "a localiser state"):
            with open_npz(path) as data:
                header = json.loads(str(data["header"]))
                arrays = {k: data[k] for k in data.files}
            check_state_header(path, header, self.saved.info)
            if header.get("settings") != self.settings.key():
                raise SeqvprError(f"{path}: saved with other settings ({header.get('settings')})")
            check_state_arrays(path, arrays, self.saved.info.dim)
            self.stepper.load_state({k.removeprefix("matcher_"): v for k, v in arrays.items()
                                     if k.startswith("matcher_")})
            self.frame, self.misses, self.since_reset = (int(header[k]) for k in ("frame", "misses", "since_reset"))
            self.last_kept = FrameRow.of(arrays["last_kept"]) if "last_kept" in arrays else None
        extra = header.get("extra", {})
        return extra if isinstance(extra, dict) else {}


def _json_extra(extra: Any) -> dict[str, Any]:
    """What a caller keeps beside a saved state: a mapping of JSON values (None: nothing), checked before writing."""
    if extra is None:
        return {}
    checks.instance(extra, "extra", Mapping, "a mapping of JSON values (or None)")
    try:
        json.dumps(dict(extra), allow_nan=False)
    except (TypeError, ValueError) as error:
        raise SettingError(f"{{extra}} must hold JSON values only ({error})") from None
    return dict(extra)


def _load_models(saved: SavedMap, model: str | Path | Sequence[str | Path] | None, device: str) -> dict[str, TrainedModel]:
    """The models given (folders), checked against those the map was built through (none read when neither has
    any, so a localiser over a descriptor map imports no model code)."""
    folders = [] if model is None else checks.paths(model, "model")
    if not folders and not saved.info.model:
        return {}
    from seqvpr.maps.match import check_map_models
    from seqvpr.models.registry import load_models

    models = load_models(folders, device)
    check_map_models(saved.info, str(saved.folder), "matching", models)
    return models


def _frame_encoder(saved: SavedMap, models: Mapping[str, TrainedModel], device: str, engine: str = "auto"):
    """Camera frames to map frames when the map was described from images (None for descriptor-file maps)."""
    if saved.info.description.get("descriptor") == "file":
        return None
    from seqvpr.localization.encoder import ImageDescriber
    from seqvpr.maps.build import FrameDescription

    return ImageDescriber(FrameDescription.from_json(saved.info.description), models, device, engine)


def next_status(score: float | None, threshold: float, misses: int, lost_after: int) -> tuple[Status, int]:
    """The status of a frame with ``score`` (None: no window yet) and the run of frames below the threshold so far."""
    if score is None:
        return "warming up", misses
    if score >= threshold:
        return "localised", 0
    misses += 1
    return ("lost" if misses >= lost_after else "uncertain"), misses


def method_matcher(saved: SavedMap, settings: LocalizerSettings):
    """The settings' method as its family's matcher over the map's frames as stored (causal windows; normalised as
    the map is; a SeqMatchNet map's frames already transformed, so plain sequence matching)."""
    from seqvpr.methods import build_matcher
    from seqvpr.sequences.match_settings import MatchSettings
    from seqvpr.sequences.windows import SequenceSpec

    method = "matching" if settings.method == "seqmatchnet" else settings.method
    common = MatchSettings(SequenceSpec(settings.window, "causal"), k=settings.k, normalize=saved.info.normalized)
    return build_matcher(method, common, {}, filter=settings.filter, seed=settings.seed)


def _stepper(saved: SavedMap, matcher, settings: LocalizerSettings):
    """The matcher stacked for the map (``matchers.assemble``) and stepped a frame at a time: with a shortlist, over
    the map's index (a sharded map's: its shards' indexes merged). One process reads a sharded map's rows through its
    shards as one map; under torchrun, without a shortlist, each rank steps its own shards."""
    from seqvpr import distributed
    from seqvpr.maps.files import open_sharded_map
    from seqvpr.matchers.stack import Shortlist, assemble

    world = distributed.current()
    sharded = open_sharded_map(saved.folder) if saved.stored == "sharded" else None  # rows read through shards
    reference = sharded if sharded is not None and world.size > 1 and not settings.shortlist else saved
    listed = None
    if settings.shortlist:
        listed = Shortlist(lambda: frame_neighbors(saved if sharded is None else sharded, settings.nprobe, world),
                           settings.shortlist, settings.history)
    return assemble(matcher, reference, listed, world).stream(reference, settings.exclusion)


def frame_neighbors(reference, nprobe: int, world):
    """The map's index (a sharded map's: its shards' merged) as a shortlist's search, which a frame at a time must
    be over frames."""
    from seqvpr.maps.match import map_neighbors

    neighbors = map_neighbors(reference, nprobe, 0, world)
    if neighbors.over != "frames":
        raise SettingError(f"{{shortlist}} needs an index over {reference.folder}'s frames: seqvpr map index "
                          f"{reference.folder} --index SPEC")
    return neighbors


def _check_window(saved: SavedMap, settings: LocalizerSettings) -> None:
    """A window longer than every segment of the map would never be complete: the localiser would never answer."""
    if settings.method == "hmm":
        return
    longest = int(np.unique(saved.frames.segment_ids, return_counts=True)[1].max())
    if settings.window > longest:
        raise SettingError(f"{{seq_len}} {settings.window} is longer than every segment of {saved.folder} (longest: "
                           f"{longest} frames): it would never localise")


def _check_index(saved: SavedMap, settings: LocalizerSettings) -> None:
    """A shortlist needs the map's index over frames (a sharded map's shards are checked as they open)."""
    if settings.shortlist and saved.stored != "sharded" and (saved.index or {}).get("over") != "frames":
        raise SettingError(f"{{shortlist}} needs an index over {saved.folder}'s frames: seqvpr map index "
                          f"{saved.folder} --index SPEC")


# --- calibrated thresholds, kept with the map ---------------------------------------------------------------------

def stored_threshold(folder: str | Path, settings: LocalizerSettings) -> tuple[float, str]:
    """The threshold ``seqvpr localize --calibrate`` stored for these settings, else the method's default; with
    where it came from, in words."""
    entry = stored_calibration(folder, settings)
    if entry is not None:
        return float(entry["threshold"]), calibration_source(entry)
    return get_method(settings.method).threshold, default_source(settings.method)


def default_source(method: str) -> str:
    """Where a default threshold came from, in words (the words ``Localizer.uses_default_threshold`` looks for)."""
    return f"the default for {method}, not calibrated on this map (seqvpr localize --calibrate)"


def stored_calibration(folder: str | Path, settings: LocalizerSettings) -> dict[str, Any] | None:
    """The calibration record ``localizer.json`` holds for these settings, if any."""
    return next((e for e in read_calibrations(folder) if e.get("settings") == settings.key()), None)


def calibration_source(entry: dict[str, Any]) -> str:
    """Where a calibrated threshold came from: the traversal, frames and ground truth, and the precision reached."""
    frames = entry.get("query_frames") or "all"
    truth = entry.get("ground_truth") or "?"
    reached = ("reached" if entry.get("reached") else "NOT reached") + f" ({entry.get('precision', float('nan')):.3f})"
    return (f"calibrated on {entry.get('calibration', '?')} frames {frames}, ground truth {truth}, target precision "
            f"{entry.get('target_precision')} {reached}, {entry.get('created', '')}").rstrip(", ")


def read_calibrations(folder: str | Path) -> list[dict[str, Any]]:
    """The calibrations in the map's ``localizer.json``, checked (``localization.saved``)."""
    return read_calibration_file(folder)


def store_calibration(folder: str | Path, settings: LocalizerSettings, record: dict[str, Any]) -> None:
    """Keep a calibrated threshold with the map (replacing one for the same settings), atomically."""
    kept = [e for e in read_calibration_file(folder, replacing=True) if e.get("settings") != settings.key()]
    kept.append({"settings": settings.key(), **record})
    with atomic_write(Path(folder) / CALIBRATION_FILE) as handle:
        json.dump(calibration_file(kept, folder), handle, indent=2)

