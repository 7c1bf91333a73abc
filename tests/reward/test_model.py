import dataclasses

import pytest
import torch

from resim.models.reward.backbone import BackboneError, load_backbone, num_tokens
from resim.models.reward.model import FeatureMismatchError, Video2Reward


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
    """resim.train.data.Batch style: whole-clip uint8 frames + meta dicts; the model takes the last window."""
    m = Video2Reward(tiny_cfg)
    frames = torch.randint(0, 256, (2, 9, 3, 24, 24), dtype=torch.uint8)
    meta = [{"infraction_score": 0.3, "dino_id": None}, {"infraction_score": 1.0, "dino_id": None}]
    loss, logs = m.loss({"frames": frames, "meta": meta, "keys": ["a", "b"]})
    with torch.no_grad():
        pred = m(video=frames[:, [2, 4, 6, 8]].float() / 255)
    assert float(loss.detach()) == pytest.approx(float(((pred - torch.tensor([0.3, 1.0])) ** 2).mean()), rel=1e-5)
    with pytest.raises(ValueError, match="sample b has no infraction_score"):
        m.loss({"frames": frames, "meta": [meta[0], {"infraction_score": None}], "keys": ["a", "b"]})


def test_output_is_bounded_by_sigmoid_unless_configured_raw(tiny_cfg):
    """The infraction score lives in [0, 1]: the default head ends in a sigmoid; "none" keeps the raw output."""
    from resim.config import ConfigError

    m = Video2Reward(tiny_cfg)
    raw = Video2Reward(dataclasses.replace(tiny_cfg, output_activation="none"))
    raw.head.load_state_dict(m.head.state_dict())
    with torch.no_grad():
        for mod in (m, raw):  # make the logit large: a last-layer bias far outside [0, 1]
            mod.head.mlp[-1].bias.fill_(5.0)
        f = torch.randn(3, *m.feature_shape) * 10
        p, r = m(features=f), raw(features=f)
    assert ((p > 0) & (p < 1)).all()
    assert torch.allclose(p, torch.sigmoid(r), atol=1e-6)
    assert (r > 1).any()  # the raw head is not bounded
    with pytest.raises(ConfigError, match="output_activation"):
        dataclasses.replace(tiny_cfg, output_activation="tanh")


def test_temporal_diff_feeds_the_head_frame_changes(tiny_cfg):
    """With temporal_diff the projection takes [features, change since the previous frame]. Keeping only
    the change half: two different static clips score alike (no change), a moving clip differently."""
    m = Video2Reward(dataclasses.replace(tiny_cfg, temporal_diff=True)).eval()
    t, n, d = m.feature_shape
    assert m.head.proj.in_features == 2 * d
    with torch.no_grad():
        m.head.proj.weight[:, :d] = 0  # see only the frame-to-frame change
        g = torch.Generator().manual_seed(0)
        a = torch.randn(1, 1, n, d, generator=g).expand(1, t, n, d)
        b = torch.randn(1, 1, n, d, generator=g).expand(1, t, n, d)
        moving = torch.randn(1, t, n, d, generator=g)
        pa, pb, pm = m(features=a), m(features=b), m(features=moving)
    assert torch.allclose(pa, pb, atol=1e-6)
    assert not torch.allclose(pa, pm, atol=1e-4)


def test_old_checkpoint_without_output_activation_loads_raw(tiny_train_cfg, tmp_path):
    """A checkpoint saved before the sigmoid existed (no output_activation in config.yaml) keeps its raw head.
    Such runs are of the layout before final/: RUN/config.yaml (a RewardTrainConfig) + RUN/reward.safetensors
    (the head's tensors as head.*, what final/model.safetensors holds for a frozen backbone)."""
    import shutil

    import yaml

    from resim.models.reward.checkpoint import load_checkpoint, save_checkpoint

    m = Video2Reward(dataclasses.replace(tiny_train_cfg.model, output_activation="none"))
    save_checkpoint(m, tmp_path, dataclasses.replace(tiny_train_cfg, model=m.cfg))
    (tmp_path / "final" / "model.safetensors").rename(tmp_path / "reward.safetensors")
    shutil.rmtree(tmp_path / "final")
    cfg = yaml.safe_load((tmp_path / "config.yaml").read_text())
    assert cfg["model"]["output_activation"] == "none"
    del cfg["model"]["output_activation"]
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(cfg))
    assert load_checkpoint(tmp_path).cfg.output_activation == "none"
    new = Video2Reward(tiny_train_cfg.model)
    save_checkpoint(new, tmp_path / "new", tiny_train_cfg)
    assert load_checkpoint(tmp_path / "new").cfg.output_activation == "sigmoid"
