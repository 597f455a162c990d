"""`seqvpr train seqnet`, `seqvpr train jist` and `seqvpr match --model` on their folders, against the library:
the command line must score exactly what the library functions score, and bad input is one line without output."""

import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from seqvpr.cli import cli
from seqvpr.cli.train import train_jist_command, train_seqmatchnet_command, train_seqnet_command
from seqvpr.data.ground_truth import Radius, ground_truth_within_radius, parse_radius
from seqvpr.training.data import classification_traversals, training_data, training_pairs
from seqvpr.data.sources import load_traversal, save_traversal_npz
from seqvpr.synthetic.routes import generate_route
from seqvpr.synthetic.world import write_demo_world
from seqvpr.matchers.retrieval import RetrievalMatcher
from seqvpr.matchers.sequence import SequenceMatcher
from seqvpr.evaluation.scoring import evaluate_match
from seqvpr.sequences.match_settings import MatchSettings
from seqvpr.sequences.windows import SequenceSpec
from seqvpr.models.jist import describe_with_jist, load_jist
from seqvpr.cli.train import jist_values
from seqvpr.models.configs import JistConfig
from seqvpr.training.jist import jist_setup
from seqvpr.training.settings import THUMBNAIL_RECIPE, with_recipe
from seqvpr.training.settings import JistTrainSettings
from seqvpr.training.seqmatchnet import SeqMatchNetSettings
from seqvpr.models.seqnet import load_seqnet
from seqvpr.training.settings import SeqNetSettings
from tests.helpers import run_cli

SEQNET_ARGS = ["--train-frames", "0:90", "--val-frames", "90:120", "--radius", "5m", "--neg-radius", "20m", "-L", "4",
               "--w", "2", "--out-dim", "8", "--epochs", "2", "--batch-size", "8", "--negative-pool", "30",
               "--optimizer", "adam", "--lr", "3e-3", "--weight-decay", "0"]
JIST_ARGS = ["--train-frames", "0:30", "--val-frames", "30:40", "--radius", "25m", "--pos-radius", "10m",
             "--backbone", "efficientnet-lite0", "--out-dim", "32", "-L", "3", "--epochs", "1", "--refreshes", "1",
             "--max-iterations", "2", "--batch-size", "2", "--images-per-batch", "8", "--image-size", "64x48",
             "--cell-size", "15", "--min-images", "2"]
KS = (1, 5, 10)


def invoke(*args) -> tuple[str, str]:
    """``seqvpr ARGS`` through click's CliRunner; must succeed; returns (stdout, stderr)."""
    result = CliRunner().invoke(cli, [str(a) for a in args], catch_exceptions=False)
    assert result.exit_code == 0, result.output
    return result.stdout, result.stderr


@pytest.fixture(scope="module")
def route(tmp_path_factory) -> tuple[Path, Path]:
    """Descriptor traversal files (16-D, positions 2 m apart) of one synthetic route."""
    folder = tmp_path_factory.mktemp("route")
    reference, query = generate_route(n_frames=150, dim=16, seed=3)
    save_traversal_npz(folder / "ref.npz", reference)
    save_traversal_npz(folder / "qry.npz", query)
    return folder / "ref.npz", folder / "qry.npz"


@pytest.fixture(scope="module")
def seqnet_run(route, tmp_path_factory) -> tuple[Path, str, str]:
    ref, qry = route
    out = tmp_path_factory.mktemp("seqnet") / "run"
    stdout, stderr = invoke("train", "seqnet", "-r", ref, "-q", qry, *SEQNET_ARGS, "--out", out)
    return out, stdout, stderr


@pytest.fixture(scope="module")
def world(tmp_path_factory) -> dict[str, Path]:
    return write_demo_world(tmp_path_factory.mktemp("world"), frames=40, width=64, height=48, seed=0,
                            query_condition="dusk")


@pytest.fixture(scope="module")
def jist_run(world, tmp_path_factory) -> tuple[Path, str, str]:
    out = tmp_path_factory.mktemp("jist") / "run"
    stdout, stderr = invoke("train", "jist", "-r", world["train_reference"], "-q", world["train_query"], *JIST_ARGS,
                            "--out", out)
    return out, stdout, stderr


