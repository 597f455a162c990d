"""JIST's training components: CosPlace classes and groups, the CosFace head, the joint loss, the optimiser."""

import itertools

import numpy as np
import pytest
import torch
from torch import nn

from seqvpr.models.jist import JistConfig, build_jist
from seqvpr.training.cosplace import CellGrouping, CosFaceHead, assign_classes, cosface_loss, group_members
from seqvpr.models.jist import trainable_parameters
from seqvpr.training.jist import JistLearner, JistLoss, JistTrainSettings, jist_losses
from tests.helpers import raises_one_line
from tests.jist_fixtures import MeanPool, random_images, tiny_model


def loop_classes(positions, headings, g: CellGrouping):
    """Plain oracle: a dict of cell keys, counts, sorted dense ids, the CosPlace modulo rule for groups."""
    keys = []
    for i, (east, north) in enumerate(positions):
        sector = 0 if headings is None else int((headings[i] % 360) // g.heading_deg)
        keys.append((int(east // g.cell_m), int(north // g.cell_m), sector))
    counts = {}
    for key in keys:
        counts[key] = counts.get(key, 0) + 1
    kept = sorted(key for key, count in counts.items() if count >= g.min_images)
    ids = {key: i for i, key in enumerate(kept)}
    classes, groups = [], []
    for key in keys:
        if key in ids:
            e, n, h = key
            classes.append(ids[key])
            groups.append(((e % g.groups_n) * g.groups_n + (n % g.groups_n)) * g.groups_l + (h % g.groups_l))
        else:
            classes.append(-1)
            groups.append(-1)
    return np.array(classes), np.array(groups), keys


@pytest.mark.parametrize("with_headings", [True, False])
def test_assign_classes_matches_a_plain_loop(with_headings):
    rng = np.random.default_rng(1)
    g = CellGrouping(cell_m=10.0, heading_deg=30.0, groups_n=3, groups_l=2, min_images=3)
    dense, sparse = rng.uniform(-40, 80, size=(2700, 2)), rng.uniform(-300, 300, size=(300, 2))
    positions = np.concatenate([dense, sparse])
    headings = rng.uniform(-180, 540, size=3000) if with_headings else None
    classes, groups = assign_classes(positions, headings, g)
    want_classes, want_groups, keys = loop_classes(positions, headings, g)
    np.testing.assert_array_equal(classes, want_classes)
    np.testing.assert_array_equal(groups, want_groups)
    assert (classes == -1).any() and (classes >= 0).any()  # some classes dropped, some kept
    counts = np.bincount(classes[classes >= 0])
    assert counts.min() >= g.min_images and len(counts) == classes.max() + 1  # dense ids
    assert groups.max() < g.n_groups
    # deterministic, and independent of the order of the images
    order = rng.permutation(len(positions))
    again = assign_classes(positions[order], None if headings is None else headings[order], g)
    np.testing.assert_array_equal(again[0], classes[order])
    np.testing.assert_array_equal(again[1], groups[order])

    # no two classes of one group are adjacent cells of one sector, nor adjacent sectors of one cell
    by_class = {}
    for i in np.flatnonzero(classes >= 0):
        by_class[classes[i]] = (keys[i], groups[i])
    for (ka, ga), (kb, gb) in itertools.combinations(by_class.values(), 2):
        if ga != gb:
            continue
        if ka[2] == kb[2]:
            assert max(abs(ka[0] - kb[0]), abs(ka[1] - kb[1])) > 1, (ka, kb)
        if ka[:2] == kb[:2]:
            assert abs(ka[2] - kb[2]) > 1, (ka, kb)


def test_group_members_renumber_one_groups_classes():
    positions = np.array([[0, 0]] * 2 + [[50, 0]] * 2 + [[10, 0]] * 2 + [[25, 25]], dtype=float)
    g = CellGrouping(groups_n=5, groups_l=1, min_images=2)
    classes, groups = assign_classes(positions, None, g)
    assert classes.tolist() == [0, 0, 2, 2, 1, 1, -1] and groups[6] == -1
    images, labels, n = group_members(classes, groups, groups[0])  # cells (0,0) and (5,0) share group 0
    assert images.tolist() == [0, 1, 2, 3] and labels.tolist() == [0, 0, 1, 1] and n == 2


def test_grouping_rejects_bad_input():
    raises_one_line("cell_m must be a finite number in (0, inf]", CellGrouping, cell_m=0)
    raises_one_line("groups_l", CellGrouping, groups_l=0)
    raises_one_line("positions must be [N, 2]", assign_classes, np.zeros((4, 3)), None, CellGrouping())
    raises_one_line("headings must be [N]", assign_classes, np.zeros((4, 2)), np.zeros(3), CellGrouping())
    raises_one_line("finite", assign_classes, np.full((4, 2), np.nan), None, CellGrouping())


def test_cosface_logits_and_loss_match_a_plain_computation():
    torch.manual_seed(0)
    head = CosFaceHead(8, 5, s=30.0, m=0.4).double()
    features = torch.randn(6, 8, dtype=torch.float64) * 3
    labels = torch.tensor([0, 4, 2, 2, 1, 3])
    w = head.weight.detach()
    cos = torch.zeros(6, 5, dtype=torch.float64)
    for i in range(6):
        for c in range(5):
            cos[i, c] = (features[i] @ w[c]) / (features[i].norm() * w[c].norm())
    want = 30.0 * cos.clone()
    for i in range(6):
        want[i, labels[i]] = 30.0 * (cos[i, labels[i]] - 0.4)
    assert torch.allclose(head(features, labels), want, atol=1e-12)
    assert torch.allclose(head(features), 30.0 * cos, atol=1e-12)  # no labels, no margin
    log_softmax = want - torch.log(torch.exp(want).sum(1, keepdim=True))
    want_loss = -torch.stack([log_softmax[i, labels[i]] for i in range(6)]).mean()
    loss = cosface_loss(head, features, labels)
    assert torch.allclose(loss, want_loss, atol=1e-12)
    plain = nn.functional.cross_entropy(head(features), labels)
    assert loss > plain  # the margin makes the task harder


def test_cosface_rejects_bad_input():
    head = CosFaceHead(8, 5)
    raises_one_line("features must be [B, 8]", head, torch.zeros(2, 7))
    raises_one_line("labels must be in [0, 5)", head, torch.zeros(2, 8), torch.tensor([0, 5]))
    raises_one_line("labels must be an integer tensor of shape [2]", head, torch.zeros(2, 8), torch.tensor([0]))


def test_jist_losses_weighted_sum_and_gradients():
    model, config = tiny_model()
    model.train()
    head = CosFaceHead(config.out_dim, 4)
    q, p = random_images(2, 3, 3, 24, 24, seed=1), random_images(2, 3, 3, 24, 24, seed=2)
    n = random_images(2, 2, 3, 3, 24, 24, seed=3)
    images, labels = random_images(4, 3, 20, 20, seed=4), torch.tensor([0, 1, 3, 1])
    losses = jist_losses(model, head, q, p, n, images, labels, config)
    assert set(losses) == {"sequence", "images", "total"}
    want = config.triplet_weight * losses["sequence"] + config.classification_weight * losses["images"]
    assert torch.allclose(losses["total"], want)
    assert losses["sequence"] > 0 and losses["images"] > 0
    # the sequence term is the mean hinge over the B*K triplets of the model's own descriptors
    with torch.no_grad():
        d = model(torch.cat([q, p, n.flatten(0, 1)]))
        dq, dp, dn = d[:2], d[2:4], d[4:].view(2, 2, -1)
        hinge = torch.relu((dq - dp).norm(dim=-1)[:, None] - (dq[:, None] - dn).norm(dim=-1) + config.margin)
    assert torch.allclose(losses["sequence"], hinge.mean(), atol=1e-6)
    losses["total"].backward()
    assert model.sequence_pool.logits.grad is not None and model.sequence_pool.logits.grad.abs().sum() > 0
    assert head.weight.grad is not None and head.weight.grad.abs().sum() > 0
    assert model.encoder.backbone.conv2.weight.grad is not None
    assert model.encoder.backbone.conv1.weight.grad is None


def test_grouping_defaults_are_the_reference_ones():
    g = CellGrouping()
    assert (g.cell_m, g.heading_deg, g.groups_n, g.groups_l, g.min_images) == (10, 30, 5, 2, 10)
    assert g.n_groups == 50


def test_loss_bad_input_is_one_line():
    model, config = tiny_model()
    head = CosFaceHead(config.out_dim, 4)
    ok = torch.zeros(2, 3, 3, 24, 24)
    images, labels = torch.zeros(4, 3, 20, 20), torch.tensor([0, 1, 3, 1])
    raises_one_line("positive windows", jist_losses, model, head, ok, ok[:1], ok[:, None], images, labels, config)
    raises_one_line("negative windows", jist_losses, model, head, ok, ok, ok[:1, None], images, labels, config)


def test_optimizer_has_a_model_group_and_a_classifier_group():
    config = JistConfig(out_dim=32, seq_length=2)
    model = build_jist(config, MeanPool(2))
    settings = JistTrainSettings()
    optimizer, scheduler = JistLearner(config, settings).build_optimizer(model, JistLoss(config, {0: 7, 3: 2}), settings)
    assert scheduler is None and isinstance(optimizer, torch.optim.Adam)
    assert [g["lr"] for g in optimizer.param_groups] == [1e-5, 1e-2]
    assert len(optimizer.param_groups[0]["params"]) == len(trainable_parameters(model, config))
    assert [p.shape for p in optimizer.param_groups[1]["params"]] == [(7, 32), (2, 32)]
