"""JIST joint training through the one training loop, on the synthetic world: loss, mining against brute force,
classification batches, determinism, resume, reload, test-time robustness (other sequence length, frame order)
and bad input."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from seqvpr.data.ground_truth import Radius
from seqvpr.data.sources import load_traversal
from seqvpr.data.traversal import frame_positions
from seqvpr.models.files import MODEL_FILE, read_json, read_tensors
from seqvpr.models.jist import ImageStore, JistConfig, build_jist, describe_with_jist, load_jist
from seqvpr.matchers.retrieval import RetrievalMatcher
from seqvpr.evaluation.scoring import evaluate_match
from seqvpr.sequences.match_settings import MatchSettings
from seqvpr.sequences.windows import window_frames
from seqvpr.synthetic.world import write_demo_world
from seqvpr.training.cosplace import CellGrouping, assign_classes, group_members
from seqvpr.training.jist import (
    JistLearner,
    JistTrainSettings,
    classification_batch,
    pool_windows,
    train_jist,
    training_spec,
    used_groups,
    window_batch,
)
from seqvpr.training.state import STATE_JSON
from seqvpr.training.trainer import TrainingData, training_context
from tests.helpers import raises_one_line

W, H = 64, 48
GROUPING = CellGrouping(cell_m=10.0, heading_deg=30.0, groups_n=2, groups_l=1, min_images=2)


class TinyBackbone(nn.Module):
    """Two strided convs: a fast stand-in for ResNet-18 (stages ``conv1``, ``conv2``)."""

    out_channels = 16

    def __init__(self) -> None:
        super().__init__()
        self.conv1 = nn.Sequential(nn.Conv2d(3, 8, 3, stride=2, padding=1), nn.BatchNorm2d(8), nn.ReLU())
        self.conv2 = nn.Sequential(nn.Conv2d(8, 16, 3, stride=2, padding=1), nn.ReLU())

    def features(self, images: torch.Tensor) -> torch.Tensor:
        return self.conv2(self.conv1(images))


CONFIG = JistConfig(out_dim=32, seq_length=3, trainable_stages=("conv1", "conv2"), lr=1e-3)
SETTINGS = JistTrainSettings(
    epochs=2, refreshes=2, queries_per_refresh=16, negative_pool=40, batch_size=2, negatives=2, images_per_batch=8,
    max_iterations=4, width=W, height=H, grouping=GROUPING, ks=(1, 5), select_k=5, seed=0,
)
POSITIVE, NEGATIVE = 10.0, 25.0


class LossLog:
    """A training monitor that keeps every step's loss."""

    def __init__(self) -> None:
        self.losses: list[float] = []

    def start_run(self, data, trainable_queries) -> None: ...

    def start_epoch(self, epoch, epochs, queries) -> None: ...

    def advance(self, queries, loss) -> None:
        if loss is not None:
            self.losses.append(loss)

    def end_epoch(self, record) -> None: ...


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> TrainingData:
    root = tmp_path_factory.mktemp("jist_world")
    paths = write_demo_world(root, frames=40, width=W, height=H, seed=0, query_condition="dusk")
    load = lambda key, role: load_traversal(paths[key], role)  # noqa: E731
    return TrainingData(
        load("train_reference", "reference"), load("train_query", "query"),
        load("test_reference", "reference"), load("test_query", "query"),
        Radius(POSITIVE, "m"), Radius(NEGATIVE, "m"), Radius(25.0, "m"),
    )


def _train(data, out, settings=SETTINGS, **kwargs):
    log = LossLog()
    result = train_jist(data, CONFIG, settings, out, backbone_factory=TinyBackbone, monitor=log, **kwargs)
    return result, log


@pytest.fixture(scope="module")
def run(data, tmp_path_factory):
    return _train(data, tmp_path_factory.mktemp("jist_run"))


def _model(seed: int = 0):
    torch.manual_seed(seed)
    return build_jist(CONFIG, backbone=TinyBackbone())


def test_joint_loss_goes_down_and_history_has_its_parts(run):
    result, log = run
    assert len(log.losses) == SETTINGS.epochs * SETTINGS.refreshes * SETTINGS.max_iterations
    assert all(np.isfinite(log.losses))
    assert np.mean(log.losses[-4:]) < np.mean(log.losses[:4])
    assert [r.epoch for r in result.history] == [0, 1, 2]  # epoch 0: the untrained model
    assert all(set(r.parts) == {"sequence", "images"} for r in result.history[1:])
    history = (result.folder / "history.csv").read_text().splitlines()
    assert len(history) == 4 and "loss_images" in history[0] and "loss_sequence" in history[0]


