"""JIST's ablation: the robustness table's window orders and scores against ``seqvpr.match``, the recipe for
thumbnails, and the command's split checks (one line each, before any training)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from PIL import Image

from seqvpr.api import match
from seqvpr.data.ground_truth import Radius, ground_truth_within_radius
from seqvpr.data.traversal import Traversal
from seqvpr.evaluation.scoring import evaluate_match
from seqvpr.experiments.jist_ablation import ORDERS, ordered_scores, reorder_windows
from seqvpr.sequences.match_settings import MatchSettings
from seqvpr.sequences.descriptors import SeqGeM
from seqvpr.sequences.windows import SequenceSpec
from seqvpr.training.settings import THUMBNAIL_RECIPE, with_recipe
from tests.helpers import examples, run_cli


@settings(max_examples=examples(50))
@given(st.integers(1, 30), st.integers(1, 9), st.sampled_from(ORDERS), st.integers(0, 2**31 - 1))
def test_a_reordered_window_holds_the_same_frames(n, length, order, seed):
    frames = np.arange(n)[:, None] + np.arange(length)[None, :]
    reordered = reorder_windows(frames, order, seed)
    np.testing.assert_array_equal(np.sort(reordered, axis=1), frames)
    if order == "reversed":
        np.testing.assert_array_equal(reordered, frames[:, ::-1])
    if order == "forward":
        np.testing.assert_array_equal(reordered, frames)


def _route(n: int, seed: int, noise: float) -> tuple[Traversal, Traversal]:
    rng = np.random.default_rng(seed)
    places = rng.normal(size=(n, 16)).astype(np.float32)
    query = places + noise * rng.normal(size=places.shape).astype(np.float32)
    make = lambda name, d: Traversal(name, np.arange(n), np.zeros(n, np.int64), descriptors=d)  # noqa: E731
    return make("reference", places), make("query", query)


@settings(max_examples=examples(20), deadline=None)
@given(st.integers(12, 40), st.sampled_from([1, 3, 5]), st.integers(0, 2**31 - 1))
@example(12, 5, 0)  # fewer windows (8) than K (10): the top-K pads with -1/inf
def test_forward_windows_score_as_seqvpr_match_and_seqgem_ignores_the_order(n, length, seed):
    reference, query = _route(n, seed, noise=1.0)
    truth = ground_truth_within_radius(query, reference, Radius(1.0, "frames"))
    pool = SeqGeM()
    scores = {order: ordered_scores(reference, query, truth, length, order, pool, seed) for order in ORDERS}
    spec = MatchSettings(SequenceSpec(length), k=10)
    for name, method in (("JIST", "seqgem"), ("sequence matching", "matching")):
        expected = evaluate_match(match(reference, query, method, settings=spec), truth, (1, 5, 10))
        assert scores["forward"][name].recall == pytest.approx(expected.recall)
        assert scores["forward"][name].queries_evaluated == expected.queries_evaluated
    for order in ORDERS[1:]:
        assert scores[order]["JIST"].recall == pytest.approx(scores["forward"]["JIST"].recall)


def test_reversed_windows_break_sequence_matching_on_a_route_without_repeats():
    reference, query = _route(60, 0, noise=1.6)  # single frames alone are often wrong at this noise
    truth = ground_truth_within_radius(query, reference, Radius(0.0, "frames"))
    scores = {order: ordered_scores(reference, query, truth, 9, order, SeqGeM()) for order in ORDERS}
    matching = {order: s["sequence matching"].recall[1] for order, s in scores.items()}
    assert matching["forward"] > 0.9 and matching["reversed"] < matching["forward"] - 0.3, matching


def test_thumbnails_take_the_recipe_at_their_own_size_and_a_given_value_wins():
    assert with_recipe({"lr": None, "epochs": 7}, (64, 32)) == {
        **THUMBNAIL_RECIPE, "width": 64, "height": 32, "epochs": 7, "recipe": "thumbnails"}
    assert with_recipe({}, (60, 30))["width"] == 64 and with_recipe({}, (60, 30))["height"] == 32  # whole patches
    assert with_recipe({"lr": None}, (640, 480)) == {"recipe": "reference"}
    assert with_recipe({"backbone": "efficientnet-lite0"}, (64, 32))["recipe"] == "reference"
    named = with_recipe({"backbone": "thumbnail-cnn"}, (960, 540))
    assert named["recipe"] == "thumbnails" and (named["width"], named["height"]) == (64, 32)


@pytest.fixture(scope="module")
def thumbnails(tmp_path_factory):
    """Two frame-aligned folders of 40 grey 64x32 frames."""
    root = tmp_path_factory.mktemp("thumbnails")
    rng = np.random.default_rng(0)
    for side in ("summer", "winter"):
        (root / side).mkdir()
        for i in range(40):
            Image.fromarray(rng.integers(0, 256, (32, 64), dtype=np.uint8)).convert("RGB").save(root / side / f"{i:03d}.png")
    return root


@pytest.mark.parametrize("args, fragment", [
    (["--train-frames", "0:20", "--val-frames", "20:30", "--test-frames", "15:40"], "--train-frames 0:20 and --test-frames 15:40 overlap"),
    (["--train-frames", "0:20", "--val-frames", "20:30", "--test-frames", "25:40"], "--val-frames 20:30 and --test-frames 25:40 overlap"),
    (["--train-frames", "0:20", "--val-frames", "20:30", "--test-frames", "30:40", "--cell-size", "4"],
     "wider than the negative radius"),
    (["--train-frames", "0:20", "--val-frames", "20:30", "--test-frames", "30:40", "--variants", "joint,both"],
     "JIST variant 'both' is not known"),
    (["--train-frames", "0:20", "--val-frames", "20:30", "--test-frames", "30:40", "-r", "/nowhere/summer"],
     "/nowhere/summer"),
])
def test_a_bad_split_is_one_line_before_any_training(monkeypatch, capsys, tmp_path, thumbnails, args, fragment):
    out = tmp_path / "ablation"
    code, stdout, stderr = run_cli(monkeypatch, capsys, "ablate", "jist", "-r", thumbnails / "summer", "-q",
                                   thumbnails / "winter", "--radius", "1f", *args, "--out", out)
    assert code == 2 and fragment in stderr and len(stderr.strip().splitlines()) == 1, stderr
    assert not (out / "joint").exists()


def test_the_help_names_the_split(monkeypatch, capsys):
    code, stdout, _ = run_cli(monkeypatch, capsys, "ablate", "jist", "--help")
    assert code == 0
    assert "train on frames 17-1199, select the epoch on 1200-1599, test on 1600-1999" in " ".join(stdout.split())
    assert "--branches" in stdout and "--test-frames" in stdout
