"""A bad argument is named as its user spelled it: a Python caller reads the argument (``seq_len must be ...``), a
command-line user the flag (``--seq-len must be ...``), from one ``SettingError`` and one table of flags."""

from __future__ import annotations

import ast
from pathlib import Path

import click
import numpy as np
import pytest

import seqvpr
from seqvpr.cli.options import FLAGS
from seqvpr.errors import SettingError
from seqvpr.maps.sharding import shard_map
from seqvpr.sequences.match_settings import MatchSettings
from seqvpr.sequences.windows import SequenceSpec
from tests.helpers import raises_one_line, run_cli, write_route_files

SRC = Path(__file__).resolve().parents[1] / "src" / "seqvpr"
#: settings a Python caller alone sets (no command takes them): their errors name them as they are
PYTHON_ONLY = {"group_per", "mining", "cosface_m", "select_k", "proposer", "sources", "descriptors", "extra", "source", "monitor",
               "classification"}


def test_a_setting_error_names_settings_as_the_caller_spells_them():
    error = SettingError("{history} H needs a {shortlist} (got H = 3)")
    assert str(error) == "history H needs a shortlist (got H = 3)"
    assert error.naming(FLAGS) == "--shortlist-history H needs a --shortlist (got H = 3)"
    assert SettingError("{unknown} stays {k}").naming({"k": "--k"}) == "unknown stays --k"


def setting_names() -> dict[str, set[str]]:
    """Every setting a SettingError's template names in the source, by the file naming it (read from the code)."""
    from seqvpr.errors import SETTING_NAME

    found: dict[str, set[str]] = {}
    for path in SRC.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Call) and getattr(node.func, "id", "") == "SettingError" and node.args:
                parts = [c.value for c in ast.walk(node.args[0]) if isinstance(c, ast.Constant)
                         and isinstance(c.value, str)]
                for name in SETTING_NAME.findall("".join(parts)):
                    found.setdefault(name, set()).add(str(path.relative_to(SRC)))
    return found


def command_options() -> set[str]:
    """Every option of every ``seqvpr`` command."""
    from seqvpr.cli import cli

    def walk(command):
        context = click.Context(command)
        if isinstance(command, click.Group):
            for name in command.list_commands(context):
                yield from walk(command.get_command(context, name))
        else:
            for parameter in command.params:
                yield from getattr(parameter, "opts", ())

    return set(walk(cli))


def test_every_setting_an_error_names_has_one_flag_and_every_flag_is_an_option():
    names = setting_names()
    assert {"seq_len", "method", "models", "shortlist", "history", "dtype", "overlap"} <= set(names)
    assert [n for n in names if n not in FLAGS and n not in PYTHON_ONLY] == []
    assert sorted(set(FLAGS.values()) - command_options()) == []


@pytest.fixture(scope="module")
def route(tmp_path_factory):
    folder = tmp_path_factory.mktemp("names")
    write_route_files(folder, n_frames=160, dim=12, seed=4)
    seqvpr.build_map([str(folder / "ref.npz")], folder / "map")
    return folder


def python_calls(f: Path):
    """(call, the message naming its argument): each public function with one bad argument."""
    from seqvpr.maps import match_map
    from seqvpr.localization import Localizer
    from seqvpr.training.seqmatchnet import SeqMatchNetSettings

    query = seqvpr.load_traversal(str(f / "qry.npz"), "query")
    settings = MatchSettings(SequenceSpec(5))
    return [
        (lambda: seqvpr.match(f / "ref.npz", query, seq_len=0), "seq_len must be an integer in [1, inf]"),
        (lambda: seqvpr.match(f / "ref.npz", query, seq_len=500), "a window of 500 frames (seq_len) is longer"),
        (lambda: seqvpr.match(f / "ref.npz", query, "single", seq_len=5), "method single uses L = 1; leave seq_len"),
        (lambda: seqvpr.match(f / "ref.npz", query, velocities=(-1.0,)), "velocities must be positive numbers"),
        (lambda: seqvpr.match(f / "ref.npz", query, shortlist=4), "shortlist S needs a map with an index"),
        (lambda: seqvpr.match(f / "map", query, history=3), "history H needs a shortlist S >= 1"),
        (lambda: seqvpr.match(f / "ref.npz", query, "seqnet"), "method seqnet needs a SeqNet model (models;"),
        (lambda: seqvpr.evaluate(seqvpr.match(f / "ref.npz", query), radius="5m", no_positive="skip"),
         "no_positive must be one of 'exclude', 'miss'"),
        (lambda: seqvpr.build_map([str(f / "ref.npz")], f / "pq", dtype="pq:7"), "dtype pq:7: M = 7 must divide"),
        (lambda: match_map(seqvpr.open_map(f / "map"), query, "delta", settings, shortlist=5),
         "shortlist applies to the frame-matching methods (single, matching, seqmatchnet), not method delta"),
        (lambda: shard_map(f / "map", f / "shards", 0, 2), "shards must be between 1"),
        (lambda: Localizer.open(f / "map", seq_len=10**6), "seq_len 1000000 is longer than every segment"),
        (lambda: Localizer.open(f / "map", method="hmm", shortlist=3), "method hmm keeps a belief over every map "
                                                                       "frame: it takes no shortlist"),
        (lambda: Localizer.open(f / "map", history=2), "history H needs a shortlist"),
        (lambda: SeqMatchNetSettings(epochs=-1), "epochs must be an integer in [0, inf]"),
        (lambda: SeqMatchNetSettings(optimizer="rmsprop"), "optimizer must be one of 'sgd', 'adam'"),
        (lambda: seqvpr.match(f / "ref.npz", query, k=2.5), "k must be an integer in [1, inf], got 2.5"),
        (lambda: seqvpr.match(f / "ref.npz", query, "adaptive", seq_len=5, steps=(0, 10**9)),
         "steps: expected MIN, MAX with 0 <= MIN <= MAX <= 16"),
        (lambda: seqvpr.match(f / "ref.npz", query, seq_len=2.0), "seq_len must be an integer in [1, inf], got 2.0"),
        (lambda: seqvpr.match(f / "ref.npz", query, velocities=["fast"]), "velocities must be numbers"),
        (lambda: seqvpr.Traversal.from_descriptors(np.array(3.0)), "descriptors must be a 2-D array"),
        (lambda: seqvpr.Traversal.from_descriptors(np.ones((4, 3), int)), "descriptors must be floating point"),
    ]


