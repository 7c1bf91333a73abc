"""WorldModel: parity with diffusers CogVideoX, block causality, per-frame levels, KV cache, conditioning."""
import pytest
import torch

from resim.models.world.config import preset
from resim.models.world.dit import WorldModel


def _inputs(b=2, t=4, h=8, w=12, seed=0):
    g = torch.Generator().manual_seed(seed)
    return (torch.randn(b, t, 16, h, w, generator=g), torch.randint(0, 1000, (b, t), generator=g),
            torch.randn(b, 16, 64, generator=g), torch.randn(b, t, 3, generator=g), torch.randn(b, 8, 3, generator=g))


@pytest.mark.parametrize("size", [(4, 8, 12), (3, 6, 10)])
def test_matches_diffusers_cogvideox(cogvideox, size):
    """causal off, one shared level, no trajectory/actions → the diffusers model's output (≤ 1e-5, fp32)."""
    model = WorldModel.from_cogvideox(cogvideox, causal=False).eval()
    t_lat, h, w = size
    x, _, text, _, _ = _inputs(2, t_lat, h, w)
    levels = torch.tensor([731, 12])
    with torch.no_grad():
        ref = cogvideox(x, text, levels).sample
        out = model(x, levels[:, None].expand(2, t_lat), text)
    assert out.shape == x.shape
    assert (out - ref).abs().max().item() <= 1e-5
    assert ref.abs().max().item() > 0.1  # not a trivial comparison


def test_from_saved_folder(cogvideox, tmp_path):
    cogvideox.save_pretrained(tmp_path / "transformer")
    a = WorldModel.from_cogvideox(tmp_path, causal=False).eval()  # pipeline-style folder
    b = WorldModel.from_cogvideox(cogvideox, causal=False).eval()
    x, t, text, _, _ = _inputs()
    with torch.no_grad():
        assert torch.equal(a(x, t, text), b(x, t, text))


def test_refuses_unsupported_variant(cogvideox):
    from resim.config import ConfigError
    from resim.models.world.config import config_from_cogvideox
    with pytest.raises(ConfigError, match="use_rotary_positional_embeddings"):
        config_from_cogvideox({**dict(cogvideox.config), "use_rotary_positional_embeddings": True})


def test_new_modules_start_neutral(cogvideox):
    """Freshly loaded: trajectory and actions change nothing (zero-initialised outputs and nulls)."""
    model = WorldModel.from_cogvideox(cogvideox, causal=True).eval()
    x, t, text, a, traj = _inputs()
    with torch.no_grad():
        assert torch.equal(model(x, t, text), model(x, t, text, traj, a))


def test_block_causal(tiny_model):
    """Perturbing frames > f (latents, levels, actions) leaves every output at frames ≤ f unchanged."""
    x, t, text, a, traj = _inputs(t=5)
    with torch.no_grad():
        out = tiny_model(x, t, text, traj, a)
        for f in range(4):
            x2, t2, a2 = x.clone(), t.clone(), a.clone()
            x2[:, f + 1:] += torch.randn_like(x2[:, f + 1:])
            t2[:, f + 1:] = 999 - t2[:, f + 1:]
            a2[:, f + 1:] += 1.0
            out2 = tiny_model(x2, t2, text, traj, a2)
            assert (out2[:, :f + 1] - out[:, :f + 1]).abs().max().item() <= 1e-6
            assert (out2[:, f + 1:] - out[:, f + 1:]).abs().max().item() > 1e-3


def test_non_causal_sees_future(cogvideox):
    model = WorldModel.from_cogvideox(cogvideox, causal=False).eval()
    x, t, text, _, _ = _inputs()
    with torch.no_grad():
        out = model(x, t, text)
        x2 = x.clone()
        x2[:, -1] += 1.0
        assert (model(x2, t, text)[:, 0] - out[:, 0]).abs().max() > 1e-4


