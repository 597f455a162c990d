"""JIST components: CosPlace classes and groups, CosFace, the frame encoder's frozen stages, the JIST model and
its joint loss (the training loop is tested elsewhere)."""

import itertools

import numpy as np
import pytest
import torch
from torch import nn

from seqvpr.features.backbones import ResNet
from seqvpr.models.jist import JistConfig, JistModel, build_jist, jist_losses, optimizer_groups
from seqvpr.models.jist import make_classifier, trainable_parameters
from seqvpr.training.cosplace import CellGrouping, CosFaceHead, assign_classes, cosface_loss, group_members
from tests.helpers import raises_one_line


class TinyBackbone(nn.Module):
    """A small two-stage convolution net with BatchNorm standing in for a real backbone."""

    def __init__(self) -> None:
        super().__init__()
        torch.manual_seed(0)
        self.conv1 = nn.Conv2d(3, 6, 3, stride=2)
        self.bn1 = nn.BatchNorm2d(6)
        self.conv2 = nn.Conv2d(6, 8, 3, stride=2)
        self.bn2 = nn.BatchNorm2d(8)
        self.out_channels = 8

    def features(self, x):
        return torch.relu(self.bn2(self.conv2(torch.relu(self.bn1(self.conv1(x))))))


class MeanPool(nn.Module):
    """Stand-in sequence pool: a learnable softmax-weighted mean over L (uniform at init), then L2."""

    def __init__(self, length: int = 3) -> None:
        super().__init__()
        self.logits = nn.Parameter(torch.zeros(length))

    def forward(self, x):
        weights = self.logits[: x.shape[1]].softmax(0)
        return nn.functional.normalize((x * weights[None, :, None]).sum(1), dim=-1)


def tiny_model(stages=("conv2", "bn2"), out_dim=16, length=3) -> tuple[JistModel, JistConfig]:
    config = JistConfig(out_dim=out_dim, trainable_stages=stages, seq_length=length)
    return build_jist(config, MeanPool(length), backbone=TinyBackbone()), config


def random_images(*shape, seed=0):
    return torch.rand(*shape, generator=torch.Generator().manual_seed(seed))


# --- CosPlace classes and groups -----------------------------------------------------------------------------


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


def test_defaults_are_the_reference_ones():
    g = CellGrouping()
    assert (g.cell_m, g.heading_deg, g.groups_n, g.groups_l, g.min_images) == (10, 30, 5, 2, 10)
    assert g.n_groups == 50
    c = JistConfig()
    assert (c.backbone, c.out_dim, c.trainable_stages, c.seq_length) == ("resnet18", 512, ("layer4",), 5)
    assert (c.triplet_weight, c.classification_weight, c.margin) == (1e4, 1e2, 0.1)
    assert (c.lr, c.classifier_lr, c.cosface_s, c.cosface_m) == (1e-5, 1e-2, 30.0, 0.4)


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
    raises_one_line("cell size", CellGrouping, cell_m=0)
    raises_one_line("groups_l", CellGrouping, groups_l=0)
    raises_one_line("positions must be [N, 2]", assign_classes, np.zeros((4, 3)), None, CellGrouping())
    raises_one_line("headings must be [N]", assign_classes, np.zeros((4, 2)), np.zeros(3), CellGrouping())
    raises_one_line("finite", assign_classes, np.full((4, 2), np.nan), None, CellGrouping())


# --- CosFace ----------------------------------------------------------------------------------------------------


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


# --- frozen stages ----------------------------------------------------------------------------------------------


def test_only_chosen_stages_train_and_frozen_batchnorm_stays_in_eval():
    model, config = tiny_model(stages=("conv2", "bn2"))
    encoder = model.encoder
    trainable = {name for name, p in model.named_parameters() if p.requires_grad}
    assert trainable == {
        "encoder.backbone.conv2.weight", "encoder.backbone.conv2.bias",
        "encoder.backbone.bn2.weight", "encoder.backbone.bn2.bias",
        "encoder.gem.p", "encoder.fc.weight", "encoder.fc.bias", "sequence_pool.logits",
    }
    assert {id(p) for p in trainable_parameters(model, config)} == {
        id(p) for p in model.parameters() if p.requires_grad
    }
    model.train()
    assert not encoder.backbone.bn1.training and encoder.backbone.bn2.training and model.training
    before = encoder.backbone.bn1.running_mean.clone()
    model(random_images(2, 3, 3, 24, 24)).sum().backward()
    assert torch.equal(encoder.backbone.bn1.running_mean, before)  # frozen statistics do not drift
    assert encoder.backbone.conv1.weight.grad is None and encoder.backbone.bn1.weight.grad is None
    assert encoder.backbone.conv2.weight.grad is not None and encoder.fc.weight.grad is not None
    model.eval()
    assert not encoder.backbone.bn2.training


