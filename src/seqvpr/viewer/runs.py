"""seqvpr's output folders read back for the viewer (``seqvpr.cli.view`` is its command): a ``match --out`` folder
(``predictions.csv``, ``run.json``), a ``localize --out`` folder (``stream.csv``), a map folder (``map.json``). Each
becomes plain lists a page can hold: the traversals' routes (positions, else frame order), each query's top-K by
every method, the ground truth, a localisation's timeline. Sources that moved since the run leave their frames
without images or positions, and a note says so; a folder seqvpr did not write is one line.
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from seqvpr.data.traversal import Traversal
from seqvpr.errors import SeqvprError

RUN_KINDS = ("match", "localize", "map")


@dataclass
class Side:
    """One traversal as the page draws it: names, positions [n, 2] (None: frame order), image paths (None: none)."""

    name: str
    names: list[str]
    positions: np.ndarray | None = None
    images: list[str] | None = None
    frame_index: np.ndarray | None = None

    def rows_of(self, frames: np.ndarray) -> np.ndarray:
        """Rows of source frame indices (-1 where the traversal has none)."""
        if self.frame_index is None:
            return np.asarray(frames, dtype=np.int64)
        order = np.argsort(self.frame_index, kind="stable")
        at = np.searchsorted(self.frame_index[order], frames)
        at = np.minimum(at, len(order) - 1)
        found = self.frame_index[order[at]] == frames
        return np.where(found & (np.asarray(frames) >= 0), order[at], -1)


@dataclass
class Method:
    """One method's top-K for each query row (reference rows, -1 none; distances) and whether its top-1 is right
    (1, 0, or -1 where the query has no true match)."""

    name: str
    refs: np.ndarray
    distances: np.ndarray
    correct: np.ndarray


@dataclass
class View:
    """What one page shows: its kind, the reference and query sides, the methods, each query's positives, a
    localisation's stream, a map's facts, and notes on what could not be found."""

    kind: str
    title: str
    reference: Side
    query: Side | None = None
    methods: list[Method] = field(default_factory=list)
    positives: list[list[int]] | None = None
    stream: dict[str, Any] | None = None
    facts: dict[str, Any] | None = None
    notes: list[str] = field(default_factory=list)


def run_kind(folder: Path) -> str:
    """Which seqvpr output ``folder`` is; anything else is one line."""
    folder = Path(folder)
    if not folder.is_dir():
        raise SeqvprError(f"{folder}: no such folder")
    if (folder / "map.json").is_file():
        return "map"
    if (folder / "metadata.yaml").is_file():
        return "recording"
    if (folder / "stream.csv").is_file() and (folder / "run.json").is_file():
        return "localize"
    if (folder / "predictions.csv").is_file() and (folder / "run.json").is_file():
        return "match"
    if (folder / "run.json").is_file() and benchmark_runs(folder):
        return "benchmark"
    raise SeqvprError(f"{folder}: not a folder seqvpr wrote (no map.json, no match or localize run.json, no "
                      "recorded bag)")


def read_views(folders: list[Path]) -> View:
    """One page's view of the folders: several match runs over the same traversals side by side (a benchmark's
    runs of its first dataset), or one localisation, recording or map."""
    kinds = [run_kind(f) for f in folders]
    if kinds == ["benchmark"]:
        return read_match_views(benchmark_runs(Path(folders[0])))
    if len(folders) > 1 and set(kinds) != {"match"}:
        raise SeqvprError("several folders are compared as match runs only; view a localisation or a map alone")
    if kinds[0] == "map":
        return read_map_view(Path(folders[0]))
    if kinds[0] == "localize":
        return read_localize_view(Path(folders[0]))
    if kinds[0] == "recording":
        return read_recording_view(Path(folders[0]))
    return read_match_views([Path(f) for f in folders])


def benchmark_runs(folder: Path) -> list[Path]:
    """A benchmark folder's runs at its main L, of its first dataset (``experiments.benchmark``:
    ``DATASET/runs/METHOD-LN``); every run of that dataset where none is marked main."""
    for dataset in sorted(p for p in Path(folder).iterdir() if (p / "runs").is_dir()):
        runs = sorted(r for r in (dataset / "runs").iterdir() if (r / "predictions.csv").is_file())
        main = [r for r in runs if read_run_json(r).get("benchmark_main")]
        if runs:
            return main or runs
    return []


def read_run_json(folder: Path) -> dict[str, Any]:
    try:
        record = json.loads((folder / "run.json").read_text())
    except (OSError, ValueError) as error:
        raise SeqvprError(f"{folder / 'run.json'}: unreadable ({error})") from None
    if not isinstance(record, dict):
        raise SeqvprError(f"{folder / 'run.json'}: not a seqvpr run record")
    return record


def source_side(source: Any, role: str, frames: str | None, notes: list[str]) -> tuple[Side, Traversal | None]:
    """The traversal a run names (a map folder or a source), cut as the run cut it; a source that cannot be read
    now gives a side of frame numbers only and a note."""
    from seqvpr.data.sources import load_traversal
    from seqvpr.data.traversal import slice_frame_range

    try:
        if (Path(str(source)) / "map.json").is_file():
            from seqvpr.maps.files import open_map

            traversal = open_map(str(source)).frames
        else:
            traversal = slice_frame_range(load_traversal(str(source), role), frames)  # type: ignore[arg-type]
    except (SeqvprError, OSError, TypeError) as error:
        notes.append(f"the {role} {source} cannot be read now ({str(error).splitlines()[0]}): its frames are shown "
                     "without images or positions")
        return Side(str(source), []), None
    return side_of(traversal, str(source), notes), traversal


def side_of(traversal: Traversal, name: str, notes: list[str]) -> Side:
    """A traversal's names, positions and image paths (images that are gone are noted, and shown as placeholders)."""
    images = list(traversal.image_paths) if traversal.image_paths is not None else None
    if images and not Path(images[0]).is_file() and not Path(images[-1]).is_file():
        notes.append(f"the images of {name} have moved or are gone: shown as placeholders")
    positions = None if traversal.positions is None else np.asarray(traversal.positions, dtype=np.float64)[:, :2]
    return Side(name, list(traversal.frame_names()), positions, images, np.asarray(traversal.frame_index))


