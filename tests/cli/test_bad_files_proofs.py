"""Saved artifacts prove what they are (issue 28): a model folder whose weights and config come from different runs,
a training state whose files were changed or that would resume on another split, a localiser state of another
format, with impossible counters or beliefs or from another map, and a ``localizer.json`` with a threshold that is
not a number or recorded for another map: each is one ``seqvpr: error`` line naming the file, exit status 2, no
partial output, and the files themselves left as they were. Harmless changes (a config re-indented, a state re-saved)
give the same result."""

from __future__ import annotations

import hashlib
import json
import shutil

import numpy as np
import pytest

from seqvpr.localization import Localizer
from seqvpr.localization.localizer import LocalizerSettings
from seqvpr.maps import open_map
from tests.helpers import QuietCapsys, run_bad_case, run_cli, write_route_files

TRAIN = ("train", "seqmatchnet", "-r", "{w}/ref.npz", "-q", "{w}/qry.npz", "--radius", "10m", "--train-frames",
         "0:50", "--val-frames", "50:80", "-L", "3", "--epochs", "1", "--negative-pool", "10")
MATCH = ("match", "-r", "{w}/ref.npz", "-q", "{w}/qry.npz", "--radius", "10m", "-L", "3", "--json")
LOCALIZE = ("localize", "-q", "{w}/qry.npz", "--out", "{out}")



def cli(*args) -> None:
    code = run_cli(pytest.MonkeyPatch(), QuietCapsys(), *map(str, args))[0]
    assert code == 0, args


def rewrite_json(path, change) -> None:
    values = json.loads(path.read_text())
    change(values)
    path.write_text(json.dumps(values))


def rewrite_state(source, target, header=None, arrays=None) -> None:
    """A copy of a saved localiser state with header fields and arrays replaced."""
    with np.load(source) as data:
        values = {k: data[k] for k in data.files}
    values["header"] = np.array(json.dumps({**json.loads(str(values["header"])), **(header or {})}))
    np.savez(target, **{**values, **(arrays or {})})


def saved_state(folder, path, **settings) -> None:
    localizer = Localizer.open(folder, **settings)
    for row in np.load(folder.parent / "qry.npz")["descriptors"][:12]:
        localizer.update(row)
    localizer.save_state(path)


def two_maps_alike(w) -> None:
    """``map_a`` and ``map_b``: other frames (so other identities), the same count, dimension and second of
    creation."""
    cli("map", "build", w / "ref.npz", "--out", w / "map_a")
    cli("map", "build", w / "qry.npz", "--out", w / "map_b")
    created = json.loads((w / "map_a" / "map.json").read_text())["created"]
    rewrite_json(w / "map_b" / "map.json", lambda v: v.update(created=created))


def calibrated_maps(w) -> None:
    """Copies of the map, each with a ``localizer.json`` damaged in one way."""
    key = LocalizerSettings().key()
    good = {"settings": key, "threshold": 0.2, "target_precision": 0.9, "precision": 0.95, "reached": True}
    bad = {"nan_text": {**good, "threshold": "NaN"}, "inf": {**good, "threshold": float("inf")},
           "nan": {**good, "threshold": float("nan")}, "negative": {**good, "threshold": -0.5},
           "text": {**good, "threshold": "0.2"}, "no_threshold": {k: v for k, v in good.items() if k != "threshold"},
           "precision": {**good, "precision": "high"}}
    for name, entry in bad.items():
        shutil.copytree(w / "map", w / f"cal_{name}")
        (w / f"cal_{name}" / "localizer.json").write_text(json.dumps(
            {"format": "seqvpr-localizer", "version": 1, "calibrations": [entry]}))
    shutil.copytree(w / "map", w / "cal_nokeys")
    (w / "cal_nokeys" / "localizer.json").write_text('{"format": "seqvpr-localizer", "version": 1}')
    shutil.copytree(w / "map_a", w / "cal_other")
    (w / "cal_other" / "localizer.json").write_text(json.dumps(
        {"format": "seqvpr-localizer", "version": 1, "map": "sha256:" + "c" * 64, "calibrations": [good]}))


