"""SeqMatchNet training end to end on small problems: learning, resume, checkpoints, and the command line."""

import json
import os

import numpy as np
import pytest
import torch

from seqvpr.data.ground_truth import Radius
from seqvpr.data.traversal import Traversal
from seqvpr.models.seqmatchnet import FrameTransform, TransformConfig, apply_transform
from seqvpr.sequences.windows import SequenceSpec
from seqvpr.models import files as ckpt
from seqvpr.models.seqmatchnet import load_seqmatchnet, save_seqmatchnet
from seqvpr.training.state import STATE_JSON
from seqvpr.training.seqmatchnet import TrainingData, SeqMatchNetSettings, train_seqmatchnet
from tests.helpers import raises_one_line, run_cli


def route(n=120, dim=16, seed=0, distortion=1.0, noise=0.3):
    """A reference route and a query that sees it through a fixed linear distortion plus noise."""
    rng = np.random.default_rng(seed)
    steps = rng.normal(size=(n, dim))
    reference = np.cumsum(steps, axis=0) / 3 + rng.normal(size=(n, dim))
    mixing = np.eye(dim) + distortion * rng.normal(size=(dim, dim)) / np.sqrt(dim)
    query = reference @ mixing + noise * rng.normal(size=(n, dim)) + 2.0 * rng.normal(size=dim)
    return reference.astype(np.float32), query.astype(np.float32)


def small_data(n=120, dim=16, seed=0):
    reference, query = route(n, dim, seed)
    ref = Traversal.from_descriptors(reference, "ref")
    qry = Traversal.from_descriptors(query, "qry")
    split = int(n * 0.7)
    return TrainingData(
        ref.slice_frames(0, split), qry.slice_frames(0, split),
        ref.slice_frames(split, n), qry.slice_frames(split, n),
        Radius(1, "frames"), Radius(3, "frames"), Radius(1, "frames"),
    )


SMALL = SeqMatchNetSettings(SequenceSpec(3), epochs=3, batch_size=8, refresh_every=30, negative_pool=20, lr=0.05,
                      lr_step=2, seed=7)


def weights(folder):
    return ckpt.read_tensors(folder / ckpt.MODEL_FILE)


def test_loss_decreases_and_recall_improves(tmp_path):
    data = small_data()
    settings = SeqMatchNetSettings(SequenceSpec(3), epochs=8, batch_size=8, refresh_every=1000, negative_pool=None,
                             optimizer="adam", lr=3e-3, weight_decay=0.0, seed=1)
    result = train_seqmatchnet(data, TransformConfig(16), settings, tmp_path / "run")
    losses = [r.loss for r in result.history[1:]]
    assert losses[-1] < 0.7 * losses[0]
    assert result.best_recall[1] > result.history[0].recall[1]
    assert result.history[result.best_epoch].recall == result.best_recall


def test_resume_after_kill_gives_the_same_weights(tmp_path):
    data = small_data()
    whole = train_seqmatchnet(data, TransformConfig(16), SMALL, tmp_path / "whole")
    # a run killed after epoch 1 (its state is what the kill leaves behind), then resumed to the same length
    from dataclasses import replace

    train_seqmatchnet(data, TransformConfig(16), replace(SMALL, epochs=1), tmp_path / "killed")
    resumed = train_seqmatchnet(data, TransformConfig(16), SMALL, tmp_path / "killed", resume=True)
    state_whole = ckpt.read_json(tmp_path / "whole" / STATE_JSON)
    state_resumed = ckpt.read_json(tmp_path / "killed" / STATE_JSON)
    last_whole = weights(tmp_path / "whole" / state_whole["state_dir"])
    last_resumed = weights(tmp_path / "killed" / state_resumed["state_dir"])
    for key in last_whole:
        assert torch.equal(last_whole[key], last_resumed[key]), key
    assert [r.loss for r in whole.history] == [r.loss for r in resumed.history]
    assert whole.best_epoch == resumed.best_epoch


def test_training_is_deterministic_for_a_seed_and_varies_with_it(tmp_path):
    data = small_data()
    from dataclasses import replace

    a = train_seqmatchnet(data, TransformConfig(16), replace(SMALL, epochs=1), tmp_path / "a")
    b = train_seqmatchnet(data, TransformConfig(16), replace(SMALL, epochs=1), tmp_path / "b")
    c = train_seqmatchnet(data, TransformConfig(16), replace(SMALL, epochs=1, seed=8), tmp_path / "c")
    assert a.history[1].loss == b.history[1].loss
    assert a.history[1].loss != c.history[1].loss