def read_match_views(folders: list[Path]) -> View:
    """Match runs over the same reference and query, each a method of the page."""
    from seqvpr.data.ground_truth import ground_truth_within_radius, parse_radius

    records = [read_run_json(f) for f in folders]
    settings = records[0].get("settings") or {}
    if "reference" not in settings or "query" not in settings:
        raise SeqvprError(f"{folders[0] / 'run.json'}: not a match run (no settings.reference and settings.query)")
    for folder, record in zip(folders[1:], records[1:]):
        other = record.get("settings") or {}
        if (other.get("reference"), other.get("query")) != (settings["reference"], settings["query"]):
            raise SeqvprError(f"{folder}: matched other traversals than {folders[0]}; compare runs over the same pair")
    notes: list[str] = []
    reference, ref_traversal = source_side(settings["reference"], "reference", settings.get("frames"), notes)
    query, qry_traversal = source_side(settings["query"], "query", settings.get("frames"), notes)
    methods = [read_method(f, r, reference, query) for f, r in zip(folders, records)]
    if not any(len(m.refs) for m in methods):
        raise SeqvprError(f"{folders[0] / 'predictions.csv'}: a match of 0 queries; nothing to view")
    positives = None
    if ref_traversal is not None and qry_traversal is not None and settings.get("radius"):
        try:
            gt = ground_truth_within_radius(qry_traversal, ref_traversal, parse_radius(settings["radius"]))
            positives = [gt.positives.indices[a:b].tolist() for a, b in zip(gt.positives.indptr[:-1],
                                                                            gt.positives.indptr[1:])]
        except SeqvprError as error:
            notes.append(f"no ground truth: {error}")
    title = " vs ".join(m.name for m in methods)
    return View("match", title, reference, query, methods, positives, notes=notes)


def method_name(folder: Path, record: dict[str, Any]) -> str:
    """A run's label: its folder and the method and L it ran."""
    settings = record.get("settings") or {}
    length = (settings.get("sequence") or {}).get("length")
    return f"{folder.name} ({settings.get('method', '?')}" + (f" L={length})" if length else ")")


def read_method(folder: Path, record: dict[str, Any], reference: Side, query: Side) -> Method:
    """One run's predictions, in rows of the page's traversals."""
    from seqvpr.evaluation.predictions import read_predictions

    found = read_predictions(folder / "predictions.csv")
    n_query = len(query.names) or (int(found.query.max()) + 1 if len(found.query) else 0)
    if not query.names:
        query.names = [str(i) for i in range(n_query)]
    rows = query.rows_of(found.query)
    refs = np.full((n_query, found.references.shape[1]), -1, np.int64)
    distances = np.full(refs.shape, np.inf)
    keep = rows >= 0
    refs[rows[keep]] = np.where(found.references[keep] >= 0,
                                reference.rows_of(found.references[keep].ravel()).reshape(-1, refs.shape[1]), -1)
    distances[rows[keep]] = found.distances[keep]
    correct = np.full(n_query, -1, np.int64)
    flags = read_correct_column(folder / "predictions.csv")
    correct[rows[keep]] = flags[keep]
    if not reference.names and refs.size:
        reference.names = [str(i) for i in range(int(refs.max()) + 1)]
    return Method(method_name(folder, record), refs, distances, correct)