# --- SeqNet ---------------------------------------------------------------------------------------------------------


def test_option_defaults_are_each_models_settings_defaults():
    """One shared option list, each command with its own model's defaults (SeqNet: 200 epochs, lr 1e-4, ...)."""
    fields = ("epochs", "lr", "lr_step", "lr_gamma", "select_k", "refresh_every", "negatives", "batch_size",
              "margin", "momentum", "weight_decay", "optimizer", "seed")
    for command, settings in ((train_seqnet_command, SeqNetSettings()), (train_seqmatchnet_command, SeqMatchNetSettings())):
        defaults = {p.name: p.default for p in command.params}
        assert {f: defaults[f] for f in fields} == {f: getattr(settings, f) for f in fields}
        assert defaults["seq_len"] == settings.sequence.length
        assert defaults["ks"] == ",".join(map(str, settings.ks))
    seqnet = {p.name: p.default for p in train_seqnet_command.params}
    assert seqnet["refresh_every"] is None and seqnet["w"] == 3 and seqnet["epochs"] == 200
    assert "velocities" not in seqnet and "hidden" not in seqnet
    jist = {p.name: p for p in train_jist_command.params}
    settings, model = JistTrainSettings(), JistConfig()
    # JIST's recipe-dependent options are left unset and the recipe fills them: each help names both defaults,
    # and a command line that gives none of them trains large frames with the settings' defaults
    assert f"[default: {settings.epochs:g}; thumbnails: {THUMBNAIL_RECIPE['epochs']:g}]" in jist["epochs"].help
    assert f"[default: {settings.width}x{settings.height}; thumbnails: their own size]" in jist["image_size"].help
    parsed = train_jist_command.make_context("jist", ["-r", "a", "-q", "b", "--train-frames", "0:9", "--val-frames",
                                                      "9:12", "--radius", "1f"]).params
    for size, expected in (((640, 480), (settings, model)), ((64, 32), None)):
        config, run = jist_setup(with_recipe(jist_values(parsed), size))
        if expected is None:
            assert (config.backbone, run.width, run.epochs) == ("thumbnail-cnn", 64, THUMBNAIL_RECIPE["epochs"])
            continue
        assert (run.epochs, run.refreshes, run.width, run.height, run.batch_size) == (
            settings.epochs, settings.refreshes, settings.width, settings.height, settings.batch_size)
        assert (config.backbone, config.lr, config.out_dim) == (model.backbone, model.lr, model.out_dim)


def test_train_seqnet_writes_its_model_folder(seqnet_run):
    out, stdout, stderr = seqnet_run
    assert stdout.startswith("best epoch") and f"seqvpr match --model {out}" in stdout
    assert "epoch 2:" in stderr and "validation R@1" in stderr
    model, config = load_seqnet(out)
    assert (config["in_dim"], config["out_dim"], config["w"], config["L"]) == (16, 8, 2, 4)
    assert config["training"]["refresh_every"] is None and config["training"]["select_k"] == 5
    assert len((out / "history.csv").read_text().splitlines()) == 4  # header, epoch 0 (untrained), 1, 2


def seqnet_library(route, run_dir, rerank=0):
    """What the library scores on the test frames 120:150 with the SeqNet of ``run_dir`` (optionally HVPR)."""
    model, config = load_seqnet(run_dir)
    ref, qry = (load_traversal(p, role).slice_frames(120, 150) for p, role in zip(route, ("reference", "query")))
    settings = MatchSettings(SequenceSpec(config["L"]), k=20)
    shortlist = dataclasses.replace(settings, k=max(rerank, 20))
    result = RetrievalMatcher(shortlist, "seqnet", model).topk(ref, qry)
    if rerank:
        result = SequenceMatcher(settings).rerank(result.reference, result.query, result.topk)
    return evaluate_match(result, ground_truth_within_radius(qry, ref, Radius(5.0, "m")), (1, 5, 10, 20))


