"""Rollout: cached == uncached, frame counts, per-round conditions, actions from a policy, guidance batching."""
import pytest
import torch

from resim.config import ConfigError
from resim.diffusion.guidance import guidance_preset
from resim.sample.rollout import Condition, RolloutConfig, rollout, rollout_num_future_frames

B, C, H, W, L, D = 2, 4, 2, 3, 5, 8


def _cond(seed=0, traj=True, label="Moving forward"):
    g = torch.Generator().manual_seed(seed)
    return Condition(text=torch.randn(B, L, D, generator=g), null_text=torch.randn(B, L, D, generator=g),
                     trajectory=torch.randn(B, 8, 3, generator=g) if traj else None, label=label)


def _history(n=3):
    return torch.randn(B, n, C, H, W, generator=torch.Generator().manual_seed(7))


class Counting(torch.nn.Module):
    """Wraps a model and records the batch size and frame count of every call."""

    def __init__(self, m):
        super().__init__()
        self.m, self.calls = m, []
        self.causal = m.causal

    def forward(self, x, *a, **kw):
        self.calls.append((x.shape[0], x.shape[1], kw.get("kv_cache") is not None))
        return self.m(x, *a, **kw)


@pytest.mark.parametrize("preset,chunk,noise", [("resim", 10, 0), ("resim", 4, 0), ("vid2world", 1, 20)])
def test_cached_equals_uncached(tiny_model, preset, chunk, noise):
    model = tiny_model()
    gcfg = guidance_preset(preset)
    acts = torch.randn(B, 12, 3, generator=torch.Generator().manual_seed(3)) if preset == "vid2world" else None
    outs = {}
    for kv in ("on", "off"):
        cfg = RolloutConfig(num_steps=6, history_frames=3, frames_per_round=10, chunk_frames=chunk,
                            history_noise_level=noise, kv_cache=kv, guidance=gcfg)
        outs[kv] = rollout(model, _history(), [_cond(0), _cond(1, label="Turning left")], 12, cfg, seed=5,
                           actions=acts)
    assert outs["on"].kv_cache_used and not outs["off"].kv_cache_used
    torch.testing.assert_close(outs["on"].latents, outs["off"].latents, rtol=1e-4, atol=1e-5)
    assert outs["on"].latents.shape == (B, 3 + 12, C, H, W)
    torch.testing.assert_close(outs["on"].latents[:, :3], _history())  # history passed through untouched
    # a different seed gives different frames (the comparison above is not vacuous)
    other = rollout(model, _history(), _cond(0), 12, cfg, seed=6, actions=acts)
    assert (other.future - outs["off"].future).abs().max() > 1e-3


def test_one_batched_forward_per_step_and_cache_reuse(tiny_model):
    m = Counting(tiny_model())
    cfg = RolloutConfig(num_steps=5, history_frames=3, frames_per_round=10, chunk_frames=10, kv_cache="on",
                        guidance=guidance_preset("resim"))
    rollout(m, _history(), _cond(), 10, cfg)
    # 1 history prefill + 5 steps, every call carries both CFG branches (2B), steps see only the chunk
    assert m.calls[0] == (2 * B, 3, False)
    assert m.calls[1:] == [(2 * B, 10, True)] * 5
    m.calls.clear()
    rollout(m, _history(), _cond(), 10, RolloutConfig(num_steps=5, kv_cache="off", guidance=guidance_preset("resim")))
    assert m.calls == [(2 * B, 13, False)] * 5
    m.calls.clear()
    rollout(m, _history(), _cond(), 10, RolloutConfig(num_steps=5, kv_cache="off", guidance=guidance_preset("none")))
    assert m.calls == [(B, 13, False)] * 5


def test_frame_by_frame_cache_appends(tiny_model):
    m = Counting(tiny_model())
    cfg = RolloutConfig(num_steps=2, history_frames=3, frames_per_round=4, chunk_frames=1, kv_cache="on",
                        guidance=guidance_preset("none"))
    res = rollout(m, _history(), _cond(traj=False), 6, cfg)
    # round 1: prefill(3), 2 steps, append(1) x3 between chunks; round 2 (window slides): prefill(3), ...
    frames = [(n, cached) for _, n, cached in m.calls]
    assert frames[:3] == [(3, False), (1, True), (1, True)]
    assert frames.count((3, False)) == 2
    assert res.future.shape[1] == 6 and res.model_forwards == len(m.calls)