def test_mined_triplets_against_brute_force(data):
    """The learner's mining (frames encoded once, windows pooled) against every window through the full model."""
    model = _model()
    settings = dataclasses.replace(SETTINGS, queries_per_refresh=1000, negative_pool=1000, negatives=3)
    learner = JistLearner(CONFIG, settings)
    context = training_context(data, learner.spec, torch.device("cpu"))
    learner.prepare(context, settings)
    queries = np.flatnonzero(context.query_starts >= 0)
    triplets = learner.mine(model, queries, np.random.default_rng(0))
    store, length = ImageStore(W, H), CONFIG.seq_length
    q_rows, r_rows = queries, np.flatnonzero(context.reference_starts >= 0)
    with torch.no_grad():  # brute force: every window through the full forward pass, one by one
        qd = {int(i): model(window_batch(store, data.query, window_frames(context.query_starts[[i]], length), "cpu"))[0]
              for i in q_rows}
        rd = torch.stack([model(window_batch(store, data.reference, window_frames(context.reference_starts[[j]], length),
                                             "cpu"))[0] for j in r_rows])
    geo = np.linalg.norm(data.query.positions[q_rows][:, None] - data.reference.positions[r_rows][None], axis=-1)
    with_positive = [int(q_rows[i]) for i in range(len(q_rows)) if (geo[i] <= POSITIVE).any()]
    assert len(triplets) > 10 and [t.query for t in triplets] == with_positive
    for t in triplets:
        i = int(np.flatnonzero(q_rows == t.query)[0])
        feat = torch.cdist(qd[t.query][None], rd)[0].numpy()
        pos = np.flatnonzero(geo[i] <= POSITIVE)
        assert t.positive == r_rows[pos[np.argmin(feat[pos])]]
        negatives = np.searchsorted(r_rows, t.negatives)
        assert (geo[i, negatives] > NEGATIVE).all()
        outside = np.flatnonzero(geo[i] > NEGATIVE)
        hardest = outside[np.argsort(feat[outside], kind="stable")[:3]]
        np.testing.assert_allclose(np.sort(feat[negatives]), np.sort(feat[hardest]), rtol=1e-5)


def test_classification_batches_come_from_one_group(data):
    images = data.reference
    class_ids, group_ids = assign_classes(images.positions, images.headings, GROUPING)
    rng = np.random.default_rng(0)
    groups = used_groups(group_ids)
    assert len(groups) >= 2
    for group in groups:
        members, labels_all, n_classes = group_members(class_ids, group_ids, group)
        rows, labels, n = classification_batch(class_ids, group_ids, group, 8, rng)
        assert n == n_classes and len(rows) == 8
        assert (group_ids[rows] == group).all()
        assert ((labels >= 0) & (labels < n_classes)).all()
        lookup = dict(zip(members.tolist(), labels_all.tolist()))
        assert [lookup[r] for r in rows] == labels.tolist()


def test_same_seed_same_weights(data, run, tmp_path):
    (first, first_log), (again, again_log) = run, _train(data, tmp_path)
    a, b = read_tensors(first.folder / MODEL_FILE), read_tensors(again.folder / MODEL_FILE)
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    assert again_log.losses == first_log.losses