@pytest.mark.parametrize("rerank", [0, 10])
def test_match_with_a_seqnet_model_equals_the_library(route, seqnet_run, tmp_path, rerank):
    ref, qry = route
    out, _, _ = seqnet_run
    stdout, _ = invoke("match", "-r", ref, "-q", qry, "--frames", "120:150", "--radius", "5m", "--model", out,
                       "--rerank", rerank, "--json", "--out", tmp_path / "m")
    result = json.loads(stdout)
    expected = seqnet_library(route, out, rerank)
    assert result["recall"] == {str(k): v for k, v in expected.recall.items()}
    assert result["queries_evaluated"] == expected.queries_evaluated
    settings = result["settings"]
    assert (settings["method"], settings["model_kind"], settings["sequence"]["length"]) == ("seqnet", "seqnet", 4)
    assert (tmp_path / "m" / "predictions.csv").is_file()


# --- JIST -----------------------------------------------------------------------------------------------------------


def test_train_jist_writes_a_loadable_model(jist_run):
    out, stdout, stderr = jist_run
    assert stdout.startswith("best epoch") and "validation R@1" in stdout and f"model: {out}" in stdout
    assert "epoch 1: loss" in stderr and "images" in stderr and "sequence" in stderr and "validation R@1" in stderr
    model = load_jist(out)
    config = json.loads((out / "config.json").read_text())
    assert config["image_size"] == [64, 48] and config["config"]["seq_length"] == 3
    assert config["config"]["trainable_stages"] == ["stage7", "head"]  # efficientnet-lite0's default
    assert (config["training"]["grouping"]["cell_m"], config["training"]["max_iterations"]) == (15.0, 2)
    assert model.dim == 32 and len((out / "history.csv").read_text().splitlines()) == 3  # header, epochs 0 and 1


def test_match_with_a_jist_model_equals_the_library(world, jist_run, tmp_path):
    out, _, _ = jist_run
    stdout, _ = invoke("match", "-r", world["test_reference"], "-q", world["test_query"], "--radius", "25m",
                       "--model", out, "--k", "1,5,10", "--json", "--out", tmp_path / "m", "--engine", "torch")
    result = json.loads(stdout)  # the oracle runs torch: ONNX Runtime's agreement is tests/features/test_engines.py's
    ref, qry = load_traversal(world["test_reference"], "reference"), load_traversal(world["test_query"], "query")
    model = load_jist(out)  # oracle: the model's frames, pooled by its SeqGeM, searched exactly
    ref, qry = (describe_with_jist(model, t, 64, 48) for t in (ref, qry))
    found = RetrievalMatcher(MatchSettings(SequenceSpec(3), k=10), "seqgem", model.sequence_pool).topk(ref, qry)
    expected = evaluate_match(found, ground_truth_within_radius(qry, ref, Radius(25.0, "m")), KS)
    assert result["recall"] == {str(k): v for k, v in expected.recall.items()}
    assert result["queries_evaluated"] == expected.queries_evaluated
    settings = result["settings"]
    assert (settings["method"], settings["descriptor"], settings["sequence"]["length"]) == ("jist", "jist", 3)


def test_a_jist_models_frames_go_with_any_method(world, jist_run, tmp_path):
    """``--model JIST --method matching`` matches JIST's frame encoder's descriptors (what ``extract --model`` writes)
    by plain sequence matching: the same figures as matching those files."""
    out, _, _ = jist_run
    common = ("--radius", "25m", "--k", "1,5,10", "--json", "-L", "3", "--method", "matching")
    stdout, _ = invoke("match", "-r", world["test_reference"], "-q", world["test_query"], "--model", out, *common,
                       "--out", tmp_path / "m")
    for side in ("test_reference", "test_query"):
        invoke("extract", world[side], "--model", out, "--role", "query" if "query" in side else "reference",
               "--out", tmp_path / f"{side}.npz")
    frames = json.loads(invoke("match", "-r", tmp_path / "test_reference.npz", "-q", tmp_path / "test_query.npz",
                               *common, "--out", tmp_path / "f")[0])
    result = json.loads(stdout)
    assert result["recall"] == frames["recall"] and result["queries_evaluated"] == frames["queries_evaluated"]
    assert result["settings"]["method"] == "matching"


