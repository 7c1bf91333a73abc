"""LoRA (peft): targets, zero start, gradients, merging; CogVideoX-2B size on the meta device; trajectory → actions."""
import math

import pytest
import torch

from resim.models.world.conditioning import actions_from_trajectory
from resim.models.world.config import config_from_cogvideox, preset
from resim.models.world.dit import NEW_MODULE_PREFIXES, WorldModel
from resim.models.world.lora import add_lora, is_lora_param, merge_lora
from resim.train.tasks.world_model import build_world

from .conftest import randomize_new_modules


def _inputs(b=2, t=3):
    g = torch.Generator().manual_seed(0)
    return (torch.randn(b, t, 16, 8, 12, generator=g), torch.randint(0, 1000, (b, t), generator=g),
            torch.randn(b, 16, 64, generator=g), torch.randn(b, 8, 3, generator=g), torch.randn(b, t, 3, generator=g))


TARGETS = ("to_q", "to_k", "to_v", "to_out.0", "ff.net.0.proj", "ff.net.2")   # diffusers' CogVideoX LoRA targets


def test_lora_targets_start_and_merge(cogvideox):
    model = WorldModel.from_cogvideox(cogvideox, causal=True).eval()
    x, t, text, traj, act = _inputs()
    randomize_new_modules(model)
    with torch.no_grad():
        before = model(x, t, text, traj, act)
    wrapped = add_lora(model, TARGETS, rank=4, alpha=8.0)
    assert len(wrapped) == len(TARGETS) * len(model.transformer_blocks)
    lora_names = [n for n, _ in model.named_parameters() if is_lora_param(n)]
    for target in TARGETS:
        assert any(f".{target}.lora_A.default.weight" in n for n in lora_names), target
    assert all(n.startswith("transformer_blocks.") for n in lora_names)   # not the trajectory encoder's linears
    q = model.transformer_blocks[0].attn1.to_q
    assert q.scaling["default"] == 2.0 and tuple(q.lora_A["default"].weight.shape) == (4, q.in_features)
    assert "transformer_blocks.0.attn1.to_q.base_layer.weight" in model.state_dict()
    with torch.no_grad():
        plain = model(x, t, text, traj, act)
        torch.testing.assert_close(plain, before, rtol=0, atol=0)   # B starts at 0: the output is unchanged
        for n, p in model.named_parameters():   # give the adapters an effect
            if ".lora_B." in n:
                p.normal_(0, 0.05)
        adapted = model(x, t, text, traj, act)
        assert (adapted - plain).abs().max() > 1e-4
        merge_lora(model)
        assert not any(is_lora_param(n) for n, _ in model.named_parameters())
        assert type(model.transformer_blocks[0].attn1.to_q) is torch.nn.Linear
        merged = model(x, t, text, traj, act)
    assert (merged - adapted).abs().max().item() <= 1e-5


def test_lora_matches_no_layer_is_an_error(cogvideox):
    model = WorldModel.from_cogvideox(cogvideox, causal=True)
    with pytest.raises(ValueError, match="to_qq"):
        add_lora(model, ("to_qq",), rank=4, alpha=4.0)
    with pytest.raises(ValueError, match="rank"):
        add_lora(model, ("to_q",), rank=0, alpha=4.0)


def test_lora_gradients_reach_only_trainables():
    torch.manual_seed(0)
    model = build_world({"preset": "tiny", "lora_rank": 2, "trainable": "lora+new"})
    x, t, text, traj, act = _inputs()
    model(x, t, text, traj, act).square().mean().backward()
    assert all(p.grad is None for p in model.parameters() if not p.requires_grad)
    # B = 0 at the start: B gets gradients (A does not yet), as do the new modules
    assert all(p.grad.abs().sum() > 0 for n, p in model.named_parameters() if ".lora_B." in n)
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for n, p in model.named_parameters()
               if n.startswith("trajectory_encoder.head"))