def test_per_frame_levels(tiny_model):
    """Changing frame f's level changes frame f's output and, causal, no earlier frame's."""
    x, t, text, a, traj = _inputs(t=4)
    with torch.no_grad():
        out = tiny_model(x, t, text, traj, a)
        for f in range(4):
            t2 = t.clone()
            t2[:, f] = (t2[:, f] + 500) % 1000
            out2 = tiny_model(x, t2, text, traj, a)
            assert (out2[:, f] - out[:, f]).abs().max().item() > 1e-3
            if f:
                assert (out2[:, :f] - out[:, :f]).abs().max().item() <= 1e-6


def test_kv_cache_matches_uncached(tiny_model):
    x, t, text, a, traj = _inputs(t=5)
    with torch.no_grad():
        full = tiny_model(x, t, text, traj, a)
        _, cache = tiny_model(x[:, :2], t[:, :2], text, traj, a[:, :2], return_kv_cache=True)
        assert cache.num_frames == 2 and len(cache.keys) == 2
        out, cache = tiny_model(x[:, 2:4], t[:, 2:4], None, traj, a[:, 2:4], kv_cache=cache, return_kv_cache=True)
        assert (out - full[:, 2:4]).abs().max().item() <= 1e-5
        last = tiny_model(x[:, 4:], t[:, 4:], None, traj, a[:, 4:], kv_cache=cache)
        assert (last - full[:, 4:]).abs().max().item() <= 1e-5
        again = tiny_model(x[:, 2:3], t[:, 2:3], None, traj, a[:, 2:3], kv_cache=cache.crop(2))
        assert (again - full[:, 2:3]).abs().max().item() <= 1e-5


def test_kv_cache_needs_causal(cogvideox):
    model = WorldModel.from_cogvideox(cogvideox, causal=False)
    x, t, text, _, _ = _inputs()
    _, cache = WorldModel.from_cogvideox(cogvideox, causal=True)(x[:, :1], t[:, :1], text, return_kv_cache=True)
    with pytest.raises(ValueError, match="causal"):
        model(x[:, 1:], t[:, 1:], None, kv_cache=cache)


def test_conditions_and_nulls(tiny_model):
    x, t, text, a, traj = _inputs()
    with torch.no_grad():
        base = tiny_model(x, t, text, traj, a)
        assert (tiny_model(x, t, text, traj + 1.0, a) - base).abs().max() > 1e-4
        assert (tiny_model(x, t, text, traj, a + 1.0) - base).abs().max() > 1e-4
        # keep=False equals passing no condition (the null embedding)
        no_traj = tiny_model(x, t, text, None, a)
        dropped = tiny_model(x, t, text, traj, a, trajectory_keep=torch.tensor([False, False]))
        assert torch.equal(no_traj, dropped)
        no_act = tiny_model(x, t, text, traj, None)
        dropped = tiny_model(x, t, text, traj, a, action_keep=torch.zeros(2, 4, dtype=torch.bool))
        assert torch.allclose(no_act, dropped, atol=1e-6)


def test_discrete_actions():
    torch.manual_seed(0)
    model = WorldModel(preset("tiny", actions=dict(kind="discrete", num_actions=5))).eval()
    with torch.no_grad():
        model.action_encoder.proj_out.weight.normal_()
    x, t, text, _, _ = _inputs()
    ids = torch.randint(0, 5, (2, 4))
    with torch.no_grad():
        out = model(x, t, text, actions=ids)
        ids2 = ids.clone()
        ids2[:, 3] = (ids2[:, 3] + 1) % 5
        out2 = model(x, t, text, actions=ids2)
    assert (out2[:, :3] - out[:, :3]).abs().max() <= 1e-6 and (out2[:, 3] - out[:, 3]).abs().max() > 1e-4
    with pytest.raises(ValueError, match="ids"):
        model(x, t, text, actions=torch.full((2, 4), 7))


def test_bad_shapes_are_named(tiny_model):
    x, t, text, a, traj = _inputs()
    with pytest.raises(ValueError, match="t must be"):
        tiny_model(x, t[:, :2], text)
    with pytest.raises(ValueError, match="trajectory must be"):
        tiny_model(x, t, text, traj[:, :5])
    with pytest.raises(ValueError, match="x must be"):
        tiny_model(x[:, :, :4], t, text)


