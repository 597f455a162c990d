"""The one validation layer (``seqvpr.checks``), and a walk over every public signature: each argument of each
public function, class and trainer given wrong types and values is one ``SeqvprError`` line naming the argument,
never another exception. A new argument without a row here fails the walk."""

from __future__ import annotations

import dataclasses
import inspect
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, strategies as st

import seqvpr
from seqvpr import checks
from seqvpr.errors import SeqvprError, SettingError
from tests.helpers import write_route_files

# --- the checks themselves


@given(st.integers(-10, 10), st.integers(-10, 10), st.integers(-10, 10))
def test_whole_takes_integers_in_range_and_refuses_the_rest(value, low, high):
    inside = low <= value <= high
    if inside:
        assert checks.whole(value, "x", low, high) == value and checks.whole(np.int64(value), "x", low, high) == value
    else:
        with pytest.raises(SettingError, match=r"^x must be an integer in"):
            checks.whole(value, "x", low, high)
    for wrong in (float(value), True, str(value), None, [value]):
        with pytest.raises(SettingError, match=r"^x must be an integer"):
            checks.whole(wrong, "x")


@given(st.floats(allow_nan=True, allow_infinity=True), st.booleans())
def test_finite_refuses_nan_infinity_and_what_is_below(value, open_low):
    ok = math.isfinite(value) and (value > 0 if open_low else value >= 0)
    if ok:
        assert checks.finite(value, "x", 0.0, open_low=open_low) == value
    else:
        with pytest.raises(SettingError, match="^x must be a finite number in"):
            checks.finite(value, "x", 0.0, open_low=open_low)


def test_paths_flags_texts_and_lists():
    assert checks.paths("a.npz", "s") == ["a.npz"] and checks.paths([Path("a"), "b"], "s") == ["a", "b"]
    for wrong in ([], [3], b"a", 3, {"a": 1}):
        with pytest.raises(SettingError, match="^s must"):
            checks.paths(wrong, "s")
    assert checks.flag(np.bool_(True), "f") is True
    for wrong in (1, "yes", None):
        with pytest.raises(SettingError, match="^f must be True or False"):
            checks.flag(wrong, "f")
    assert checks.whole_numbers((1, np.int32(5)), "ks") == (1, 5)
    for wrong in ("1,5", 5, [], [0], [2.5]):
        with pytest.raises(SettingError, match="^ks must"):
            checks.whole_numbers(wrong, "ks")
    with pytest.raises(SettingError, match=r"^m must be one of 'a', 'b', got 'c'"):
        checks.text("c", "m", ("a", "b"))


def test_the_command_lines_number_options_use_the_same_interval():
    from click.exceptions import BadParameter

    from seqvpr.cli.options import FRACTION

    assert FRACTION.convert("1", None, None) == 1.0
    with pytest.raises(BadParameter, match=r"0 is not in \(0, 1\]"):
        FRACTION.convert("0", None, None)
    assert checks.range_text(0, 1, True) == "(0, 1]" and not checks.in_range(0.0, 0, 1, True)


# --- the walk over every public signature

OBJECT = object()
COUNT = [0, -1, 2.5, True, "3", None, OBJECT]  # an integer >= 1
COUNT0 = [-1, 2.5, True, "3", None, OBJECT]  # an integer >= 0
OPTIONAL_COUNT = [0, 2.5, True, "3", OBJECT]
TEXT = [None, 3, b"x", OBJECT, ""]
CHOICE = [None, 3, "nope", OBJECT]
PATH = [None, 3, b"x", OBJECT, ""]
FLAG = [None, 1, "yes", OBJECT]
FINITE = [math.nan, math.inf, "1", True, None, OBJECT]
OPTIONAL_FINITE = [math.nan, -math.inf, "1", True, OBJECT]
FUNCTION = [3, "f", OBJECT]
INSTANCE = [3, "x", OBJECT]
ARRAY = [3, "x", OBJECT, [["a"]]]