def test_resnet_layer4_only():
    config = JistConfig(out_dim=32, seq_length=2)
    model = build_jist(config, MeanPool(2))
    backbone = model.encoder.backbone
    assert isinstance(backbone, ResNet)
    for name, p in backbone.named_parameters():
        assert p.requires_grad == name.startswith("layer4."), name
    model.train()
    frozen_bn = [m for n, m in backbone.named_modules() if isinstance(m, nn.BatchNorm2d) and not n.startswith("layer4")]
    live_bn = [m for n, m in backbone.named_modules() if isinstance(m, nn.BatchNorm2d) and n.startswith("layer4")]
    assert frozen_bn and live_bn and not any(m.training for m in frozen_bn) and all(m.training for m in live_bn)
    out = model(random_images(2, 2, 3, 32, 32))
    assert out.shape == (2, 32)
    out.sum().backward()
    assert all(p.grad is None for n, p in backbone.named_parameters() if not n.startswith("layer4."))
    assert backbone.layer4[0].conv1.weight.grad is not None
    groups = optimizer_groups(model, make_classifier(config, 7), config)
    assert [g["lr"] for g in groups] == [1e-5, 1e-2]
    assert len(groups[0]["params"]) == len(trainable_parameters(model, config))
    torch.optim.Adam(groups)  # a valid Adam configuration


# --- model ------------------------------------------------------------------------------------------------------


def test_forward_equals_pooling_frames_encoded_one_at_a_time():
    model, _ = tiny_model()
    model.eval()
    windows = random_images(2, 3, 3, 24, 24, seed=3)
    with torch.no_grad():
        batched = model(windows)
        frames = torch.stack([torch.stack([model.frames(windows[b, t : t + 1])[0] for t in range(3)]) for b in range(2)])
        one_by_one = model.sequence_pool(frames)
    assert batched.shape == (2, 16)
    assert torch.allclose(batched, one_by_one, atol=1e-6)
    assert torch.allclose(frames.norm(dim=-1), torch.ones(2, 3), atol=1e-6)  # unit-norm frame descriptors


# --- joint loss -------------------------------------------------------------------------------------------------


def test_jist_losses_weighted_sum_and_gradients():
    model, config = tiny_model()
    model.train()
    head = make_classifier(config, 4)
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


def test_bad_input_is_one_line():
    model, config = tiny_model()
    head = make_classifier(config, 4)
    raises_one_line("windows must be [B, L, 3, H, W]", model, torch.zeros(2, 3, 24, 24))
    raises_one_line("windows must be [B, L, 3, H, W]", model, torch.zeros(2, 3, 1, 24, 24))
    raises_one_line("images must be [B, 3, H, W]", model.frames, torch.zeros(3, 24, 24))
    ok = torch.zeros(2, 3, 3, 24, 24)
    images, labels = torch.zeros(4, 3, 20, 20), torch.tensor([0, 1, 3, 1])
    raises_one_line("positive windows", jist_losses, model, head, ok, ok[:1], ok[:, None], images, labels, config)
    raises_one_line("negative windows", jist_losses, model, head, ok, ok, ok[:1, None], images, labels, config)
    raises_one_line("backbone 'vgg16' is not known", JistConfig, backbone="vgg16")
    raises_one_line("unknown backbone stage 'layer5'", build_jist, JistConfig(trainable_stages=("layer5",)), MeanPool())
    raises_one_line("unknown backbone stage 'layer4'", build_jist, JistConfig(), MeanPool(), backbone=TinyBackbone())
    raises_one_line("trainable_stages", JistConfig, trainable_stages="layer4")
    raises_one_line("positive integer", JistConfig, seq_length=0)


def test_efficientnet_stages_cover_the_feature_path():
    from seqvpr.features.backbones import efficientnet_lite0
    from seqvpr.models.jist import backbone_stages

    lite = efficientnet_lite0(None)
    stages = backbone_stages(lite)
    assert list(stages) == ["stem", *(f"stage{i}" for i in range(1, 8)), "head"]
    covered = {id(p) for modules in stages.values() for m in modules for p in m.parameters()}
    expected = {id(p) for n, p in lite.named_parameters() if not n.startswith("_fc.")}
    assert covered == expected


def test_cosplace_checkpoint_fills_backbone_and_head(tmp_path):
    torch.manual_seed(5)
    source = ResNet(18)
    names = {"conv1": "0", "bn1": "1", "layer1": "4", "layer2": "5", "layer3": "6", "layer4": "7"}
    state = {}
    for key, value in source.state_dict().items():
        child, _, rest = key.partition(".")
        state[f"backbone.{names[child]}.{rest}"] = value
    state["aggregation.1.p"] = torch.tensor([2.5])
    state["aggregation.3.weight"] = torch.randn(32, 512)
    state["aggregation.3.bias"] = torch.randn(32)
    path = tmp_path / "cosplace.pth"
    torch.save(state, path)
    model = build_jist(JistConfig(weights=str(path), out_dim=32), MeanPool(2))
    assert torch.equal(model.encoder.backbone.layer4[1].conv2.weight, source.layer4[1].conv2.weight)
    assert torch.equal(model.encoder.fc.weight, state["aggregation.3.weight"])
    assert model.encoder.gem.p.item() == 2.5 and model.encoder.gem.p.requires_grad
    raises_one_line("set out_dim to match", build_jist, JistConfig(weights=str(path), out_dim=16), MeanPool(2))