def test_the_ablations_sequence_matching_over_jist_frames_is_the_command_lines(world, jist_run, tmp_path):
    """The JIST ablation's forward "sequence matching" row (over the trained model's frames) is what ``seqvpr match
    --model RUN --method matching -L`` prints: one path."""
    from seqvpr.experiments.jist_ablation import JistSplit, robustness_rows

    out, _, _ = jist_run
    test = tuple(load_traversal(world[side], role) for side, role in (("test_reference", "reference"),
                                                                      ("test_query", "query")))
    split = JistSplit(test, test, test, Radius(25.0, "m"))
    rows = dict(robustness_rows(out, split, lengths=(3,)))
    stdout, _ = invoke("match", "-r", world["test_reference"], "-q", world["test_query"], "--model", out, "--radius",
                       "25m", "--k", "1,5,10", "--json", "-L", "3", "--method", "matching", "--out", tmp_path / "m")
    assert json.loads(stdout)["recall"] == {str(k): v for k, v in rows["L = 3"]["sequence matching"].recall.items()}


def image_folders(world: dict[str, Path], tmp_path: Path, keys: tuple[str, ...]) -> dict[str, Path]:
    """Copies of the world's traversals as bare image folders (frame-aligned, no positions)."""
    folders = {}
    for key in keys:
        folders[key] = tmp_path / key
        folders[key].mkdir()
        for image in sorted(world[key].glob("*.jpg")):
            shutil.copy(image, folders[key] / image.name)
    return folders


def test_frame_radius_places_frame_aligned_images_along_the_route(world, tmp_path):
    """Image folders without positions (Nordland-like): --radius 1f counts frames, negatives outside 2.5 frames."""
    folders = image_folders(world, tmp_path, ("train_reference", "train_query"))
    train, validation, _ = training_pairs(str(folders["train_reference"]), str(folders["train_query"]), "0:30",
                                          "30:40", lambda r, q: (r, q))
    data = training_data("jist", train, validation, parse_radius("1f"))
    one = parse_radius("1f")
    assert (data.positive_radius, data.negative_radius, data.val_radius) == (one, Radius(2.5, one.unit), one)
    np.testing.assert_array_equal(data.val_query.positions[:, 0], np.arange(30, 40))
    np.testing.assert_array_equal(data.reference.positions[:, 0], np.arange(30))


def test_class_images_add_a_traversals_training_frames_placed_as_the_pair(world, tmp_path):
    """``--class-images``: a third frame-aligned traversal's --train-frames join the classification images, placed
    along the route as the training pair is (its frame i at position i); no extra source keeps the default."""
    folders = image_folders(world, tmp_path, ("train_reference", "train_query", "test_query"))
    train, validation, _ = training_pairs(str(folders["train_reference"]), str(folders["train_query"]), "5:30",
                                          "30:40", lambda r, q: (r, q))
    data = training_data("jist", train, validation, parse_radius("1f"))
    assert classification_traversals(data, (), "5:30") is None
    traversals = classification_traversals(data, [str(folders["test_query"])], "5:30", frames="0:38")
    assert traversals[:2] == (data.reference, data.query) and len(traversals) == 3
    extra = traversals[2]
    np.testing.assert_array_equal(extra.positions[:, 0], np.arange(5, 30))
    assert [Path(p).name for p in extra.image_paths] == sorted(p.name for p in world["test_query"].glob("*.jpg"))[5:30]


# --- one-line errors, no output -------------------------------------------------------------------------------------


