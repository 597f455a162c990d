"""A training epoch's files commit as one: a kill at any rename leaves the previous epoch's complete set or this
one's (the weights are those the config records), and resuming reaches the uninterrupted run's weights. Resuming
on other data, or from a state whose files were changed, is one line naming the file."""

import json
from dataclasses import replace

import pytest
import torch

import seqvpr.io
from seqvpr.identity import digest_file
from seqvpr.io import TEMP_TAG
from seqvpr.models import files as ckpt
from seqvpr.models.registry import load_trained_model
from seqvpr.models.seqmatchnet import TransformConfig
from seqvpr.training.seqmatchnet import train_seqmatchnet
from seqvpr.training.state import STATE_FILE, STATE_JSON
from tests.helpers import raises_one_line
from tests.training.test_seqmatchnet_training import SMALL, small_data

TWO = replace(SMALL, epochs=2)


class Killed(Exception):
    """What the injected failure raises (as a kill would, between two renames)."""


def train(out, resume=False, data=None):
    data = data or small_data(60, 8)
    return train_seqmatchnet(data, TransformConfig(8), TWO, out, resume=resume)


def failing_at(monkeypatch, k):
    """Make the k-th rename or exchange (counted together) raise ``Killed``; returns the call counter."""
    calls = [0]
    for name in ("rename", "exchange"):
        real = getattr(seqvpr.io, name)

        def failing(*args, real=real):
            calls[0] += 1
            if calls[0] == k:
                raise Killed(f"call {k}")
            return real(*args)

        monkeypatch.setattr(seqvpr.io, name, failing)
    return calls


def assert_consistent(out):
    """Weights are those config.json records, every file train_state.json records holds its digest, and no
    temporary is left beside or inside the folder."""
    for folder in (out, out / json.loads((out / STATE_JSON).read_text())["state_dir"]):
        if (folder / ckpt.CONFIG_FILE).is_file():
            recorded = json.loads((folder / ckpt.CONFIG_FILE).read_text())["files"][ckpt.MODEL_FILE]
            assert digest_file(folder / ckpt.MODEL_FILE) == recorded
            load_trained_model(folder)
    state = json.loads((out / STATE_JSON).read_text())
    assert all(digest_file(out / name) == digest for name, digest in state["files"].items())
    assert not [p for p in out.parent.rglob("*") if TEMP_TAG in p.name]


@pytest.mark.slow
def test_a_failure_at_any_rename_leaves_one_epochs_set_and_resume_reaches_the_same_weights(tmp_path, monkeypatch):
    whole = train(tmp_path / "whole")
    with monkeypatch.context() as patch:
        calls = failing_at(patch, 0)
        train(tmp_path / "count")
    assert calls[0] > 10  # every file of three epochs, and the folder swaps
    expected = ckpt.read_tensors(whole.folder / ckpt.MODEL_FILE)
    for k in range(1, calls[0] + 1):
        out = tmp_path / "runs" / f"k{k}"
        with monkeypatch.context() as patch:
            failing_at(patch, k)
            with pytest.raises(Killed):
                train(out)
        if (out / STATE_JSON).is_file():
            assert_consistent(out)
        else:
            assert not out.exists()
        resumed = train(out, resume=True)
        assert_consistent(out)
        got = ckpt.read_tensors(out / ckpt.MODEL_FILE)
        assert resumed.best_epoch == whole.best_epoch
        assert all(torch.equal(got[name], value) for name, value in expected.items()), k


def test_resume_on_other_data_or_from_changed_files_is_one_line(tmp_path):
    out = tmp_path / "run"
    train(out)
    other = small_data(60, 8, seed=3)
    raises_one_line("trained on other data: its reference was", train, out, True, other)
    state = json.loads((out / STATE_JSON).read_text())
    state_file = out / state["state_dir"] / STATE_FILE
    state_file.write_bytes(state_file.read_bytes() + b" ")
    message = raises_one_line("its content is not what", train, out, True)
    assert str(state_file) in message and STATE_JSON in message


def test_a_user_folder_that_is_not_a_run_is_refused_before_training(tmp_path):
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("mine")
    raises_one_line("holds other files and no train_state.json", train, tmp_path / "mine")
    assert (tmp_path / "mine" / "notes.txt").read_text() == "mine"


def test_files_of_the_run_folder_are_carried_over_between_epochs(tmp_path):
    out = tmp_path / "run"
    train(out)
    (out / "notes.txt").write_text("kept")
    train_seqmatchnet(small_data(60, 8), TransformConfig(8), replace(TWO, epochs=3), out, resume=True)
    assert (out / "notes.txt").read_text() == "kept"
    assert sorted(p.name for p in (out / "state").iterdir()) == ["epoch_0003"]