def test_resume_refuses_other_settings_a_second_run_and_starts_over_without_state(tmp_path):
    data = small_data()
    from dataclasses import replace

    train_seqmatchnet(data, TransformConfig(16), replace(SMALL, epochs=1), tmp_path / "run")
    raises_one_line("lr", train_seqmatchnet, data, TransformConfig(16), replace(SMALL, lr=0.1), tmp_path / "run",
                    resume=True)
    raises_one_line("use resume to continue it", train_seqmatchnet, data, TransformConfig(16), SMALL, tmp_path / "run")
    fresh = train_seqmatchnet(data, TransformConfig(16), replace(SMALL, epochs=1), tmp_path / "new", resume=True)
    assert [r.epoch for r in fresh.history] == [0, 1]  # nothing to resume yet: a killed-at-start run starts over


def test_saved_model_applies_identically_after_reload(tmp_path):
    model = FrameTransform(TransformConfig(12, out_dim=7, hidden=(9,)), seed=3)
    x = np.random.default_rng(0).normal(size=(30, 12)).astype(np.float32)
    save_seqmatchnet(tmp_path / "m", model, {"sequence": {"length": 5}})
    loaded, config = load_seqmatchnet(tmp_path / "m")
    assert np.array_equal(apply_transform(model, x), apply_transform(loaded, x))
    assert config["sequence"]["length"] == 5 and config["transform"]["out_dim"] == 7


def test_model_loading_errors_are_one_line(tmp_path):
    raises_one_line("no such model folder", load_seqmatchnet, tmp_path / "absent")
    save_seqmatchnet(tmp_path / "m", FrameTransform(TransformConfig(4)), {})
    (tmp_path / "m" / ckpt.MODEL_FILE).write_bytes(b"garbage")
    raises_one_line(f"{ckpt.MODEL_FILE}: its content is not what", load_seqmatchnet, tmp_path / "m")
    config = json.loads((tmp_path / "m" / ckpt.CONFIG_FILE).read_text())
    del config["files"]  # a folder from before the weights' digest was recorded: the file itself is read
    (tmp_path / "m" / ckpt.CONFIG_FILE).write_text(json.dumps(config))
    raises_one_line("not a readable safetensors file", load_seqmatchnet, tmp_path / "m")
    save_seqmatchnet(tmp_path / "m2", FrameTransform(TransformConfig(4)), {})
    config = json.loads((tmp_path / "m2" / ckpt.CONFIG_FILE).read_text())
    config["transform"]["in_dim"] = 5
    (tmp_path / "m2" / ckpt.CONFIG_FILE).write_text(json.dumps(config))
    raises_one_line("do not fit the config", load_seqmatchnet, tmp_path / "m2")


def test_transform_rejects_other_dimensions():
    raises_one_line("expects 4-D", FrameTransform(TransformConfig(4)), torch.zeros(2, 5))


# --- the command line ----------------------------------------------------------------------------------------


run = run_cli


@pytest.fixture
def files(tmp_path):
    reference, query = route(150, 16, seed=2)
    ref, qry = tmp_path / "ref.npy", tmp_path / "qry.npy"
    np.save(ref, reference)
    np.save(qry, query)
    return ref, qry


COMMON = ["--train-frames", "0:90", "--val-frames", "90:120", "--radius", "1f", "-L", "3", "--epochs", "2",
          "--batch-size", "8", "--negative-pool", "20", "--lr", "0.05"]


def test_cli_train_then_match_with_the_model(monkeypatch, capsys, tmp_path, files):
    ref, qry = files
    run_dir = tmp_path / "run"
    code, out, err = run(monkeypatch, capsys, "train", "seqmatchnet", "-r", ref, "-q", qry, *COMMON, "--out", run_dir)
    assert code == 0, err
    assert "best epoch" in out and (run_dir / "model.safetensors").is_file()
    assert "epoch 2:" in err and "validation R@1" in err
    history = (run_dir / "history.csv").read_text().splitlines()
    assert len(history) == 4 and history[0].startswith("epoch,loss")
    code, out, err = run(monkeypatch, capsys, "match", "-r", ref, "-q", qry, "--frames", "120:150", "--radius", "1f",
                         "--model", run_dir, "--json", "--out", tmp_path / "m")
    assert code == 0, err
    result = json.loads(out)
    assert result["settings"]["sequence"]["length"] == 3  # the model's L is the default
    assert result["settings"]["model"] == str(run_dir)
    best = json.loads((run_dir / "config.json").read_text())
    assert best["sequence"]["length"] == 3 and best["transform"]["in_dim"] == 16