def test_a_python_callers_bad_argument_names_the_argument(route):
    for call, message in python_calls(route):
        text = raises_one_line(message, call)
        words = message.replace("(", " ").replace(")", " ").replace(":", " ").split()
        subject = next(word for word in words if word in FLAGS or word in PYTHON_ONLY)
        assert subject in text and FLAGS.get(subject, "--") not in text, text  # the argument, never its flag


def cli_calls(f: Path):
    """(arguments, the message naming the flag): each command with one bad setting the library refuses."""
    return [
        (("match", "-r", f / "ref.npz", "-q", f / "qry.npz", "-L", "500", "--out", f / "o1"),
         "--seq-len 500: longer than every segment"),
        (("match", "-r", f / "ref.npz", "-q", f / "qry.npz", "--method", "single", "-L", "5", "--out", f / "o2"),
         "--method single uses L = 1; leave --seq-len out"),
        (("match", "-r", f / "ref.npz", "-q", f / "qry.npz", "--method", "seqnet", "--out", f / "o3"),
         "--method seqnet needs a SeqNet model (--model;"),
        (("match", "--map", f / "map", "-q", f / "qry.npz", "--method", "delta", "--shortlist", "5", "--out", f / "o4"),
         "--shortlist applies to the frame-matching methods (single, matching, seqmatchnet), not --method delta"),
        (("localize", "--map", f / "map", "-q", f / "qry.npz", "--method", "hmm", "--shortlist", "3", "--out",
          f / "o5"), "--method hmm keeps a belief over every map frame: it takes no --shortlist"),
        (("localize", "--map", f / "map", "-q", f / "qry.npz", "-L", "100000", "--out", f / "o6"),
         "--seq-len 100000 is longer than every segment"),
        (("map", "build", f / "ref.npz", "--dtype", "pq:7", "--out", f / "o7"), "--dtype pq:7: M = 7 must divide"),
        (("map", "shard", f / "map", "--shards", "100000", "--out", f / "o8"), "--shards must be between 1"),
        (("map", "index", f / "map", "--index", "ivf:0"), "--index 'ivf:0': numbers must be at least 1"),
        (("train", "seqmatchnet", "-r", f / "ref.npz", "-q", f / "qry.npz", "--radius", "5m", "--train-frames", "0:100",
          "--val-frames", "100:160", "--negatives", "100000", "--out", f / "o9"), "--negatives must be from 1 to"),
        (("train", "seqnet", "-r", f / "ref.npz", "-q", f / "qry.npz", "--radius", "5m", "--train-frames", "0:100",
          "--val-frames", "100:160", "--optimizer", "sgd", "--lr", "1e-3", "-L", "500", "--out", f / "o10"),
         "(--seq-len) is longer than every segment"),
        (("eval", f / "predictions.csv", "-r", f / "ref.npz", "-q", f / "qry.npz", "--radius", "5m",
          "--ground-truth", f / "gt.npy"), "give --radius or --ground-truth, not both"),
        (("demo", "--frames", "10", "--out", f / "o11"), "--frames must be at least 50"),
    ]


@pytest.mark.parametrize("number", range(13))
def test_a_command_line_users_bad_setting_names_the_flag(route, monkeypatch, capsys, number):
    arguments, message = cli_calls(route)[number]
    code, _, err = run_cli(monkeypatch, capsys, *arguments)
    assert code == 2 and message in err and err.count("seqvpr: error:") == 1, err
    assert not any((route / f"o{i}").exists() for i in range(1, 12))


def test_a_python_caller_may_give_settings_and_rows_in_the_forms_the_cli_reads(route):
    """Velocities as the command line's text, rows as a torch tensor (bfloat16, with gradients) or nested lists: the
    same match as the canonical forms, not a TypeError from deep inside."""
    import torch

    reference = seqvpr.load_traversal(str(route / "ref.npz"), "reference")
    query = seqvpr.load_traversal(str(route / "qry.npz"), "query")
    expected = seqvpr.match(reference, query, seq_len=3, velocities=(0.8, 0.9, 1.0, 1.1, 1.2)).topk.indices
    np.testing.assert_array_equal(seqvpr.match(reference, query, seq_len=3, velocities="0.8:1.2:0.1").topk.indices,
                                  expected)
    rows = torch.tensor(query.descriptors, requires_grad=True)
    as_tensor = seqvpr.Traversal.from_descriptors(rows, "q", segment_ids=query.segment_ids)
    as_lists = seqvpr.Traversal.from_descriptors(query.descriptors.tolist(), "q", segment_ids=query.segment_ids)
    for other in (as_tensor, as_lists):
        np.testing.assert_array_equal(seqvpr.match(reference, other, seq_len=3).topk.indices[:, 0],
                                      seqvpr.match(reference, query, seq_len=3).topk.indices[:, 0])
    half = seqvpr.Traversal.from_descriptors(rows.to(torch.bfloat16), "q")
    assert half.descriptors.dtype == np.float32
