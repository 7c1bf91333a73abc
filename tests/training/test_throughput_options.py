"""Training-throughput options, on the real world model: a compiled step gives the eager step's loss (loss
parity), selective activation checkpointing keeps less than none and more than full while giving the same
gradients, and the AdamW kernels (fused, foreach, for-loop) train alike."""
import json

import pytest
import torch

from resim.config import ConfigError, from_dict
from resim.models.registry import build
from resim.train.config import RunConfig, TrainerConfig
from resim.train.tasks.vae import TrainableVAE
from resim.train.traffic import SavedActivations
from resim.train.trainer import Trainer, adamw_kernel

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _world(num_layers=4):
    torch.manual_seed(0)
    return build("world", {"preset": "tiny", "overrides": {"num_layers": num_layers}})


class _Batch(dict):
    """A dict the world model's FLOP count can read as attributes (``batch.latents``), as it reads a Batch."""

    def __getattr__(self, k):
        try:
            return self[k]
        except KeyError:
            raise AttributeError(k) from None

    def to(self, device):
        return _Batch({k: v.to(device) if isinstance(v, torch.Tensor) else v for k, v in self.items()})


def _data(n=3, b=2, seed=1):
    g = torch.Generator().manual_seed(seed)
    return [_Batch({"latents": torch.randn(b, 4, 16, 4, 6, generator=g), "text": torch.randn(b, 16, 64, generator=g),
             "null_text": torch.zeros(b, 16, 64), "trajectory": torch.randn(b, 8, 3, generator=g),
             "source": ["carla"] * b}) for _ in range(n)]


def _cfg(**trainer):
    t = {"steps": 3, "progress_bar": False, "tensorboard": False, "loss_curve_png": False,
         "save_final_weights": False, **trainer}
    return from_dict(RunConfig, {"model_name": "world", "trainer": t, "optim": {"lr": 1e-3}})


def _losses(run_dir):
    return [json.loads(line)["loss"] for line in open(run_dir / "metrics.jsonl")]


def test_compiled_steps_match_eager(tmp_path, needs_inductor):
    """trainer.compile compiles each block; the loss's noise and dropout stay eager, so the same seed gives the
    same losses step after step (the loss parity the GPU runs rely on), and the same weights, up to the
    compiler's rounding."""
    torch._dynamo.reset()
    runs = {}
    for name, comp in (("eager", False), ("compiled", True)):
        model = _world()
        torch._dynamo.utils.counters.clear()
        Trainer(model, _cfg(compile=comp), tmp_path / name).fit(_data())
        runs[name] = (_losses(tmp_path / name), torch.cat([p.detach().flatten() for p in model.parameters()]),
                      torch._dynamo.utils.counters["stats"]["unique_graphs"])
    assert runs["eager"][2] == 0 and runs["compiled"][2] >= 1        # it compiled, and only then
    assert runs["compiled"][0] == pytest.approx(runs["eager"][0], rel=1e-4)
    # Adam divides by the gradient's running RMS, which turns rounding in near-zero gradients into updates of up
    # to ~lr: 3 steps of lr 1e-3 move a weight by up to 3e-3, and the two runs agree to 1e-4 of that scale
    torch.testing.assert_close(runs["compiled"][1], runs["eager"][1], rtol=1e-3, atol=1e-4)


def _saved_bytes_and_grads(every):
    model = _world()
    if every:
        model.set_activation_checkpointing(True, every_blocks=every)
    batch = _data(1, b=2)[0]
    saved = SavedActivations(model.parameters())
    with torch.autograd.graph.saved_tensors_hooks(*saved.hooks()):
        loss, _ = model.loss(_seeded(batch))
    loss.backward()
    return saved.bytes, loss.item(), {n: p.grad.clone() for n, p in model.named_parameters() if p.grad is not None}


def _seeded(batch):
    torch.manual_seed(5)   # the objective draws its noise and levels from torch's RNG
    return batch


def test_selective_activation_checkpointing():
    """Every second block checkpointed: the tensors kept for backward lie between none and all blocks
    checkpointed, and the loss and gradients are the same (recomputation is exact)."""
    none, loss0, g0 = _saved_bytes_and_grads(0)
    half, loss2, g2 = _saved_bytes_and_grads(2)
    full, loss1, g1 = _saved_bytes_and_grads(1)
    assert full < half < none, (full, half, none)
    assert loss0 == loss1 == loss2
    for n in g0:
        torch.testing.assert_close(g2[n], g0[n], rtol=1e-5, atol=1e-7)
        torch.testing.assert_close(g1[n], g0[n], rtol=1e-5, atol=1e-7)


def test_activation_estimate_follows_the_setting():
    m = _world(num_layers=6)
    est = [m.activation_bytes_per_sample((13, 8, 12), ac, 2, every_blocks=k) for ac, k in
           ((False, 1), (True, 3), (True, 2), (True, 1))]
    assert est[0] > est[1] > est[2] > est[3]


def test_every_blocks_validated():
    with pytest.raises(ConfigError, match="activation_checkpointing_every_blocks"):
        TrainerConfig(activation_checkpointing_every_blocks=0)
    vae = build("vae", {"block_out_channels": [8, 8, 8, 8], "norm_num_groups": 2, "clip_frames": 9})
    assert isinstance(vae, TrainableVAE)
    with pytest.raises(ConfigError, match="all of its blocks or none"):
        vae.set_activation_checkpointing(True, every_blocks=2)
    vae.set_activation_checkpointing(True)                        # every block: diffusers' own checkpointing
    assert vae.is_gradient_checkpointing


def test_adamw_kernels(tmp_path):
    assert adamw_kernel("auto", torch.device("cpu")) == {"foreach": False, "fused": False}
    assert adamw_kernel("auto", torch.device("cuda")) == {"fused": True}
    weights = {}
    for impl in ("for-loop", "foreach", "fused"):
        model = _world(num_layers=2)
        cfg = from_dict(RunConfig, {"model_name": "world", "optim": {"lr": 1e-3, "implementation": impl},
                                    "trainer": {"steps": 2, "progress_bar": False, "tensorboard": False,
                                                "loss_curve_png": False, "save_final_weights": False}})
        tr = Trainer(model, cfg, tmp_path / impl)
        tr.fit(_data(2))
        d = tr.optimizer.defaults
        assert (bool(d.get("fused")), bool(d.get("foreach"))) == (impl == "fused", impl == "foreach")
        weights[impl] = torch.cat([p.detach().flatten() for p in model.parameters()])
    # the same updates up to rounding (2 steps of lr 1e-3: weights move by up to 2e-3)
    torch.testing.assert_close(weights["foreach"], weights["for-loop"], rtol=1e-4, atol=2e-5)
    torch.testing.assert_close(weights["fused"], weights["for-loop"], rtol=1e-4, atol=2e-5)
    with pytest.raises(ConfigError):
        from_dict(RunConfig, {"model_name": "world", "optim": {"implementation": "apex"}})