def test_cli_match_with_the_model_equals_matching_transformed_descriptors(monkeypatch, capsys, tmp_path, files):
    ref, qry = files
    model = FrameTransform(TransformConfig(16), seed=5)
    save_seqmatchnet(tmp_path / "m", model, {"sequence": {"length": 3}})
    for name, path in (("ref_t", ref), ("qry_t", qry)):
        np.save(tmp_path / f"{name}.npy", apply_transform(model, np.load(path)))
    args = ["--radius", "1f", "-L", "3", "--json"]
    _, with_model, _ = run(monkeypatch, capsys, "match", "-r", ref, "-q", qry, "--model", tmp_path / "m", *args,
                           "--out", tmp_path / "a")
    _, transformed, _ = run(monkeypatch, capsys, "match", "-r", tmp_path / "ref_t.npy", "-q", tmp_path / "qry_t.npy",
                            *args, "--out", tmp_path / "b")
    assert json.loads(with_model)["recall"] == json.loads(transformed)["recall"]
    assert (tmp_path / "a" / "predictions.csv").read_text() == (tmp_path / "b" / "predictions.csv").read_text()


def test_cli_ablate_prints_five_rows(monkeypatch, capsys, tmp_path, files):
    ref, qry = files
    out_dir = tmp_path / "ab"
    code, out, err = run(monkeypatch, capsys, "ablate", "seqmatchnet", "-r", ref, "-q", qry, *COMMON,
                         "--epochs", "1", "--test-frames", "120:150", "--out", out_dir)
    assert code == 0, err
    for label in ("untransformed", "single/single", "single/seqmatch", "seqmatch/single", "seqmatch/seqmatch"):
        assert label in out
    table = (out_dir / "ablation.csv").read_text().splitlines()
    assert len(table) == 6
    assert sorted(p.name for p in out_dir.iterdir() if p.is_dir() and not p.name.startswith(".")) == [
        "seqmatch-seqmatch", "seqmatch-single", "single-seqmatch", "single-single"]


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--val-frames", "80:120"], "overlap"),
        (["--neg-radius", "0.5f"], "smaller than the positive radius"),
        (["--neg-radius", "5m"], "same unit"),
        (["--train-frames", "500:600"], "no frame has an index"),
        (["--negative-pool", "many"], "--negative-pool"),
        (["-L", "200"], "longer than every segment"),
    ],
)
def test_cli_train_bad_input_is_one_line_without_output(monkeypatch, capsys, tmp_path, files, extra, message):
    ref, qry = files
    code, out, err = run(monkeypatch, capsys, "train", "seqmatchnet", "-r", ref, "-q", qry, *COMMON, *extra,
                         "--out", tmp_path / "run")
    assert code == 2
    assert err.startswith("seqvpr: error:") and err.count("\n") == 1 and message in err, err
    assert not (tmp_path / "run").exists()


def test_cli_train_names_the_file_of_other_dimension(monkeypatch, capsys, tmp_path, files):
    ref, _ = files
    narrow = tmp_path / "narrow.npy"
    np.save(narrow, np.load(ref)[:, :8])
    code, _, err = run(monkeypatch, capsys, "train", "seqmatchnet", "-r", ref, "-q", narrow, *COMMON,
                       "--out", tmp_path / "run")
    assert code == 2 and err.count("\n") == 1
    assert f"{ref} has 16, {narrow} (query) has 8" in err
    assert not (tmp_path / "run").exists()


def test_cli_match_model_of_other_dimension(monkeypatch, capsys, tmp_path, files):
    ref, qry = files
    save_seqmatchnet(tmp_path / "m", FrameTransform(TransformConfig(8)), {})
    code, _, err = run(monkeypatch, capsys, "match", "-r", ref, "-q", qry, "--radius", "1f", "--model",
                       tmp_path / "m", "--out", tmp_path / "out")
    assert code == 2 and "expects 8-D descriptors" in err and err.count("\n") == 1
    assert not (tmp_path / "out").exists()


def test_cli_train_in_frames_then_test_in_metres_on_another_dataset(monkeypatch, capsys, tmp_path, files):
    """A model trained with a frame radius applies to another traversal pair whose ground truth is in metres."""
    ref, qry = files
    run_dir = tmp_path / "run"
    code, _, err = run(monkeypatch, capsys, "train", "seqmatchnet", "-r", ref, "-q", qry, *COMMON, "--out", run_dir)
    assert code == 0, err
    reference, query = route(80, 16, seed=9)
    along = np.stack([np.arange(80) * 5.0, np.zeros(80)], axis=1)  # 5 m between frames
    np.savez(tmp_path / "other_ref.npz", descriptors=reference, positions=along)
    np.savez(tmp_path / "other_qry.npz", descriptors=query, positions=along + [1.0, 2.0])
    code, out, err = run(monkeypatch, capsys, "match", "-r", tmp_path / "other_ref.npz", "-q",
                         tmp_path / "other_qry.npz", "--radius", "6m", "--model", run_dir, "--json",
                         "--out", tmp_path / "m")
    assert code == 0, err
    result = json.loads(out)
    assert result["queries_evaluated"] == 78 and result["settings"]["ground_truth_rule"] == "within 6 m"