def damaged_states(w) -> None:
    saved_state(w / "map", w / "state.npz")
    saved_state(w / "map", w / "state_hmm.npz", method="hmm")
    rewrite_state(w / "state.npz", w / "state_v2.npz", {"version": 99})
    rewrite_state(w / "state.npz", w / "state_negative.npz", {"misses": -1})
    rewrite_state(w / "state.npz", w / "state_inf.npz", {"frame": float("inf")})
    rewrite_state(w / "state.npz", w / "state_fraction.npz", {"since_reset": 2.5})
    rewrite_state(w / "state.npz", w / "state_count.npz", arrays={"matcher_count": np.array(np.inf)})
    with np.load(w / "state.npz") as data:
        partial = data["matcher_ring"].copy()
    partial[0, 3] = np.nan
    rewrite_state(w / "state.npz", w / "state_sums.npz", arrays={"matcher_ring": partial})
    with np.load(w / "state_hmm.npz") as data:
        belief = data["matcher_belief"].copy()
    rewrite_state(w / "state_hmm.npz", w / "state_belief.npz", arrays={"matcher_belief": belief * 3})
    belief[4] = np.nan
    rewrite_state(w / "state_hmm.npz", w / "state_belief_nan.npz", arrays={"matcher_belief": belief})
    saved_state(w / "map_a", w / "state_a.npz")
    rewrite_state(w / "state.npz", w / "state_kept.npz", arrays={"last_kept": np.zeros(3, np.float32)})


def trained_runs(w) -> None:
    """A run, a second run of other weights, a model folder mixing them, and runs damaged in one way each."""
    cli(*(a.format(w=w) for a in TRAIN), "--out", w / "run")
    cli(*(a.format(w=w) for a in TRAIN), "--seed", "9", "--out", w / "run2")
    shutil.copytree(w / "run", w / "mixed")
    shutil.copy(w / "run2" / "model.safetensors", w / "mixed" / "model.safetensors")
    shutil.copytree(w / "run", w / "version")
    rewrite_json(w / "version" / "config.json", lambda v: v.update(version=99))
    shutil.copytree(w / "run", w / "run_state")
    state = w / "run_state" / json.loads((w / "run" / "train_state.json").read_text())["state_dir"]
    (state / "train_state.safetensors").write_bytes((state / "train_state.safetensors").read_bytes()[:-4] + b"\0\0\0\0")
    shutil.copytree(w / "run", w / "run_split")
    cli("map", "build", w / "ref.npz", "--model", w / "run", "--out", w / "map_model")


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    w = tmp_path_factory.mktemp("proofs")
    write_route_files(w, 80, 16, 2)
    cli("map", "build", w / "ref.npz", "--out", w / "map")
    two_maps_alike(w)
    calibrated_maps(w)
    damaged_states(w)
    trained_runs(w)
    return w


