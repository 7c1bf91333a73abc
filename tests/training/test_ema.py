"""The EMA's warm-up: the decay rule of diffusers' EMAModel, its effect on a short run, and exact resume."""
import pytest
import torch
from diffusers.training_utils import EMAModel
from safetensors.torch import load_file

from resim.config import from_dict
from training.config import RunConfig
from training.ema import EMA, warmup_decay
from training.registry import build
from training.trainer import Trainer


def _cfg(**trainer):
    t = {"steps": 6, "progress_bar": False, "tensorboard": False, "loss_curve_png": False, **trainer}
    return from_dict(RunConfig, {"model_name": "toy", "trainer": t, "optim": {"lr": 1e-2}})


def _data(n=6, bs=4, seed=1):
    g = torch.Generator().manual_seed(seed)
    return [{"x": torch.randn(bs, 16, generator=g)} for _ in range(n)]


def test_warmup_decay_is_diffusers_rule():
    ref = EMAModel([torch.nn.Parameter(torch.zeros(1))], decay=0.999)
    for n in (1, 2, 3, 10, 100, 1000, 5000):
        assert warmup_decay(0.999, n) == pytest.approx(ref.get_decay(n)), n
    with pytest.raises(ValueError):
        warmup_decay(0.999, 0)


def test_warmup_lets_a_short_run_forget_its_start():
    """A weight walking 0 -> 1 over 300 updates: with warm-up the EMA ends near it, without warm-up it is still
    mostly the initial 0 (0.999 ** 300 = 0.74 of it)."""
    ends = {}
    for warm in (True, False):
        p = torch.nn.Linear(1, 1, bias=False)
        with torch.no_grad():
            p.weight.zero_()
        ema = EMA(p, 0.999, warmup=warm)
        for n in range(1, 301):
            with torch.no_grad():
                p.weight.fill_(n / 300)
            ema.update(n)
        ends[warm] = float(ema.shadow["weight"])
    assert ends[True] > 0.8
    assert ends[False] < 0.2


def test_resumed_ema_equals_uninterrupted(tmp_path):
    """The warm-up counts the trainer's steps, which a resume restores: the resumed EMA is the same."""
    torch.manual_seed(0)
    Trainer(build("toy", {}), _cfg(ema_decay=0.9), tmp_path / "ref").fit(_data())
    torch.manual_seed(0)
    s = Trainer(build("toy", {}), _cfg(ema_decay=0.9, max_wall_s=0.0, checkpoint_every_steps=1),
                tmp_path / "cut").fit(_data())
    assert s["final_step"] == 1
    torch.manual_seed(0)
    Trainer(build("toy", {}), _cfg(ema_decay=0.9), tmp_path / "cut", resume=True).fit(_data())
    ref = load_file(str(tmp_path / "ref" / "final" / "ema.safetensors"))
    cut = load_file(str(tmp_path / "cut" / "final" / "ema.safetensors"))
    assert set(ref) == set(cut)
    for k in ref:
        torch.testing.assert_close(cut[k], ref[k], rtol=1e-6, atol=1e-7)