#: per callable: each parameter -> (wrong values, the word the message names it by; default: the parameter)
MATCH = {
    "reference": ([None, 3, OBJECT, [1, 2]], None), "query": ([None, 3, OBJECT], None), "method": (CHOICE, None),
    "seq_len": (OPTIONAL_COUNT, None), "models": ([3, OBJECT, [3], {"a": 1}], None), "settings": (INSTANCE, None),
    "shortlist": (COUNT0, None), "history": (COUNT0 + [2], None), "nprobe": (COUNT, None), "rerank": (COUNT0, None),
    "index": (CHOICE, None), "steps": ([3, (0,), (0, 99), (1.5, 2), "0:2"], None),
    "contrast_window": ([1, 2.5, True, "3", OBJECT], None), "proposer": ([3, "nope", OBJECT], None),
    "progress": (FUNCTION, None),
    # ``conf``: the MatchSettings fields by name, and extraction's
    "k": (COUNT, None), "align": (CHOICE, None), "boundary": (CHOICE, None),
    "velocities": ([[-1.0], "fast", OBJECT, []], None), "normalize": (FLAG, None), "dtype": (CHOICE, None),
    "device": ([3, "nope", OBJECT], None), "memory_budget": (OPTIONAL_COUNT, None),
    "cache_dir": ([3, OBJECT], None), "skip_bad": (FLAG, None), "engine": (CHOICE, None), "conf": ([], None),
}
EVALUATE = {
    "result": ([None, 3, OBJECT], None), "radius": ([OBJECT, [1], "abc", True], None),
    "ground_truth": ([3, OBJECT, b"x"], None), "ks": ([3, "1,5", [0], [2.5], []], None),
    "no_positive": (CHOICE, None), "uniqueness": ([-1, 2.5, True, "3", OBJECT], None),
}
LOAD = {"source": (PATH, None), "role": (CHOICE, None)}
BUILD = {
    "sources": ([None, 3, OBJECT, [], [3]], None), "out": (PATH, None), "description": (INSTANCE, None),
    "models": ([3, "x", {"a": 1}], None), "dtype": (CHOICE + ["pq:0"], None), "normalize": (FLAG, None),
    "device": ([3, "nope", OBJECT], None), "progress": (FUNCTION, None), "frames": ([3, "abc", OBJECT], None),
    "indexed": (FUNCTION, None), "thumbnails": (FLAG, None), "extraction": ([], None),
}
OPEN_MAP = {"folder": (PATH, None)}
LOCALIZER_OPEN = {
    "map_folder": (PATH, None), "model": ([3, OBJECT, [3]], None), "device": ([3, "nope", OBJECT], None),
    "engine": (CHOICE, None),
    "settings": ([], None),
}
UPDATE = {"frame": ([None, 3, "x", OBJECT, np.zeros(3, np.float32), np.zeros(8, int), np.full(8, np.nan)], None),
          "timestamp": ([math.nan, "1", True, OBJECT], None)}
SAVE_STATE = {"path": (PATH, None), "extra": ([3, "x", [1], {"a": OBJECT}, {"a": math.nan}], None)}
RESTORE = {"path": (PATH, None)}
FROM_DESCRIPTORS = {
    "descriptors": ([None, 3, "x", OBJECT, np.ones((3, 2), int), [[1.0], [1.0, 2.0]]], None), "name": (TEXT, None),
    "positions": (ARRAY, None), "segment_ids": (ARRAY, None), "timestamps": (ARRAY, None), "source": ([3, OBJECT], None),
}
TRAIN = {"data": (INSTANCE, None), "transform": (INSTANCE, None), "settings": (INSTANCE, None), "out_dir": (PATH, None),
         "resume": (FLAG, None), "monitor": (INSTANCE, None), "config": (INSTANCE, None),
         "backbone_factory": (FUNCTION, None), "classification": ([3, "x", [OBJECT]], None)}
#: dataclass fields whose message names them another way
ALIASES = {("SequenceSpec", "length"): "seq_len"}


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    folder = tmp_path_factory.mktemp("walk")
    route = write_route_files(folder, n_frames=40, dim=8, seed=2)
    saved = seqvpr.build_map([str(route / "ref.npz")], folder / "map")
    return folder, route, saved