@pytest.mark.parametrize("seconds,expected", [(4, 10), (10, 25), (0.4, 1), (1.0, 3)])
def test_seconds_to_frames(seconds, expected):
    assert rollout_num_future_frames(seconds, fps_hz=10) == expected


def test_n_second_rollout_frame_count(tiny_model):
    n = rollout_num_future_frames(10)  # 10 s at 10 Hz = 100 px frames = 25 latent frames, 3 rounds
    res = rollout(tiny_model(), _history(), lambda i: _cond(i, label=f"r{i}"), n,
                  RolloutConfig(num_steps=2, guidance=guidance_preset("none")))
    assert res.future.shape[1] == 25 and res.round_labels == ["r0", "r1", "r2"]
    # CogVideoX's causal VAE decodes T latent frames to 1 + 4 (T - 1) pixel frames: 9 history + 100 future
    assert 1 + 4 * (res.latents.shape[1] - 1) == 9 + 100


def test_policy_closed_loop(tiny_model):
    seen = []

    def policy(inp):
        seen.append((inp.frame_index, inp.num_frames, inp.latents.shape[1]))
        # steer by the mean of the last frame: a closed loop that reads the imagined frames
        return inp.latents[:, -1].mean(dim=(1, 2, 3))[:, None, None].expand(B, inp.num_frames, 3).clone()

    cfg = RolloutConfig(num_steps=2, frames_per_round=3, chunk_frames=1, guidance=guidance_preset("vid2world"))
    res = rollout(tiny_model(), _history(), _cond(traj=False), 5, cfg, policy=policy)
    assert [s[0] for s in seen] == [3, 4, 5, 6, 7] and all(s[1] == 1 for s in seen)
    assert res.actions.shape == (B, 8, 3)
    torch.testing.assert_close(res.actions[:, 3], res.latents[:, 2].mean(dim=(1, 2, 3))[:, None].expand(B, 3))


def test_actions_change_the_future(tiny_model):
    cfg = RolloutConfig(num_steps=3, chunk_frames=1, frames_per_round=4, guidance=guidance_preset("vid2world"))
    a = torch.zeros(B, 4, 3)
    r0 = rollout(tiny_model(), _history(), _cond(traj=False), 4, cfg, actions=a)
    r1 = rollout(tiny_model(), _history(), _cond(traj=False), 4, cfg, actions=a + 1.0)
    assert (r0.future - r1.future).abs().max() > 1e-3


def test_errors(tiny_model):
    with pytest.raises(ConfigError, match="causal"):
        rollout(tiny_model(causal=False), _history(), _cond(), 2, RolloutConfig(kv_cache="on"))
    # auto on a bidirectional model: no cache, still works
    r = rollout(tiny_model(causal=False), _history(), _cond(), 2,
                RolloutConfig(num_steps=2, guidance=guidance_preset("resim")))
    assert not r.kv_cache_used
    with pytest.raises(ConfigError, match="chunk_frames"):
        RolloutConfig(chunk_frames=11, frames_per_round=10)
    with pytest.raises(ValueError, match="null_text"):
        rollout(tiny_model(), _history(), Condition(text=torch.zeros(B, L, D)), 2,
                RolloutConfig(num_steps=1, guidance=guidance_preset("resim")))
    with pytest.raises(ValueError, match="policy returned"):
        rollout(tiny_model(), _history(), _cond(), 2, RolloutConfig(num_steps=1, chunk_frames=1),
                policy=lambda inp: torch.zeros(B, 5, 3))


def _real_tiny_world_model(seed=0):
    from resim.models.world.config import preset
    from resim.models.world.dit import WorldModel
    torch.manual_seed(seed)
    m = WorldModel(preset("tiny")).eval()
    with torch.no_grad():  # the new encoders start at zero output; make them matter for this test
        for name, p in m.named_parameters():
            if name.startswith(("trajectory_encoder.", "action_encoder.")):
                p.normal_(0, 0.2)
    return m