RESUME = (*TRAIN, "--resume")
CASES = {
    # --- model folders
    "match: weights of another run under a config": ((*MATCH, "--model", "{w}/mixed"),
                                                    "mixed/model.safetensors: its content is not what"),
    "match: a model folder of another version": ((*MATCH, "--model", "{w}/version"), "model folder version 99"),
    "match --map: a model of the same kind and shape, other weights": (
        ("match", "--map", "{w}/map_model", "-q", "{w}/qry.npz", "--radius", "10m", "--model", "{w}/run2"),
        "is not the seqmatchnet model"),
    # --- training runs
    "train --resume: a state file changed since it was written": ((*RESUME[:-1], "--out", "{w}/run_state", "--resume"),
                                                                  "train_state.safetensors: its content is not what"),
    "train --resume: another training split": ((*(a.replace("0:50", "0:45") for a in TRAIN), "--out", "{w}/run_split",
                                                "--resume"), "trained on other data"),
    # --- localiser states
    "localize: a state of another format version": ((*LOCALIZE, "--map", "{w}/map", "--resume-state", "{w}/state_v2.npz"),
                                                    "state_v2.npz: localiser state version 99"),
    "localize: a negative counter": ((*LOCALIZE, "--map", "{w}/map", "--resume-state", "{w}/state_negative.npz"),
                                     "state_negative.npz: misses -1 is not a count"),
    "localize: an infinite counter": ((*LOCALIZE, "--map", "{w}/map", "--resume-state", "{w}/state_inf.npz"),
                                      "state_inf.npz: frame inf is not a count"),
    "localize: a fractional counter": ((*LOCALIZE, "--map", "{w}/map", "--resume-state", "{w}/state_fraction.npz"),
                                       "since_reset 2.5 is not a count"),
    "localize: an infinite matcher count": ((*LOCALIZE, "--map", "{w}/map", "--resume-state", "{w}/state_count.npz"),
                                            "matcher_count"),
    "localize: NaN distance rows": ((*LOCALIZE, "--map", "{w}/map", "--resume-state", "{w}/state_sums.npz"),
                                   "matcher_ring holds NaN"),
    "localize: a last frame of another dimension": ((*LOCALIZE, "--map", "{w}/map", "--resume-state",
                                                    "{w}/state_kept.npz"), "state_kept.npz: last_kept has shape (3,)"),
    "localize: a belief above 1": ((*LOCALIZE, "--map", "{w}/map", "--method", "hmm", "--resume-state",
                                    "{w}/state_belief.npz"), "matcher_belief is not a belief"),
    "localize: a NaN belief": ((*LOCALIZE, "--map", "{w}/map", "--method", "hmm", "--resume-state",
                                "{w}/state_belief_nan.npz"), "state_belief_nan.npz: matcher_belief is not a belief"),
    "localize: a state of another map of the same count, dimension and second": (
        (*LOCALIZE, "--map", "{w}/map_b", "--resume-state", "{w}/state_a.npz"),
        "state_a.npz: a localiser state for another map (identity"),
    # --- localizer.json
    **{f"localize: localizer.json threshold {name}": ((*LOCALIZE, "--map", f"{{w}}/cal_{name}"), fragment)
       for name, fragment in {
           "nan_text": "localizer.json: calibration 1 threshold 'NaN' is not a number",
           "inf": "localizer.json: calibration 1 threshold inf is not a number",
           "nan": "localizer.json: calibration 1 threshold nan is not a number",
           "negative": "localizer.json: calibration 1 threshold -0.5 is not a number >= 0",
           "text": "localizer.json: calibration 1 threshold '0.2' is not a number",
           "no_threshold": "localizer.json: calibration 1 has no threshold",
           "precision": "localizer.json: calibration 1 precision 'high' is not a number in [0, 1]",
           "nokeys": "localizer.json: malformed (no list of calibrations)",
           "other": "localizer.json: calibrated for another map",
       }.items()},
}


def snapshot(world) -> dict[str, str]:
    return {str(p.relative_to(world)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(world.rglob("*")) if p.is_file() and ".seqvpr-lock" not in p.name}


@pytest.mark.parametrize("case", list(CASES))
def test_a_file_that_is_not_what_it_claims_is_one_line_exit_2_and_changes_nothing(world, tmp_path, monkeypatch,
                                                                                  capsys, case):
    args, fragment = CASES[case]
    out = tmp_path / "out"
    before = snapshot(world)
    run_bad_case(monkeypatch, capsys, args, fragment, world, out)
    assert snapshot(world) == before


def test_harmless_changes_give_the_same_result(world, tmp_path, monkeypatch, capsys):
    """A config re-indented, a map's calibration-free copy, a state re-saved: the same answers as the originals."""
    args = [a.format(w=world) for a in MATCH]
    code, original, err = run_cli(monkeypatch, capsys, *args, "--model", world / "run")
    assert code == 0, err
    shutil.copytree(world / "run", tmp_path / "reindented")
    config = tmp_path / "reindented" / "config.json"
    config.write_text(json.dumps(json.loads(config.read_text()), indent=8, sort_keys=True))
    code, again, err = run_cli(monkeypatch, capsys, *args, "--model", tmp_path / "reindented")
    assert code == 0 and json.loads(again)["recall"] == json.loads(original)["recall"], err
    rewrite_state(world / "state.npz", tmp_path / "resaved.npz")  # the same arrays, a new file
    frames = np.load(world / "qry.npz")["descriptors"][12:30]
    estimates = []
    for state in (world / "state.npz", tmp_path / "resaved.npz"):
        localizer = Localizer.open(open_map(world / "map"))
        localizer.restore(state)
        estimates.append([(e.index, e.status, e.score) for e in map(localizer.update, frames)])
    assert estimates[0] == estimates[1]