def wrong_calls(world):
    """(label, parameter, the call with one wrong value, the word its message names) for every row."""
    from seqvpr.data.ground_truth import Radius
    from seqvpr.training.jist import train_jist
    from seqvpr.training.learner import TrainingData
    from seqvpr.training.seqmatchnet import train_seqmatchnet
    from seqvpr.training.seqnet import train_seqnet
    from seqvpr.training.settings import JistTrainSettings, SeqMatchNetSettings, SeqNetSettings
    from seqvpr.models.jist import JistConfig

    folder, route, saved = world
    ref, qry = str(route / "ref.npz"), str(route / "qry.npz")
    reference, query = seqvpr.load_traversal(ref, "reference"), seqvpr.load_traversal(qry, "query")
    data = TrainingData(reference.slice_frames(0, 30), query.slice_frames(0, 30), reference.slice_frames(30, 40),
                        query.slice_frames(30, 40), Radius(1, "frames"), Radius(3, "frames"), Radius(1, "frames"))
    localizer = seqvpr.Localizer.open(saved, seq_len=3)
    result = seqvpr.match(ref, qry, seq_len=3)
    rows = np.zeros((10, 4), np.float32)
    jist = (train_jist, {"data": data, "config": JistConfig(), "settings": JistTrainSettings(), "out_dir": folder / "j"})
    plans = [
        ("match", seqvpr.match, {"reference": ref, "query": qry}, MATCH),
        ("evaluate", seqvpr.evaluate, {"result": result, "radius": "2f"}, EVALUATE),
        ("load_traversal", seqvpr.load_traversal, {"source": ref, "role": "reference"}, LOAD),
        ("build_map", seqvpr.build_map, {"sources": [ref], "out": folder / "built"}, BUILD),
        ("open_map", seqvpr.open_map, {"folder": folder / "map"}, OPEN_MAP),
        ("Localizer.open", seqvpr.Localizer.open, {"map_folder": saved, "seq_len": 3}, LOCALIZER_OPEN),
        ("Localizer.update", localizer.update, {"frame": np.zeros(8, np.float32)}, UPDATE),
        ("Localizer.save_state", localizer.save_state, {"path": folder / "s.npz"}, SAVE_STATE),
        ("Localizer.restore", localizer.restore, {"path": folder / "s.npz"}, RESTORE),
        ("Traversal.from_descriptors", seqvpr.Traversal.from_descriptors, {"descriptors": rows}, FROM_DESCRIPTORS),
        ("train_seqmatchnet", train_seqmatchnet, {"data": data, "settings": SeqMatchNetSettings(epochs=0),
                                                  "out_dir": folder / "s"}, TRAIN),
        ("train_seqnet", train_seqnet, {"data": data, "settings": SeqNetSettings(epochs=0), "out_dir": folder / "n"},
         TRAIN),
        ("train_jist", *jist, TRAIN),
    ]
    for label, function, base, table in plans:
        parameters = inspect.signature(function).parameters
        assert set(parameters) <= set(table), f"{label}: no wrong values for {set(parameters) - set(table)}"
        names = set(parameters) | ({n for n in table if n in MATCH} if label == "match" else set())
        for name in names & set(table):
            wrong, word = table[name]
            for value in wrong:
                yield label, name, (function, {**base, name: value}), word or name
        yield from unknown_names(label, function, base, parameters)


def unknown_names(label, function, base, parameters):
    """A function taking ``**settings`` refuses a name it does not know, naming it."""
    if any(p.kind is p.VAR_KEYWORD for p in parameters.values()):
        yield label, "an unknown setting", (function, {**base, "bogus": 1}), "bogus"


def dataclass_calls():
    """Each field of the public settings dataclasses given a value of the wrong type for its default."""
    from seqvpr.localization.localizer import LocalizerSettings
    from seqvpr.sequences.filter import FilterSettings
    from seqvpr.training.settings import CellGrouping, JistTrainSettings, SeqMatchNetSettings, SeqNetSettings

    wrong_for = {bool: FLAG, int: [2.5, "3", True, OBJECT], float: [math.nan, "1", True, OBJECT],
                 str: [3, OBJECT], tuple: ["x", OBJECT, [OBJECT]], type(None): ["3", True, OBJECT]}
    for kind in (seqvpr.MatchSettings, seqvpr.SequenceSpec, LocalizerSettings, FilterSettings, SeqMatchNetSettings,
                 SeqNetSettings, JistTrainSettings, CellGrouping):
        for field in dataclasses.fields(kind):
            default = field.default if field.default is not dataclasses.MISSING else field.default_factory()
            wrong = wrong_for.get(type(default), INSTANCE)
            for value in wrong:
                yield kind.__name__, field.name, (kind, {field.name: value}), ALIASES.get((kind.__name__, field.name),
                                                                                        field.name)


def test_every_public_argument_refuses_wrong_types_and_values_naming_it(world, monkeypatch):
    monkeypatch.chdir(world[0])  # a path that happens to exist is no wrong value: run where none does
    failures, calls = [], [*wrong_calls(world), *dataclass_calls()]
    assert len({label for label, *_ in calls}) == 21 and len(calls) > 500, len(calls)
    for label, name, (function, kwargs), word in calls:
        shown = checks.shown(kwargs.get(name, "bogus"))
        try:
            function(**kwargs)
        except SeqvprError as error:
            text = str(error)
            named = any(w in text for w in (word, word.replace("_", " "), word.replace("_", "-")))
            if "\n" in text or not (named or shown.strip("'\"") in text):
                failures.append(f"{label}({name}={shown}): names neither: {text}")
        except Exception as error:  # noqa: BLE001 - what the walk looks for
            failures.append(f"{label}({name}={shown}): {type(error).__name__}: {error}")
        else:
            failures.append(f"{label}({name}={shown}): accepted")
    assert not failures, "\n".join(failures)
