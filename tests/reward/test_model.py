import dataclasses

import pytest
import torch

from training.reward.backbone import BackboneError, load_backbone, num_tokens
from training.reward.model import FeatureMismatchError, Video2Reward


def test_shapes_and_placeholder_metadata(tiny_cfg):
    m = Video2Reward(tiny_cfg)
    assert m.backbone_info["placeholder"] is True
    assert "placeholder" in m.feature_id and m.metadata()["backbone_placeholder"] is True
    assert m.feature_shape == (4, num_tokens(56, 8), 32) == (4, 50, 32)
    v = torch.rand(2, 4, 3, 30, 40)
    feats = m.encode(v)
    assert feats.shape == (2, 4, 50, 32)
    assert torch.equal(feats, feats.half().float())  # rounded like dino.npy
    out = m(video=v)
    assert out.shape == (2,) and out.dtype == torch.float32
    assert torch.allclose(out, m(features=feats), atol=1e-6)
    with pytest.raises(ValueError, match="windows of 4 frames"):
        m(video=torch.rand(1, 5, 3, 30, 40))
    with pytest.raises(FeatureMismatchError):
        m(features=torch.rand(1, 4, 17, 32))


def test_placeholder_weights_deterministic_from_seed(tiny_cfg):
    a, _ = load_backbone(tiny_cfg.backbone_dir, 0)
    b, _ = load_backbone(tiny_cfg.backbone_dir, 0)
    c, info = load_backbone(tiny_cfg.backbone_dir, 1)
    sa, sb, sc = a.state_dict(), b.state_dict(), c.state_dict()
    assert all(torch.equal(sa[k], sb[k]) for k in sa)
    assert not all(torch.equal(sa[k], sc[k]) for k in sa)
    assert info["id"].endswith("seed1")
    with pytest.raises(BackboneError, match="no config.json"):
        load_backbone("/nonexistent/dinov2", 0)


def test_frozen_by_default_and_fine_tunable(tiny_cfg):
    batch = {"video": torch.rand(2, 4, 3, 24, 24), "infraction_score": torch.tensor([0.2, 1.0])}
    m = Video2Reward(tiny_cfg)
    m.train()
    assert not m.backbone.training
    loss, logs = m.loss(batch)
    loss.backward()
    assert all(p.grad is None for p in m.backbone.parameters())
    assert all(p.grad is not None for p in m.head.parameters())
    assert logs["used_features"] == 0.0 and logs["loss"] > 0
    ft = Video2Reward(dataclasses.replace(tiny_cfg, freeze_backbone=False))
    loss, _ = ft.loss(batch)
    loss.backward()
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in ft.backbone.parameters())


def test_loss_accepts_attribute_batches_and_checks_feature_id(tiny_cfg):
    m = Video2Reward(tiny_cfg)

    @dataclasses.dataclass
    class B:
        dino: torch.Tensor
        dino_id: list
        infraction_score: torch.Tensor

    f = torch.rand(2, *m.feature_shape)
    loss, logs = m.loss(B(f, [m.feature_id] * 2, torch.tensor([0.0, 1.0])))
    assert logs["used_features"] == 1.0 and torch.isfinite(loss)
    with pytest.raises(FeatureMismatchError, match="recompute"):
        m.loss(B(f, ["other-backbone|224px|T8s5"] * 2, torch.tensor([0.0, 1.0])))
    with pytest.raises(ValueError, match="no infraction_score"):
        m.loss({"video": torch.rand(1, 4, 3, 8, 8)})


def test_loss_reads_the_common_stream_batch(tiny_cfg):
    """training.data.Batch style: whole-clip uint8 frames + meta dicts; the model takes the last window."""
    m = Video2Reward(tiny_cfg)
    frames = torch.randint(0, 256, (2, 9, 3, 24, 24), dtype=torch.uint8)
    meta = [{"infraction_score": 0.3, "dino_id": None}, {"infraction_score": 1.0, "dino_id": None}]
    loss, logs = m.loss({"frames": frames, "meta": meta, "keys": ["a", "b"]})
    with torch.no_grad():
        pred = m(video=frames[:, [2, 4, 6, 8]].float() / 255)
    assert float(loss) == pytest.approx(float(((pred - torch.tensor([0.3, 1.0])) ** 2).mean()), rel=1e-5)
    with pytest.raises(ValueError, match="sample b has no infraction_score"):
        m.loss({"frames": frames, "meta": [meta[0], {"infraction_score": None}], "keys": ["a", "b"]})