def test_the_untrained_epoch_is_kept_only_when_asked(tmp_path):
    """With a step too small to change recall every epoch ties epoch 0: the trained epoch 1 is kept unless
    ``select_untrained``; with no epoch to train, the untrained model is the one written."""
    from dataclasses import replace

    data = small_data()
    still = replace(SMALL, epochs=2, lr=1e-12)
    trained = train_seqmatchnet(data, TransformConfig(16), still, tmp_path / "trained")
    assert [r.recall for r in trained.history[1:]] == [trained.history[0].recall] * 2
    assert trained.best_epoch == 1 and json.loads((tmp_path / "trained" / "config.json").read_text())["epoch"] == 1
    untrained = train_seqmatchnet(data, TransformConfig(16), replace(still, select_untrained=True), tmp_path / "asked")
    assert untrained.best_epoch == 0
    nothing = train_seqmatchnet(data, TransformConfig(16), replace(still, epochs=0), tmp_path / "none")
    assert nothing.best_epoch == 0 and (tmp_path / "none" / "config.json").is_file()


@pytest.mark.slow
def test_two_processes_with_one_seed_give_bit_identical_weights(tmp_path):
    """Fresh processes (threads and all), as two users' runs are: the weights are equal to the bit (CPU)."""
    import subprocess
    import sys

    from seqvpr.data.sources import save_traversal_npz

    reference, query = route(300, 128, 3)
    save_traversal_npz(tmp_path / "ref.npz", Traversal.from_descriptors(reference, "ref"))
    save_traversal_npz(tmp_path / "qry.npz", Traversal.from_descriptors(query, "qry"))
    runs = []
    for name in ("a", "b"):
        command = [sys.executable, "-c", "from seqvpr.cli import main; main()", "train", "seqmatchnet",
                   "-r", str(tmp_path / "ref.npz"), "-q", str(tmp_path / "qry.npz"), "--train-frames", "0:220",
                   "--val-frames", "220:300", "--radius", "1f", "-L", "5", "--epochs", "2", "--out", str(tmp_path / name)]
        done = subprocess.run(command, capture_output=True, text=True, timeout=300, env={**os.environ, "OMP_NUM_THREADS": "2"})
        assert done.returncode == 0, done.stderr
        runs.append(weights(tmp_path / name))
    for key in runs[0]:
        assert torch.equal(runs[0][key], runs[1][key]), key


@pytest.mark.slow
def test_kill_9_mid_run_then_resume_gives_bit_identical_weights(tmp_path):
    """A training process killed with SIGKILL once an epoch's state is saved, then ``--resume``: the weights of an
    uninterrupted run, to the bit."""
    import signal
    import subprocess
    import sys
    import time

    from seqvpr.data.sources import save_traversal_npz

    reference, query = route(600, 64, 4)
    save_traversal_npz(tmp_path / "ref.npz", Traversal.from_descriptors(reference, "ref"))
    save_traversal_npz(tmp_path / "qry.npz", Traversal.from_descriptors(query, "qry"))

    def command(out, *extra):
        return [sys.executable, "-c", "from seqvpr.cli import main; main()", "train", "seqmatchnet",
                "-r", str(tmp_path / "ref.npz"), "-q", str(tmp_path / "qry.npz"), "--train-frames", "0:450",
                "--val-frames", "450:600", "--radius", "1f", "-L", "5", "--epochs", "6", "--out", str(out), *extra]

    env = {**os.environ, "OMP_NUM_THREADS": "2"}
    whole = subprocess.run(command(tmp_path / "whole"), capture_output=True, text=True, timeout=300, env=env)
    assert whole.returncode == 0, whole.stderr
    killed = subprocess.Popen(command(tmp_path / "killed"), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)
    state = tmp_path / "killed" / STATE_JSON
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and not (state.exists() and json.loads(state.read_text())["state_dir"] != "state/epoch_0000"):
        time.sleep(0.05)
    killed.send_signal(signal.SIGKILL)
    killed.wait()
    assert killed.returncode == -signal.SIGKILL
    saved = json.loads(state.read_text())["state_dir"]
    assert saved != "state/epoch_0006"  # it really was cut short
    resumed = subprocess.run(command(tmp_path / "killed", "--resume"), capture_output=True, text=True, timeout=300,
                             env=env)
    assert resumed.returncode == 0, resumed.stderr
    a, b = weights(tmp_path / "whole"), weights(tmp_path / "killed")
    for key in a:
        assert torch.equal(a[key], b[key]), key