def test_gradient_checkpointing_same_gradients():
    torch.manual_seed(0)
    a = WorldModel(preset("tiny"))
    b = WorldModel(preset("tiny", gradient_checkpointing=True))
    b.load_state_dict(a.state_dict())
    x, t, text, act, traj = _inputs(t=3)
    for m in (a, b):
        m(x, t, text, traj, act).square().mean().backward()
    ga = a.transformer_blocks[0].attn1.to_q.weight.grad
    assert torch.allclose(ga, b.transformer_blocks[0].attn1.to_q.weight.grad, atol=1e-6) and ga.abs().sum() > 0


def test_block_causal_mask_layout():
    from resim.models.world.attention import block_causal_mask
    m = block_causal_mask(text_len=2, tokens_per_frame=2, num_frames=2)
    expect = torch.tensor([[1, 1, 0, 0, 0, 0],   # text sees text only
                           [1, 1, 0, 0, 0, 0],
                           [1, 1, 1, 1, 0, 0],   # frame 0 sees text + frame 0
                           [1, 1, 1, 1, 0, 0],
                           [1, 1, 1, 1, 1, 1],   # frame 1 sees text + frames 0, 1
                           [1, 1, 1, 1, 1, 1]], dtype=torch.bool)
    assert torch.equal(m, expect)
    suffix = block_causal_mask(2, 2, 1, prefix_frames=1, with_text_queries=False)
    assert torch.equal(suffix, expect[4:])


def test_blocks_return_no_views(tiny_model):
    """Blocks are FSDP2 units: a view among their outputs makes FSDP2 warn that an in-place op on it could
    corrupt gradients (its pre-backward hook lands on the view). Every output must own its storage."""
    blk = tiny_model.transformer_blocks[0]
    d = blk.attn1.to_q.in_features
    tdim = blk.norm1.linear.in_features
    video, text = torch.randn(2, 3 * 4, d, requires_grad=True), torch.randn(2, 5, d, requires_grad=True)
    temb, temb_text = torch.randn(2, 3, tdim), torch.randn(2, tdim)
    v, e, kv = blk(video, text, temb, temb_text, None)
    assert kv is None and v._base is None and e._base is None  # training: no keys/values returned
    v, e, kv = blk(video, text, temb, temb_text, None, None, True)
    assert all(t._base is None and t.is_contiguous() for t in (v, e, *kv))
    assert kv[0].shape == kv[1].shape == (2, blk.attn1.heads, 5 + 12, blk.attn1.head_dim)


def _pooled_model(seed=0):
    """tiny + the pooled-text path, its zero-initialised head given weights (as after training)."""
    torch.manual_seed(seed)
    model = WorldModel(preset("tiny", text_pool=dict(enabled=True, hidden_dim=32, num_heads=2))).eval()
    with torch.no_grad():
        model.text_pooler.head.weight.normal_(std=0.3)
    return model


def test_text_pool_starts_neutral_and_loads_older_weights():
    """Enabled but untrained, the pooled path changes nothing: weights without it give the same outputs."""
    torch.manual_seed(0)
    pooled = WorldModel(preset("tiny", text_pool=dict(enabled=True, hidden_dim=32, num_heads=2))).eval()
    plain = WorldModel(preset("tiny")).eval()
    plain.load_state_dict({k: v for k, v in pooled.state_dict().items() if not k.startswith("text_pooler.")})
    x, t, text, a, traj = _inputs()
    with torch.no_grad():
        assert torch.equal(pooled(x, t, text, traj, a), plain(x, t, text, traj, a))
    assert {p for p in pooled.new_parameters()} >= set(pooled.text_pooler.parameters())


