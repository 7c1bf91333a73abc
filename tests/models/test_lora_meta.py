"""LoRA (peft) trainability and merging; CogVideoX-2B size on the meta device; trajectory → actions."""
import math

import pytest
import torch

from training.models.conditioning import actions_from_trajectory
from training.models.config import config_from_cogvideox, preset
from training.models.dit import NEW_MODULE_PREFIXES, WorldModel
from training.models.lora import LoraSettings, add_lora, lora_state_dict, merge_lora


def _inputs(b=2, t=3):
    g = torch.Generator().manual_seed(0)
    return (torch.randn(b, t, 16, 8, 12, generator=g), torch.randint(0, 1000, (b, t), generator=g),
            torch.randn(b, 16, 64, generator=g), torch.randn(b, 8, 3, generator=g), torch.randn(b, t, 3, generator=g))


def test_lora_trainable_set_and_merge(cogvideox):
    model = add_lora(WorldModel.from_cogvideox(cogvideox, causal=True), LoraSettings(rank=4, alpha=8.0)).eval()
    names = {n for n, p in model.named_parameters() if p.requires_grad}
    assert names and all("lora_" in n or n.startswith(NEW_MODULE_PREFIXES) for n in names)
    lora_names = [n for n in names if "lora_" in n]
    for target in ("to_q", "to_k", "to_v", "to_out.0", "ff.net.0.proj", "ff.net.2"):
        assert any(f".{target}.lora_A" in n for n in lora_names), target
    assert not any(n.startswith("trajectory_encoder") and "lora_" in n for n in lora_names)
    assert any(n.startswith("trajectory_encoder.") for n in names)
    frozen = [n for n, p in model.named_parameters() if not p.requires_grad]
    assert "transformer_blocks.0.attn1.to_q.base_layer.weight" in frozen and "proj_out.weight" in frozen
    assert set(lora_state_dict(model)) == names

    x, t, text, traj, act = _inputs()
    with torch.no_grad():
        plain = model(x, t, text, traj, act)
        for n, p in model.named_parameters():   # LoRA B starts at 0: give the adapters an effect
            if "lora_B" in n or n.startswith(("trajectory_encoder.head", "action_encoder.proj_out")):
                p.normal_(0, 0.05)
        adapted = model(x, t, text, traj, act)
        assert (adapted - plain).abs().max() > 1e-4
        merge_lora(model)
        assert not any("lora_" in n for n, _ in model.named_parameters())
        assert isinstance(model.transformer_blocks[0].attn1.to_q, torch.nn.Linear)
        merged = model(x, t, text, traj, act)
    assert (merged - adapted).abs().max().item() <= 1e-5


def test_lora_gradients_reach_only_trainables(cogvideox):
    model = add_lora(WorldModel.from_cogvideox(cogvideox, causal=True), LoraSettings(rank=2))
    x, t, text, traj, act = _inputs()
    model(x, t, text, traj, act).square().mean().backward()
    assert all(p.grad is None for p in model.parameters() if not p.requires_grad)
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for n, p in model.named_parameters() if "lora_A" in n
               or "trajectory_encoder.head" in n)


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