@pytest.mark.parametrize("chunk,preset_name", [(10, "resim"), (1, "vid2world")])
def test_real_world_model_cached_equals_uncached(chunk, preset_name):
    """The same check on the real WorldModel (tiny preset, block-causal, its own KV-cache hook)."""
    torch.set_num_threads(1)
    m = _real_tiny_world_model()
    g = torch.Generator().manual_seed(0)
    hist = torch.randn(1, 3, 16, 8, 12, generator=g)
    cond = Condition(text=torch.randn(1, 6, 64, generator=g), null_text=torch.randn(1, 6, 64, generator=g),
                     trajectory=torch.randn(1, 8, 3, generator=g))
    acts = torch.randn(1, 4, 3, generator=g) if preset_name == "vid2world" else None
    outs = [rollout(m, hist, cond, 4, RolloutConfig(num_steps=3, frames_per_round=4, chunk_frames=min(chunk, 4),
                                                       kv_cache=kv, guidance=guidance_preset(preset_name)),
                    actions=acts).latents for kv in ("on", "off")]
    torch.testing.assert_close(outs[0], outs[1], rtol=1e-4, atol=1e-4)
    assert torch.isfinite(outs[0]).all()


class KeepSpy(torch.nn.Module):
    """Records (trajectory_keep, action_keep) of every call."""

    def __init__(self, m):
        super().__init__()
        self.m, self.calls = m, []
        self.causal = m.causal

    def forward(self, x, *a, **kw):
        self.calls.append((kw.get("trajectory_keep"), kw.get("action_keep")))
        return self.m(x, *a, **kw)


@pytest.mark.parametrize("chunk", [10, 4])
def test_resim_guidance_drops_trajectory_derived_actions_with_the_trajectory(tiny_model, chunk):
    """Training drops actions derived from a trajectory whenever it drops the trajectory, so the unconditional
    branch (trajectory dropped) must not see them; given (not derived) actions stay in both branches."""
    acts = torch.randn(B, 12, 3, generator=torch.Generator().manual_seed(3))
    for derived in (True, False):
        m = KeepSpy(tiny_model())
        cfg = RolloutConfig(num_steps=2, history_frames=3, frames_per_round=10, chunk_frames=chunk,
                            guidance=guidance_preset("resim"))
        res = rollout(m, _history(), [_cond(0), _cond(1)], 12, cfg, actions=acts, actions_from_trajectory=derived)
        assert res.action_valid[:, 3:].all() and not res.action_valid[:, :3].any()
        for traj_keep, act_keep in m.calls:
            assert traj_keep[:B].all() and not traj_keep[B:].any()
            cond_keep, uncond_keep = act_keep[:B], act_keep[B:]
            if derived:
                assert not uncond_keep.any()
            else:
                assert torch.equal(uncond_keep, cond_keep)
        assert any(k[:B].any() for _, k in m.calls)      # the conditional branch does get the actions


@pytest.mark.parametrize("chunk", [10, 4, 1])
def test_cached_equals_uncached_with_derived_actions(tiny_model, chunk):
    acts = torch.randn(B, 12, 3, generator=torch.Generator().manual_seed(3))
    outs = [rollout(tiny_model(), _history(), [_cond(0), _cond(1)], 12,
                    RolloutConfig(num_steps=3, frames_per_round=10, chunk_frames=chunk, kv_cache=kv,
                                  guidance=guidance_preset("resim")), seed=2, actions=acts,
                    actions_from_trajectory=True).latents for kv in ("on", "off")]
    torch.testing.assert_close(outs[0], outs[1], rtol=1e-4, atol=1e-5)


def test_policy_valid_mask_gives_the_null_action(tiny_model):
    """A policy may return (actions, valid): invalid frames (e.g. past the trajectory's horizon) get the null
    action, exactly as if the policy had returned no actions there."""
    cfg = RolloutConfig(num_steps=2, frames_per_round=4, chunk_frames=2, guidance=guidance_preset("none"))
    a = torch.randn(B, 4, 3, generator=torch.Generator().manual_seed(1))
    valid = torch.tensor([[True, True, False, False]] * B)

    def policy(inp):
        k = inp.frame_index - 3
        return a[:, k:k + inp.num_frames], valid[:, k:k + inp.num_frames]

    res = rollout(tiny_model(), _history(), _cond(traj=False), 4, cfg, policy=policy)
    assert torch.equal(res.action_valid[:, 3:], valid) and not res.actions[:, 5:].any()
    garbage = a.clone()
    garbage[:, 2:] = 1e3          # what the policy puts under an invalid mask must not matter
    res2 = rollout(tiny_model(), _history(), _cond(traj=False), 4, cfg,
                   policy=lambda inp: (garbage[:, inp.frame_index - 3:inp.frame_index - 3 + inp.num_frames],
                                       valid[:, :inp.num_frames] if inp.frame_index == 3 else valid[:, 2:]))
    torch.testing.assert_close(res.latents, res2.latents, rtol=0, atol=0)
