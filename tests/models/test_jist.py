"""JIST's model: the per-backbone trainable stages, frozen stages and BatchNorm, the forward pass, CosPlace heads."""

import torch
from torch import nn

from seqvpr.features.backbones import ResNet
from seqvpr.models.jist import DEFAULT_STAGES, JistConfig, build_jist, trainable_parameters
from tests.helpers import raises_one_line
from tests.jist_fixtures import MeanPool, TinyBackbone, random_images, tiny_model


def test_config_defaults_are_the_reference_ones():
    c = JistConfig()
    assert (c.backbone, c.out_dim, c.trainable_stages, c.seq_length) == ("resnet18", 512, ("layer4",), 5)
    assert (c.triplet_weight, c.classification_weight, c.margin) == (1e4, 1e2, 0.1)
    assert (c.lr, c.classifier_lr, c.cosface_s, c.cosface_m) == (1e-5, 1e-2, 30.0, 0.4)
    assert JistConfig(backbone="efficientnet-lite0").trainable_stages == DEFAULT_STAGES["efficientnet-lite0"]


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


def test_model_bad_input_is_one_line():
    model, config = tiny_model()
    raises_one_line("windows must be [B, L, 3, H, W]", model, torch.zeros(2, 3, 24, 24))
    raises_one_line("windows must be [B, L, 3, H, W]", model, torch.zeros(2, 3, 1, 24, 24))
    raises_one_line("images must be [B, 3, H, W]", model.frames, torch.zeros(3, 24, 24))
    raises_one_line("backbone 'vgg16' is not known", JistConfig, backbone="vgg16")
    raises_one_line("unknown backbone stage 'layer5'", build_jist, JistConfig(trainable_stages=("layer5",)), MeanPool())
    raises_one_line("unknown backbone stage 'layer4'", build_jist, JistConfig(), MeanPool(), backbone=TinyBackbone())
    raises_one_line("trainable_stages", JistConfig, trainable_stages="layer4")
    raises_one_line("positive integer", JistConfig, seq_length=0)


def test_seqgem_normalization_switch_is_built_saved_and_loaded(tmp_path):
    """``seqgem_normalize=False`` gives upstream's unnormalised SeqGeM, and the folder keeps it."""
    from seqvpr.models.jist import JistConfig, build_jist, load_jist, save_jist

    config = JistConfig(backbone="resnet18", out_dim=16, seq_length=3, seqgem_normalize=False)
    torch.manual_seed(0)
    model = build_jist(config)
    assert model.sequence_pool.normalize is False
    frames = torch.rand(2, 3, 16)
    pooled = model.pool(torch.nn.functional.normalize(frames, dim=-1))
    assert not torch.allclose(pooled.norm(dim=-1), torch.ones(2))
    save_jist(tmp_path / "m", model, config, {"image_size": [64, 48]})
    assert load_jist(tmp_path / "m").sequence_pool.normalize is False
    assert build_jist(JistConfig(backbone="resnet18", out_dim=16)).sequence_pool.normalize is True
