"""attention_backend="flex": same outputs as "sdpa" (fp32, tiny preset), KV cache, gradients, config checks.

On CPU flex_attention runs eagerly (unfused reference implementation), so these compare the *pattern* and
the plumbing exactly; the compiled CUDA kernel is checked by the ``gpu`` test at the end (skipped without CUDA).
"""
import pytest
import torch

from resim.config import ConfigError, from_dict
from resim.models.world.config import WorldModelConfig, preset
from resim.models.world.dit import WorldModel

from .conftest import randomize_new_modules

TOL = 1e-5   # fp32: both backends sum the same products in a different order


def _inputs(b=2, t=4, h=8, w=12, seed=0):
    g = torch.Generator().manual_seed(seed)
    return (torch.randn(b, t, 16, h, w, generator=g), torch.randint(0, 1000, (b, t), generator=g),
            torch.randn(b, 16, 64, generator=g), torch.randn(b, t, 3, generator=g), torch.randn(b, 8, 3, generator=g))


def _pair(**overrides):
    """Two tiny models with identical weights, backends sdpa and flex."""
    torch.manual_seed(1)
    a = randomize_new_modules(WorldModel(preset("tiny", **overrides))).eval()
    b = WorldModel(preset("tiny", attention_backend="flex", **overrides)).eval()
    b.load_state_dict(a.state_dict())
    return a, b


def _maxdiff(x, y):
    return (x - y).abs().max().item()


@pytest.mark.parametrize("causal", [True, False])
def test_flex_equals_sdpa(causal):
    sdpa, flex = _pair(causal=causal)
    x, t, text, a, traj = _inputs()
    with torch.no_grad():
        ref, out = sdpa(x, t, text, traj, a), flex(x, t, text, traj, a)
    assert _maxdiff(out, ref) <= TOL and ref.abs().max().item() > 0.1


def test_flex_kv_cache_matches_sdpa_uncached():
    """History once with return_kv_cache, then new frames against the cache (S_q != S_k BlockMasks)."""
    sdpa, flex = _pair()
    x, t, text, a, traj = _inputs(t=5)
    with torch.no_grad():
        full = sdpa(x, t, text, traj, a)
        _, cache = flex(x[:, :2], t[:, :2], text, traj, a[:, :2], return_kv_cache=True)
        out, cache = flex(x[:, 2:4], t[:, 2:4], None, traj, a[:, 2:4], kv_cache=cache, return_kv_cache=True)
        assert _maxdiff(out, full[:, 2:4]) <= TOL
        last = flex(x[:, 4:], t[:, 4:], None, traj, a[:, 4:], kv_cache=cache)
        assert _maxdiff(last, full[:, 4:]) <= TOL


def test_flex_rollout_step_equals_sdpa():
    """A short guided rollout (KV cache on) through resim.sample gives the same frames with both backends."""
    from resim.diffusion.guidance import guidance_preset
    from resim.sample.rollout import Condition, RolloutConfig, rollout

    sdpa, flex = _pair()
    g = torch.Generator().manual_seed(0)
    hist = torch.randn(1, 3, 16, 8, 12, generator=g)
    cond = Condition(text=torch.randn(1, 6, 64, generator=g), null_text=torch.randn(1, 6, 64, generator=g),
                     trajectory=torch.randn(1, 8, 3, generator=g))
    cfg = RolloutConfig(num_steps=2, frames_per_round=2, chunk_frames=1, kv_cache="on",
                        guidance=guidance_preset("resim"))
    outs = [rollout(m, hist, cond, 2, cfg, seed=3) for m in (sdpa, flex)]
    assert outs[1].kv_cache_used
    torch.testing.assert_close(outs[1].latents, outs[0].latents, rtol=1e-4, atol=1e-4)


def test_flex_gradients_equal_sdpa():
    """Training path (backward through eager flex_attention), with gradient checkpointing on the flex model."""
    sdpa, flex = _pair()
    flex.cfg.gradient_checkpointing = True
    x, t, text, a, traj = _inputs(t=3)
    for m in (sdpa, flex):
        m.train()
        m(x, t, text, traj, a).square().mean().backward()
    for name in ("transformer_blocks.0.attn1.to_q.weight", "transformer_blocks.1.attn1.to_k.weight",
                 "patch_embed.proj.weight"):
        ga, gb = (dict(m.named_parameters())[name].grad for m in (sdpa, flex))
        assert ga.abs().sum() > 0 and torch.allclose(ga, gb, atol=1e-6, rtol=1e-4), name


