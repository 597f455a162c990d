"""JIST joint training on the synthetic world: loss, mining, classification batches, determinism, reload,
test-time robustness (other sequence length, shuffled frame order) and bad input."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from seqvpr.data.sources import load_traversal
from seqvpr.data.world import write_demo_world
from seqvpr.errors import SeqvprError
from seqvpr.models.jist import JistConfig, build_jist
from seqvpr.training.cosplace import CellGrouping, assign_classes, group_members
from seqvpr.training.jist import (
    ImageStore,
    JistData,
    JistTrainSettings,
    classification_batch,
    describe_with_jist,
    evaluate_jist,
    frame_positions,
    image_windows,
    load_jist,
    mine_triplets,
    pool_windows,
    select_triplets,
    train_jist,
    training_spec,
    used_groups,
    window_batch,
)

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


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> JistData:
    root = tmp_path_factory.mktemp("jist_world")
    paths = write_demo_world(root, frames=40, width=W, height=H, seed=0, query_condition="dusk")
    load = lambda key, role: load_traversal(paths[key], role)  # noqa: E731
    return JistData(
        load("train_reference", "reference"), load("train_query", "query"),
        load("test_reference", "reference"), load("test_query", "query"),
    )


@pytest.fixture(scope="module")
def run(data, tmp_path_factory):
    out = tmp_path_factory.mktemp("jist_run")
    return train_jist(data, CONFIG, SETTINGS, out, backbone_factory=TinyBackbone)


def _model(seed: int = 0):
    torch.manual_seed(seed)
    return build_jist(CONFIG, backbone=TinyBackbone())


def test_joint_loss_goes_down(run):
    totals = [losses["total"] for losses in run.iteration_losses]
    assert len(totals) == SETTINGS.epochs * SETTINGS.refreshes * SETTINGS.max_iterations
    assert all(np.isfinite(totals))
    assert np.mean(totals[-4:]) < np.mean(totals[:4])
    assert [row["epoch"] for row in run.history] == [0, 1]
    assert (run.out_dir / "history.csv").read_text().count("\n") == 3


def test_select_triplets_matches_brute_force():
    rng = np.random.default_rng(3)
    q, r = torch.as_tensor(rng.normal(size=(6, 8))), torch.as_tensor(rng.normal(size=(30, 8)))
    positives = [np.sort(rng.choice(30, size=int(rng.integers(0, 4)), replace=False)) for _ in range(6)]
    near = [np.union1d(p, rng.choice(30, size=5, replace=False)) for p in positives]
    pool = np.sort(rng.choice(30, size=20, replace=False))
    got = {qi: (p, n) for qi, p, n in select_triplets(q, r, positives, near, pool, 3)}
    for qi in range(6):
        if len(positives[qi]) == 0:
            assert qi not in got
            continue
        dist = lambda j: float(torch.dist(q[qi], r[j]))  # noqa: E731
        best = min(positives[qi], key=dist)
        candidates = sorted((j for j in pool if j not in near[qi]), key=dist)
        assert got[qi] == (best, tuple(candidates[:3]))


def test_mined_triplets_against_brute_force(data):
    model = _model()
    settings = dataclasses.replace(SETTINGS, queries_per_refresh=1000, negative_pool=1000, negatives=3)
    spec = training_spec(CONFIG.seq_length)
    qw, rw = image_windows(data.train_query, spec), image_windows(data.train_reference, spec)
    store = ImageStore(W, H)
    triplets = mine_triplets(model, data, qw, rw, settings, np.random.default_rng(0), store)
    with torch.no_grad():  # brute force: every window through the full forward pass, one by one
        qd = torch.cat([model(window_batch(store, data.train_query, qw.frames[i : i + 1], "cpu")) for i in range(len(qw.rows))])
        rd = torch.cat([model(window_batch(store, data.train_reference, rw.frames[i : i + 1], "cpu")) for i in range(len(rw.rows))])
    qxy, rxy = data.train_query.positions[qw.rows], data.train_reference.positions[rw.rows]
    geo = np.linalg.norm(qxy[:, None] - rxy[None], axis=-1)
    with_positive = [i for i in range(len(qw.rows)) if (geo[i] <= data.positive_radius).any()]
    assert len(triplets) > 10 and [t.query for t in triplets] == with_positive
    for t in triplets:
        feat = torch.cdist(qd[t.query : t.query + 1], rd)[0].numpy()
        pos = np.flatnonzero(geo[t.query] <= data.positive_radius)
        assert t.positive == pos[np.argmin(feat[pos])]
        assert (geo[t.query, list(t.negatives)] > data.negative_radius).all()
        outside = np.flatnonzero(geo[t.query] > data.negative_radius)
        hardest = outside[np.argsort(feat[outside], kind="stable")[:3]]
        np.testing.assert_allclose(np.sort(feat[list(t.negatives)]), np.sort(feat[hardest]), rtol=1e-5)


def test_classification_batches_come_from_one_group(data):
    images = data.train_reference
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
    again = train_jist(data, CONFIG, SETTINGS, tmp_path, backbone_factory=TinyBackbone)
    first, second = run.model.state_dict(), again.model.state_dict()
    assert first.keys() == second.keys()
    assert all(torch.equal(first[k], second[k]) for k in first)
    assert again.iteration_losses == run.iteration_losses


def test_saved_model_reloads(data, run):
    loaded = load_jist(run.out_dir, backbone=TinyBackbone())
    windows = image_windows(data.val_query, training_spec(CONFIG.seq_length))
    batch = window_batch(ImageStore(W, H), data.val_query, windows.frames[:6], "cpu")
    with torch.no_grad():
        assert torch.equal(loaded(batch), run.model.eval()(batch))


def test_other_length_and_shuffled_frames(data, run):
    model = run.model.eval()
    store = ImageStore(W, H)
    kwargs = dict(radius=data.val_radius, ks=(1, 5), store=store)
    base = evaluate_jist(model, data.val_reference, data.val_query, seq_length=3, **kwargs)
    longer = evaluate_jist(model, data.val_reference, data.val_query, seq_length=5, **kwargs)
    shuffled = evaluate_jist(model, data.val_reference, data.val_query, seq_length=3, shuffle_frames=True, seed=1, **kwargs)
    assert longer.queries_evaluated < base.queries_evaluated  # longer windows: fewer frames have one
    assert shuffled.recall == base.recall
    np.testing.assert_array_equal(shuffled.correct, base.correct)
    frames = torch.randn(10, 5, CONFIG.out_dim)
    descriptors = nn.functional.normalize(frames, dim=-1)
    order = np.stack([np.random.default_rng(i).permutation(5) for i in range(4)])
    rows = np.arange(20).reshape(4, 5)
    flat = descriptors.reshape(50, -1)
    torch.testing.assert_close(
        pool_windows(model, flat, rows), pool_windows(model, flat, np.take_along_axis(rows, order, 1))
    )


def test_bad_input_is_one_line_error(data, tmp_path):
    no_positions = dataclasses.replace(data.train_query, positions=None)
    with pytest.raises(SeqvprError, match="needs positions") as error:
        dataclasses.replace(data, train_query=no_positions)
    assert "\n" not in str(error.value)
    missing = dataclasses.replace(
        data.val_reference, image_paths=tuple(Path(tmp_path) / f"gone{i}.jpg" for i in range(len(data.val_reference)))
    )
    bad = dataclasses.replace(data, val_reference=missing)
    with pytest.raises(SeqvprError, match="does not exist") as error:
        train_jist(bad, CONFIG, SETTINGS, tmp_path / "out", backbone_factory=TinyBackbone)
    assert "\n" not in str(error.value)


def test_pipeline_retrieval_over_jist_frames_equals_evaluate_jist(data, run):
    """describe_with_jist + retrieve_traversals(seqgem, the model's pool) is JIST's own evaluation (benchmark path)."""
    from seqvpr.data.groundtruth import Radius, ground_truth_within_radius
    from seqvpr.pipeline import MatchSettings, evaluate_match, retrieve_traversals

    model, store = run.model.eval(), ImageStore(W, H)
    reference = describe_with_jist(model, data.val_reference, W, H, store=store)
    query = describe_with_jist(model, data.val_query, W, H, store=store)
    assert reference.descriptors.shape == (len(data.val_reference), CONFIG.out_dim)
    settings = MatchSettings(training_spec(CONFIG.seq_length), k=5)
    result = retrieve_traversals(reference, query, "seqgem", settings, model=model.sequence_pool)
    gt = ground_truth_within_radius(query, reference, Radius(data.val_radius, "m"))
    ours = evaluate_match(result, gt, (1, 5))
    theirs = evaluate_jist(model, data.val_reference, data.val_query, seq_length=CONFIG.seq_length,
                           radius=data.val_radius, ks=(1, 5), store=store)
    assert ours.recall == theirs.recall
    np.testing.assert_array_equal(ours.correct, theirs.correct)


def test_frame_positions_count_frames_along_the_route(data):
    frame_aligned = dataclasses.replace(data.val_query, positions=None, headings=None).select(np.arange(3, 9))
    placed = frame_positions(frame_aligned, spacing=2.0)
    np.testing.assert_array_equal(placed.positions[:, 0], 2.0 * frame_aligned.frame_index)
    assert (placed.positions[:, 1] == 0).all() and (placed.headings == 0).all()
    assert frame_positions(data.val_query) is data.val_query  # positions already known: unchanged