def read_correct_column(path: Path) -> np.ndarray:
    """``predictions.csv``'s ``correct`` column (1, 0; -1 where empty: no true match)."""
    with open(path, newline="") as handle:
        values = [row.get("correct", "") for row in csv.DictReader(handle)]
    return np.array([int(v) if v in ("0", "1") else -1 for v in values], dtype=np.int64)


def read_localize_view(folder: Path) -> View:
    """A localisation: the map's route, the query's frames, and the stream's status, score and estimate a frame."""
    record = read_run_json(folder)
    notes: list[str] = []
    reference, _ = source_side(record.get("map"), "reference", None, notes)
    query, _ = source_side(record.get("query"), "query", record.get("query_frames"), notes)
    with open(folder / "stream.csv", newline="") as handle:
        rows = list(csv.DictReader(handle))
    if not rows:
        raise SeqvprError(f"{folder / 'stream.csv'}: a localisation of 0 frames; nothing to view")
    if not query.names:
        query.names = [r["query_frame"] for r in rows]
    stream = {"status": [r["status"] for r in rows], "score": [_number(r["score"]) for r in rows],
              "localised": [_row(r["localised_row"]) for r in rows], "best": [_row(r["best_row"]) for r in rows],
              "correct": [_row(r.get("correct")) for r in rows], "threshold": record.get("threshold"),
              "columns": list(rows[0]), "rows": [list(r.values()) for r in rows]}
    return View("localize", f"localisation: {folder.name}", reference, query, stream=stream, notes=notes)


def _number(text: str | None) -> float | None:
    """A number from a CSV cell or a status value (None where empty, or written as nan)."""
    return float(text) if text not in ("", "nan", None) else None


def _row(text: str | None) -> int:
    """A row from a CSV cell or a status value (-1 where empty)."""
    return int(text) if text not in ("", None) else -1


def read_recording_view(folder: Path) -> View:
    """A node's recorded ``/seqvpr/status`` (``seqvpr play --record``) as a localisation: each status's values a
    row, the map named by its hardware id (where it still is) for the route and the matched frames."""
    statuses = recorded_statuses(folder)
    if not statuses:
        raise SeqvprError(f"{folder}: a bag with no /seqvpr/status message (not a recording of seqvpr node)")
    notes: list[str] = []
    reference, _ = source_side(statuses[0][0], "reference", None, notes)
    columns = list(dict.fromkeys(k for _, values in statuses for k in values))
    rows = [[values.get(c, "") for c in columns] for _, values in statuses]
    values = [v for _, v in statuses]
    stream = {"status": [v.get("state", "") for v in values], "score": [_number(v.get("score")) for v in values],
              "localised": [_row(v.get("map_index")) for v in values],
              "best": [_row(v.get("best_index")) for v in values], "correct": [-1] * len(values),
              "threshold": _number(values[0].get("threshold")), "columns": columns, "rows": rows}
    query = Side(str(folder), [v.get("stamp", str(i)) for i, (_, v) in enumerate(statuses)])
    return View("localize", f"recorded node: {folder.name}", reference, query, stream=stream, notes=notes)


def recorded_statuses(folder: Path) -> list[tuple[str, dict[str, str]]]:
    """The bag's ``/seqvpr/status`` messages in order: (hardware id, key-values), malformed frames' reports left
    out (they carry no estimate)."""
    from rosbags.highlevel import AnyReader

    from seqvpr.errors import reading

    found = []
    with reading(folder, "a recorded bag"):
        with AnyReader([folder]) as reader:
            connections = [c for c in reader.connections if c.topic == "/seqvpr/status"]
            for connection, _, raw in reader.messages(connections=connections):
                status = reader.deserialize(raw, connection.msgtype).status[0]
                values = {kv.key: kv.value for kv in status.values}
                if values.get("frame", "") != "":
                    found.append((status.hardware_id, values))
    return found


def read_map_view(folder: Path) -> View:
    """A map: its sessions, frames, descriptor settings, identity, and its route."""
    from seqvpr.maps.files import open_map

    saved = open_map(folder)
    notes: list[str] = []
    info = saved.info
    facts = {"folder": str(folder), "frames": info.count, "dimension": info.dim, "dtype": info.dtype,
             "identity": info.identity, "descriptor": json.loads(json.dumps(info.description, default=str)),
             "sessions": _sessions(info),
             "index": info.index}
    return View("map", f"map: {folder.name}", side_of(saved.frames, str(folder), notes), facts=facts, notes=notes)


def _sessions(info: Any) -> list[dict[str, Any]]:
    from seqvpr.maps.parts import sessions_of

    return [dict(s) for s in sessions_of(info)]