def test_flex_under_autocast():
    """Under autocast SDPA runs in the autocast dtype; the flex path casts q, k, v to it itself."""
    sdpa, flex = _pair()
    x, t, text, a, traj = _inputs(t=2)
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
        ref, out = sdpa(x, t, text, traj, a), flex(x, t, text, traj, a)
    assert out.dtype == ref.dtype and _maxdiff(out.float(), ref.float()) <= 0.05 * ref.abs().max().item()


def test_block_mask_is_cached_and_matches_dense():
    from resim.models.world.attention import block_causal_block_mask, block_causal_mask
    bm = block_causal_block_mask(3, 4, 2, prefix_frames=1, with_text_queries=False)
    assert block_causal_block_mask(3, 4, 2, prefix_frames=1, with_text_queries=False) is bm  # built once
    assert block_causal_block_mask(3, 4, 3, prefix_frames=1, with_text_queries=False) is not bm
    dense = block_causal_mask(3, 4, 2, prefix_frames=1, with_text_queries=False)
    q, k = torch.meshgrid(torch.arange(dense.shape[0]), torch.arange(dense.shape[1]), indexing="ij")
    assert bm.shape[-2:] == dense.shape
    assert torch.equal(bm.mask_mod(0, 0, q, k), dense)


def test_config_validation():
    assert preset("tiny").attention_backend == "sdpa"              # default: nothing changes for existing users
    assert preset("tiny", attention_backend="flex").attention_backend == "flex"
    with pytest.raises(ConfigError, match="attention_backend"):
        preset("tiny", attention_backend="cudnn")                   # as when a run config is loaded
    with pytest.raises(ConfigError, match="attention_backend"):
        WorldModelConfig(attention_backend="flash")
    cfg = from_dict(WorldModelConfig, {"attention_backend": "flex"})
    assert cfg.attention_backend == "flex"
    model = WorldModel(preset("tiny"))
    model.set_attention_backend("flex")
    assert model.cfg.attention_backend == "flex"
    with pytest.raises(ConfigError, match="attention_backend"):
        model.set_attention_backend("xformers")


def test_build_world_override():
    from resim.train.tasks.world_model import build_world
    model = build_world({"preset": "tiny", "overrides": {"attention_backend": "flex"}})
    assert model.cfg.attention_backend == "flex"


@pytest.mark.gpu
def test_flex_compiled_on_cuda_equals_sdpa():
    """The compiled Triton kernel (CUDA only), uncached and with a KV cache (two more geometries: recompiles).
    Looser tolerance than on CPU: the two CUDA kernels may use TF32 / different tilings for fp32."""
    sdpa, flex = (m.cuda() for m in _pair())
    x, t, text, a, traj = (v.cuda() for v in _inputs(t=5))
    with torch.no_grad():
        full = sdpa(x, t, text, traj, a)
        _, cache = flex(x[:, :2], t[:, :2], text, traj, a[:, :2], return_kv_cache=True)
        out, cache = flex(x[:, 2:4], t[:, 2:4], None, traj, a[:, 2:4], kv_cache=cache, return_kv_cache=True)
        last = flex(x[:, 4:], t[:, 4:], None, traj, a[:, 4:], kv_cache=cache)
        diffs = [_maxdiff(flex(x, t, text, traj, a), full), _maxdiff(out, full[:, 2:4]), _maxdiff(last, full[:, 4:])]
    print(f"max |flex - sdpa| on CUDA, fp32: uncached / cached 2 frames / cached 1 frame = {diffs}")
    assert max(diffs) <= 5e-3, diffs
    for m in (sdpa, flex):                        # backward through the compiled kernel
        m.train()
        m(x, t, text, traj, a).square().mean().backward()
    ga, gb = (m.transformer_blocks[0].attn1.to_q.weight.grad for m in (sdpa, flex))
    rel = ((ga - gb).abs().max() / ga.abs().max()).item()
    print(f"to_q gradient, max |flex - sdpa| / max |sdpa| on CUDA = {rel:.2e}")
    assert ga.abs().sum() > 0 and rel <= 1e-2