def bad_cases(route, world, seqnet_run, jist_run, tmp_path):
    ref, qry = route
    unknown = tmp_path / "unknown"
    unknown.mkdir()
    (unknown / "config.json").write_text('{"format": "someone-elses"}')
    match = ["match", "-r", ref, "-q", qry, "--radius", "5m"]
    images = ["-r", world["train_reference"], "-q", world["train_query"]]
    return {
        "method without model": ([*match, "--method", "seqnet"], "--method seqnet needs a SeqNet model (--model; seqvpr train seqnet --out), got none"),
        "seqnet model, other method": ([*match, "--model", seqnet_run[0], "--method", "delta"], "use --method seqnet"),
        "jist method, seqnet model": ([*match, "--model", seqnet_run[0], "--method", "jist"], "got a SeqNet model"),
        "jist model on descriptors": ([*match, "--model", jist_run[0]], "descriptors only"),
        "missing model folder": ([*match, "--model", tmp_path / "absent"], "no such model folder"),
        "unknown model format": ([*match, "--model", unknown], f"{unknown / 'config.json'}: unknown model format"),
        "frame radius with positions": (["train", "jist", *images, *JIST_ARGS, "--radius", "1f", "--pos-radius", "1f"],
                                        "has positions; give the radius in metres"),
        "mixed radius units": (["train", "jist", *images, *JIST_ARGS, "--neg-radius", "3f"], "share one unit"),
        "jist on descriptors": (["train", "jist", "-r", ref, "-q", qry, *JIST_ARGS], "holds descriptors only"),
        "seqnet w longer than L": (["train", "seqnet", "-r", ref, "-q", qry, *SEQNET_ARGS, "--w", "5"],
                                   "shorter than the temporal kernel width w=5"),
        "two models of one kind": ([*match, "--model", seqnet_run[0], "--model", seqnet_run[0]],
                                   "a second seqnet model"),
        "extract --model of a SeqNet": (["extract", world["test_query"], "--model", seqnet_run[0], "--out",
                                         tmp_path / "x.npz"], "give one model that describes images"),
        "single at another length": ([*match, "--method", "single", "-L", "5"], "uses L = 1"),
        "cells wider than negatives": (["train", "jist", *images, *JIST_ARGS, "--cell-size", "20"],
                                       "wider than the negative radius 25m"),
        "hue beyond half a turn": (["train", "jist", *images, *JIST_ARGS, "--hue", "0.7"], "'--hue': 0.7 is not in [0, 0.5]"),
        "missing class images": (["train", "jist", *images, *JIST_ARGS, "--class-images", tmp_path / "nowhere"],
                                 f"{tmp_path / 'nowhere'}: no such file or folder"),
    }


CASES = ["method without model", "seqnet model, other method", "jist method, seqnet model",
         "jist model on descriptors", "missing model folder", "unknown model format", "frame radius with positions",
         "mixed radius units", "jist on descriptors", "seqnet w longer than L", "two models of one kind",
         "extract --model of a SeqNet", "single at another length", "cells wider than negatives", "hue beyond half a turn",
         "missing class images"]


@pytest.mark.parametrize("case", CASES)
def test_bad_input_is_one_line_without_output(monkeypatch, capsys, tmp_path, route, world, seqnet_run, jist_run, case):
    args, needle = bad_cases(route, world, seqnet_run, jist_run, tmp_path)[case]
    out = tmp_path / "out"
    code, stdout, stderr = run_cli(monkeypatch, capsys, *args, "--out", out)
    assert code == 2, stderr
    assert stderr.startswith("seqvpr: error:") and stderr.count("\n") == 1 and needle in stderr, stderr
    assert stdout == "" and not out.exists()


def test_match_hvpr_with_two_models_equals_the_library_match(route, seqnet_run, tmp_path):
    """``--model SEQNET --model SEQMATCHNET --method hvpr``: the benchmark's HVPR row from the command line."""
    from seqvpr.api import match
    from seqvpr.models.configs import TransformConfig
    from seqvpr.models.registry import load_trained_model
    from seqvpr.models.seqmatchnet import FrameTransform, save_seqmatchnet

    save_seqmatchnet(tmp_path / "smn", FrameTransform(TransformConfig(16), seed=3), {"sequence": {"length": 4}})
    ref, qry = route
    stdout, _ = invoke("match", "-r", ref, "-q", qry, "--frames", "120:150", "--radius", "5m", "--model", seqnet_run[0],
                       "--model", tmp_path / "smn", "--method", "hvpr", "--json", "--out", tmp_path / "m")
    result = json.loads(stdout)
    models = {m.kind: m for m in (load_trained_model(seqnet_run[0]), load_trained_model(tmp_path / "smn"))}
    reference, query = (load_traversal(p, role).slice_frames(120, 150) for p, role in zip(route, ("reference", "query")))
    found = match(reference, query, "hvpr", models=models, settings=MatchSettings(SequenceSpec(4), k=20))
    expected = evaluate_match(found, ground_truth_within_radius(query, reference, Radius(5.0, "m")), (1, 5, 10, 20))
    assert result["recall"] == {str(k): v for k, v in expected.recall.items()}
    assert result["settings"]["model_kind"] == ["seqnet", "seqmatchnet"] and result["settings"]["method"] == "hvpr"