def test_resume_after_kill_gives_the_same_weights(data, run, tmp_path):
    """A run killed after epoch 1 and resumed reaches the uninterrupted run's last weights (heads included)."""
    whole, whole_log = run
    _train(data, tmp_path, dataclasses.replace(SETTINGS, epochs=1))
    resumed, resumed_log = _train(data, tmp_path, resume=True)
    last = lambda folder: read_tensors(folder / read_json(folder / STATE_JSON)["state_dir"] / MODEL_FILE)  # noqa: E731
    a, b = last(whole.folder), last(resumed.folder)
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert [r.loss for r in resumed.history] == [r.loss for r in whole.history]
    assert resumed_log.losses == whole_log.losses[len(whole_log.losses) // 2 :]


def test_validation_through_onnx_runtime_gives_the_same_run(data, run, tmp_path, monkeypatch):
    """``engine="onnx"``: each epoch's validation runs an export of that epoch's encoder (checked against torch, not
    kept in the cache); the run's validation recalls and weights are torch's."""
    monkeypatch.setenv("SEQVPR_CACHE", str(tmp_path / "cache"))
    (first, _), (again, _) = run, _train(data, tmp_path / "run", dataclasses.replace(SETTINGS, engine="onnx"))
    assert [r.recall for r in again.history] == [r.recall for r in first.history]
    a, b = read_tensors(first.folder / MODEL_FILE), read_tensors(again.folder / MODEL_FILE)
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert not list((tmp_path / "cache").rglob("*.onnx"))  # an export an epoch, none kept


def test_saved_model_reloads_and_scores_its_validation_recall(data, run):
    """The best model folder loads, and the pipeline's JIST evaluation of it is the recall the loop recorded."""
    result, _ = run
    loaded = load_jist(result.folder, backbone=TinyBackbone())
    saved = read_tensors(result.folder / MODEL_FILE)
    assert all(torch.equal(loaded.state_dict()[k], saved[k]) for k in saved)
    store = ImageStore(W, H)
    reference, query = (describe_with_jist(loaded, t, W, H, store=store) for t in (data.val_reference, data.val_query))
    result_match = RetrievalMatcher(MatchSettings(training_spec(3), k=5), "seqgem", loaded.sequence_pool).topk(
        reference, query)
    from seqvpr.data.ground_truth import ground_truth_within_radius

    gt = ground_truth_within_radius(query, reference, Radius(25.0, "m"))
    assert evaluate_match(result_match, gt, (1, 5)).recall == result.best_recall


def test_other_length_and_shuffled_frames(data, run):
    """A model trained at L = 3 pools any L; SeqGeM does not depend on the order of a window's frames."""
    result, _ = run
    model = load_jist(result.folder, backbone=TinyBackbone())
    store = ImageStore(W, H)
    reference, query = (describe_with_jist(model, t, W, H, store=store) for t in (data.val_reference, data.val_query))
    scored = [RetrievalMatcher(MatchSettings(training_spec(n), k=5), "seqgem", model.sequence_pool).topk(
        reference, query).topk.has_window.sum() for n in (3, 5)]
    assert scored[1] < scored[0]  # longer windows: fewer frames have one
    descriptors = nn.functional.normalize(torch.randn(10, 5, CONFIG.out_dim), dim=-1)
    order = np.stack([np.random.default_rng(i).permutation(5) for i in range(4)])
    rows = np.arange(20).reshape(4, 5)
    flat = descriptors.reshape(50, -1)
    torch.testing.assert_close(
        pool_windows(model, flat, rows), pool_windows(model, flat, np.take_along_axis(rows, order, 1))
    )


def test_bad_input_is_one_line_error(data, tmp_path):
    no_positions = dataclasses.replace(data.reference, positions=None)
    raises_one_line("needs images with positions", train_jist, dataclasses.replace(data, reference=no_positions), CONFIG,
                    SETTINGS, tmp_path / "a", backbone_factory=TinyBackbone)
    missing = dataclasses.replace(
        data.val_reference, image_paths=tuple(Path(tmp_path) / f"gone{i}.jpg" for i in range(len(data.val_reference)))
    )
    raises_one_line("does not exist", train_jist, dataclasses.replace(data, val_reference=missing), CONFIG, SETTINGS,
                    tmp_path / "b", backbone_factory=TinyBackbone)
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def test_frame_positions_count_frames_along_the_route(data):
    frame_aligned = dataclasses.replace(data.val_query, positions=None, headings=None).select(np.arange(3, 9))
    placed = frame_positions(frame_aligned, spacing=2.0)
    np.testing.assert_array_equal(placed.positions[:, 0], 2.0 * frame_aligned.frame_index)
    assert (placed.positions[:, 1] == 0).all() and (placed.headings == 0).all()
    assert frame_positions(data.val_query) is data.val_query  # positions already known: unchanged


@pytest.mark.parametrize("branches", ["joint", "sequence", "images"])
def test_each_branch_is_selectable_and_a_left_out_branch_is_never_computed(data, tmp_path, branches):
    """The loss trains what ``branches`` names: the other part reads 0 in every epoch, and what only it would train
    stays at its initial value (the CosFace heads without classification; the sequence pool without triplets)."""
    config = dataclasses.replace(CONFIG, branches=branches)
    settings = dataclasses.replace(SETTINGS, epochs=1, refreshes=1, max_iterations=2)
    result = train_jist(data, config, settings, tmp_path / "run", backbone_factory=TinyBackbone)
    parts = result.history[1].parts
    assert (parts["sequence"] > 0) == (branches != "images") and (parts["images"] > 0) == (branches != "sequence")
    state = read_tensors(tmp_path / "run" / MODEL_FILE)
    start = build_jist(config, backbone=_seeded_backbone(settings.seed)).state_dict()
    pool_moved = any(not torch.equal(state[k], start[k]) for k in start if k.startswith("sequence_pool."))
    assert pool_moved == (branches != "images")
    assert read_json(tmp_path / "run" / "config.json")["config"]["branches"] == branches


def _seeded_backbone(seed: int) -> nn.Module:
    torch.manual_seed(seed)
    return TinyBackbone()


def test_an_unknown_branch_is_one_line():
    raises_one_line("branches 'both' is not known", JistConfig, branches="both")
