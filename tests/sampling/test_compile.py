"""Compiled sampling (resim/sample/compile.py): a rollout with compiled blocks equals the eager one, the
compiled code is what runs, and runtime.compile reaches the model from the command line."""
import pytest
import torch

from resim.config import ConfigError, from_dict
from resim.diffusion.guidance import guidance_preset
from resim.models.world.config import preset
from resim.models.world.dit import WorldModel
from resim.sample.compile import compile_blocks, is_compiled, maybe_compile, wants_compile
from resim.sample.rollout import Condition, RolloutConfig, rollout
from resim.sample.settings import RuntimeConfig

B, C, H, W, L, D = 2, 16, 4, 6, 16, 64   # the tiny WorldModel preset's channels, text length and width


@pytest.fixture
def world():
    """The real DiT (its blocks are what gets compiled) at the tiny preset, conditioning modules randomised."""
    torch.manual_seed(1)
    model = WorldModel(preset("tiny")).eval().requires_grad_(False)
    with torch.no_grad():
        for n, p in model.named_parameters():
            if n.startswith(("trajectory_encoder.head", "trajectory_encoder.null")):
                p.normal_(0, 0.1)
    return model


def _inputs():
    g = torch.Generator().manual_seed(0)
    cond = Condition(text=torch.randn(B, L, D, generator=g), null_text=torch.randn(B, L, D, generator=g),
                     trajectory=torch.randn(B, 8, 3, generator=g))
    return torch.randn(B, 3, C, H, W, generator=g), cond


def test_wants_compile():
    assert wants_compile("auto", "cuda") and wants_compile("auto", torch.device("cuda", 1))
    assert not wants_compile("auto", "cpu") and not wants_compile("auto", torch.device("cpu"))
    assert wants_compile("on", "cpu") and not wants_compile("off", "cuda")
    with pytest.raises(ValueError, match="compile='yes'"):
        wants_compile("yes", "cpu")


def test_off_leaves_the_model_eager(world):
    model = world
    info = maybe_compile(model, "auto", "cpu")
    assert info == {"compile": False, "compile_flag": "auto"} and not is_compiled(model)


def test_the_settings_take_the_compile_choices():
    """`--set runtime.compile=...` is validated on load against the choices maybe_compile takes."""
    assert from_dict(RuntimeConfig, {}).compile == "auto"
    assert from_dict(RuntimeConfig, {"compile": "on", "compile_mode": "reduce-overhead"}).compile == "on"
    with pytest.raises(ConfigError, match="runtime.compile: 'yes' is not one of"):
        from_dict(RuntimeConfig, {"compile": "yes"}, prefix="runtime")


def test_compiled_rollout_equals_eager(world, needs_inductor):
    """Same seed, same inputs: compiled blocks give the eager rollout up to rounding, through the KV cache and
    CFG batching, frame by frame (Vid2World: the cache grows every chunk, the hard case for shapes; ReSim's
    one-chunk rollout with --compile on is checked by tests/sampling/test_cli.py). The compiled code is what
    runs: dynamo captured graphs, below its recompile limit (past it a block would quietly run eager), and a
    second rollout reuses them."""
    torch._dynamo.reset()
    model = world
    hist, cond = _inputs()
    cfg = RolloutConfig(num_steps=2, history_frames=3, frames_per_round=6, chunk_frames=1,
                        guidance=guidance_preset("vid2world"))
    eager = rollout(model, hist, cond, 6, cfg, seed=4).future
    names = list(model.state_dict())
    info = maybe_compile(model, "on", "cpu")
    assert info["compile"] and is_compiled(model)
    assert list(model.state_dict()) == names          # checkpoints and EMA names unchanged
    assert compile_blocks(model) == 0                  # idempotent
    torch._dynamo.utils.counters.clear()
    stats = torch._dynamo.utils.counters["stats"]
    compiled = rollout(model, hist, cond, 6, cfg, seed=4).future
    torch.testing.assert_close(compiled, eager, rtol=1e-4, atol=1e-4)
    graphs = stats["unique_graphs"]
    # 6 cache lengths frame by frame, each with a chunk step and an append: static graphs per length would be
    # 13, past the limit; torch's default compiles static first, then once with symbolic lengths
    assert 1 <= graphs < 8, dict(stats)
    again = rollout(model, hist, cond, 6, cfg, seed=4).future
    torch.testing.assert_close(again, compiled, rtol=0, atol=0)
    assert stats["unique_graphs"] == graphs            # the code compiled above, reused


def test_compile_needs_blocks():
    with pytest.raises(TypeError, match="no transformer_blocks"):
        compile_blocks(torch.nn.Linear(2, 2))
    m = torch.nn.Module()
    m.transformer_blocks = torch.nn.ModuleList([torch.nn.Linear(2, 2)])
    with pytest.raises(ValueError, match="compile mode"):
        compile_blocks(m, mode="fast")
    assert not is_compiled(m)                       # refused before anything was compiled