def test_cogvideox_2b_on_meta_device():
    """The real 2B layout, no memory: same parameter names/shapes/count as diffusers' + the new modules."""
    from diffusers import CogVideoXTransformer3DModel
    cfg2b = dict(num_attention_heads=30, attention_head_dim=64, in_channels=16, out_channels=16,
                 time_embed_dim=512, text_embed_dim=4096, num_layers=30, sample_width=90, sample_height=60,
                 sample_frames=49, patch_size=2, max_text_seq_length=226)
    with torch.device("meta"):
        ref = CogVideoXTransformer3DModel(**cfg2b)
        ours = WorldModel(config_from_cogvideox(dict(ref.config)))
        named = WorldModel(preset("cogvideox-2b"))
    ref_shapes = {n: tuple(p.shape) for n, p in ref.named_parameters()}
    dit_shapes = {n: tuple(p.shape) for n, p in ours.named_parameters() if not n.startswith(NEW_MODULE_PREFIXES)}
    assert dit_shapes == ref_shapes
    n_ref = sum(p.numel() for p in ref.parameters())
    n_new = sum(p.numel() for p in ours.new_parameters())
    assert 1.6e9 < n_ref < 1.8e9 and 0 < n_new < 0.02 * n_ref
    assert sum(p.numel() for p in ours.parameters()) == n_ref + n_new
    assert sum(p.numel() for p in named.parameters()) == sum(p.numel() for p in ours.parameters())
    assert all(p.is_meta for p in ours.parameters())


def test_actions_from_straight_and_turning_trajectories():
    # straight at 10 m/s: waypoints every 0.5 s at 5 m spacing → each 0.4 s latent frame moves 4 m forward
    straight = torch.tensor([[[5.0 * (i + 1), 0.0, 0.0] for i in range(8)]])
    acts, valid = actions_from_trajectory(straight, num_frames=13, first_future_frame=3)
    assert valid[0, :3].sum() == 0 and valid[0, 3:].all()            # 10 future frames = 4.0 s horizon
    assert torch.allclose(acts[0, 3:], torch.tensor([4.0, 0.0, 0.0]).expand(10, 3), atol=1e-5)
    assert acts[0, :3].abs().sum() == 0
    # constant-curvature left turn: yaw rate w, speed v → in each frame's own start frame the motion is identical
    v, w = 8.0, 0.2
    tt = torch.arange(1, 9) * 0.5
    arc = torch.stack([v / w * torch.sin(w * tt), v / w * (1 - torch.cos(w * tt)), w * tt], dim=-1)[None]
    acts, valid = actions_from_trajectory(arc, num_frames=6, first_future_frame=1)
    assert valid[0, 1:].all()
    # chords of the interpolated polyline: yaw change exactly w * 0.4 where spans align with waypoints
    assert torch.allclose(acts[0, 1:, 2], torch.full((5,), w * 0.4), atol=1e-5)
    assert (acts[0, 1:, 1] > 0).all() and (acts[0, 1:, 0] > 3.0).all()  # moving forward and drifting left


def test_actions_beyond_horizon_are_invalid():
    traj = torch.zeros(2, 8, 3)
    _, valid = actions_from_trajectory(traj, num_frames=20, first_future_frame=2)
    assert valid[:, 2:12].all() and not valid[:, 12:].any() and not valid[:, :2].any()
    with pytest.raises(ValueError, match="trajectory"):
        actions_from_trajectory(torch.zeros(2, 8), 4, 1)


def test_presets_validate():
    from resim.config import ConfigError
    for name in ("tiny", "small", "cogvideox-2b"):
        assert preset(name).hidden_dim % 16 == 0
    with pytest.raises(ConfigError, match="text_timestep"):
        preset("tiny", text_timestep="max", causal=True)
    with pytest.raises(ConfigError, match="unknown"):
        preset("huge")
    assert math.isclose(preset("tiny", norm_eps=1e-6).norm_eps, 1e-6)