def test_text_pool_steers_every_frame_and_keeps_cache_exact():
    """Trained (non-zero head): the prompt changes every frame's output through the modulation, and the KV
    cache carries the pooled vector so cached rollouts equal uncached ones."""
    model = _pooled_model()
    x, t, text, a, traj = _inputs(t=5)
    with torch.no_grad():
        full = model(x, t, text, traj, a)
        assert torch.allclose(model(x, t, text.flip(1), traj, a), full, atol=1e-5)   # text tokens are a set
        other_text = torch.randn(text.shape, generator=torch.Generator().manual_seed(5))
        assert (model.text_pooler(other_text) - model.text_pooler(text)).abs().max() > 1e-2
        with torch.no_grad():
            no_pool = _pooled_model()
            no_pool.text_pooler.head.weight.zero_()
        moved = (model(x, t, other_text, traj, a) - full).flatten(2).norm(dim=-1)
        moved_joint_only = (no_pool(x, t, other_text, traj, a) - no_pool(x, t, text, traj, a)).flatten(2).norm(dim=-1)
        assert (moved > 1.5 * moved_joint_only).all()          # every frame, beyond what joint attention does
        _, cache = model(x[:, :2], t[:, :2], text, traj, a[:, :2], return_kv_cache=True)
        assert cache.text_cond is not None and cache.crop(1).text_cond is cache.text_cond
        out = model(x[:, 2:], t[:, 2:], None, traj, a[:, 2:], kv_cache=cache)
        assert (out - full[:, 2:]).abs().max().item() <= 1e-5
        plain_cache = WorldModel(preset("tiny"))(x[:, :2], t[:, :2], text, return_kv_cache=True)[1]
        with pytest.raises(ValueError, match="pooled text"):
            model(x[:, 2:], t[:, 2:], None, traj, a[:, 2:], kv_cache=plain_cache)


def _local_model(seed=0, **head):
    torch.manual_seed(seed)
    return WorldModel(preset("tiny", local_head=dict(enabled=True, channels=16, **head)))


def test_local_head_starts_neutral_and_keeps_cache_exact():
    """Enabled but untrained, the head adds nothing (weights without it give the same outputs); trained, it works
    frame by frame, so a KV-cached call still equals the uncached one."""
    head = _local_model().eval()
    plain = WorldModel(preset("tiny")).eval()
    plain.load_state_dict({k: v for k, v in head.state_dict().items() if not k.startswith("local_head.")})
    x, t, text, a, traj = _inputs(t=5)
    with torch.no_grad():
        assert torch.equal(head(x, t, text, traj, a), plain(x, t, text, traj, a))
        head.local_head.conv_out.weight.normal_(std=0.1)
        full = head(x, t, text, traj, a)
        assert (full - plain(x, t, text, traj, a)).abs().max() > 1e-2
        _, cache = head(x[:, :2], t[:, :2], text, traj, a[:, :2], return_kv_cache=True)
        assert (head(x[:, 2:], t[:, 2:], None, traj, a[:, 2:], kv_cache=cache) - full[:, 2:]).abs().max() <= 1e-5
    assert set(head.new_parameters()) >= set(head.local_head.parameters())


def test_local_head_learns_what_wide_patches_cannot():
    """The pixel-wise part of v: a target equal to the noisy input itself (v = eps at t = 0 of a zero image).
    With 4 x 4 patches of 16 channels (256 values per token) through a width-64 DiT, the projection to pixels has
    rank <= 64, so the plain model cannot get far below 1 - 64/256 of the variance; with the head it can."""
    def fit(model, steps=150):
        opt = torch.optim.Adam(model.parameters(), lr=3e-3)
        g = torch.Generator().manual_seed(1)
        text = torch.zeros(4, 4, 64)
        for _ in range(steps):
            x = torch.randn(4, 2, 16, 8, 8, generator=g)
            loss = ((model(x, torch.zeros(4, 2, dtype=torch.long), text) - x) ** 2).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
        return float(loss.detach())
    wide = dict(patch_size=4, num_attention_heads=2, attention_head_dim=32, num_layers=1)
    torch.manual_seed(0)
    plain = fit(WorldModel(preset("tiny", **wide)))
    torch.manual_seed(0)
    with_head = fit(WorldModel(preset("tiny", **wide, local_head=dict(enabled=True, channels=32))))
    assert plain > 0.7 and with_head < 0.5 * plain, (plain, with_head)
