"""The generic loop on a toy model (in process): schedule, accumulation, EMA, non-finite stop, safe loading."""
import json
import math
import pickle

import pytest
import torch
from diffusers.training_utils import EMAModel
from safetensors.torch import load_file

from resim.config import ConfigError, from_dict
from resim.models.registry import build
from resim.train import checkpoint as ckpt
from resim.train.config import RunConfig
from resim.train.ema import EMA, warmup_decay
from resim.train.lr import lr_at
from resim.train.trainer import NonFiniteLossError, Trainer


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _cfg(**trainer):
    t = {"steps": 6, "progress_bar": False, "tensorboard": False, "loss_curve_png": False, **trainer}
    return from_dict(RunConfig, {"model_name": "toy", "trainer": t, "optim": {"lr": 1e-2}})


def _data(n=6, bs=4, seed=1):
    g = torch.Generator().manual_seed(seed)
    return [{"x": torch.randn(bs, 16, generator=g)} for _ in range(n)]


def test_lr_schedule_closed_form():
    kw = dict(base_lr=1.0, warmup_steps=4, total_steps=14)
    assert [lr_at(s, **kw) for s in range(4)] == [0.25, 0.5, 0.75, 1.0]
    assert lr_at(9, **kw) == 1.0
    cos = [lr_at(s, schedule="cosine", min_lr_ratio=0.1, **kw) for s in range(4, 14)]
    assert cos[0] == pytest.approx(1.0) and cos[-1] == pytest.approx(0.1)
    mid = 0.1 + 0.9 * 0.5 * (1 + math.cos(math.pi * 5 / 9))
    assert cos[5] == pytest.approx(mid)


def test_grad_accumulation_matches_big_batch(tmp_path):
    """accum 2 x batch 2 == accum 1 x batch 4 for a model whose loss is a per-sample mean (noise off)."""
    data4 = _data(3, 4)
    data2 = [{"x": d["x"][i:i + 2]} for d in data4 for i in (0, 2)]
    out = []
    for name, data, acc in (("a", data4, 1), ("b", data2, 2)):
        torch.manual_seed(0)
        m = build("toy", {"noise_std": 0.0})
        Trainer(m, _cfg(steps=3, grad_accum_steps=acc, save_final_weights=False), tmp_path / name).fit(data)
        out.append([json.loads(line)["loss"] for line in open(tmp_path / name / "metrics.jsonl")])
        out.append(torch.cat([p.detach().flatten() for p in m.parameters()]))
    assert out[0] == pytest.approx(out[2], rel=1e-5)
    torch.testing.assert_close(out[1], out[3], rtol=1e-5, atol=1e-6)


def test_ema_and_final_weights(tmp_path):
    torch.manual_seed(0)
    m = build("toy", {})
    init = {n: p.detach().clone() for n, p in m.named_parameters()}
    Trainer(m, _cfg(steps=4, ema_decay=0.5), tmp_path).fit(_data())
    w = load_file(str(tmp_path / "final" / "model.safetensors"))
    e = load_file(str(tmp_path / "final" / "ema.safetensors"))
    assert set(w) == set(init) == set(e)
    for n, p in m.named_parameters():
        torch.testing.assert_close(w[n], p.detach())
        assert not torch.equal(e[n], w[n]) and not torch.equal(e[n], init[n])  # in between


class _Exploding(torch.nn.Module):
    def __init__(self):
        super().__init__()
        self.w = torch.nn.Parameter(torch.ones(3))
        self.calls = 0

    def loss(self, batch):
        self.calls += 1
        out = (self.w * batch["x"][:, :3]).pow(2).mean()
        return (out * float("nan") if self.calls == 5 else out), {}


def test_nonfinite_loss_stops_naming_last_checkpoint(tmp_path):
    cfg = _cfg(steps=8, checkpoint_every_steps=2)
    with pytest.raises(NonFiniteLossError) as ei:
        Trainer(_Exploding(), cfg, tmp_path).fit(_data(8))
    msg = str(ei.value)
    assert "step 5" in msg and str(ckpt.checkpoint_path(tmp_path, 4)) in msg and "precision fp32" in msg
    assert ckpt.latest_complete(tmp_path) == ckpt.checkpoint_path(tmp_path, 4)


def test_checkpoint_refuses_foreign_pickles(tmp_path):
    torch.manual_seed(0)
    Trainer(build("toy", {}), _cfg(steps=2), tmp_path).fit(_data())
    path = ckpt.latest_complete(tmp_path)
    md = path / ".metadata"
    assert md.is_file()

    class Evil:
        def __reduce__(self):   # eval, not print: a Ray import earlier in the process replaces builtins.print
            return (eval, ("1",))

    md.write_bytes(pickle.dumps(Evil()))
    m = build("toy", {})
    t = Trainer(m, _cfg(steps=4), tmp_path, resume=True)
    with pytest.raises(ckpt.CheckpointError, match="builtins.eval"):
        t.fit(_data())


def test_resume_with_no_checkpoint_starts_fresh(tmp_path, capsys):
    torch.manual_seed(0)
    s = Trainer(build("toy", {}), _cfg(steps=2), tmp_path, resume=True).fit(_data())
    assert s["start_step"] == 0 and s["final_step"] == 2


def test_ema_export_is_complete_with_frozen_weights(tmp_path):
    """EMA tracks only trainable parameters; final/ema.safetensors must still be a full state dict (frozen tensors
    from the model, EMA values over the trained ones), else sampling / init_weights cannot load it strictly."""
    torch.manual_seed(0)
    m = build("toy", {})
    m.inp.requires_grad_(False)        # a frozen part, like the DiT in ReSim stage 2
    init = {n: p.detach().clone() for n, p in m.named_parameters()}
    Trainer(m, _cfg(steps=4, ema_decay=0.5), tmp_path).fit(_data())
    w = load_file(str(tmp_path / "final" / "model.safetensors"))
    e = load_file(str(tmp_path / "final" / "ema.safetensors"))
    assert set(e) == set(w) == set(m.state_dict())
    for n in ("inp.weight", "inp.bias"):          # frozen: the model's (= initial) values
        torch.testing.assert_close(e[n], init[n], rtol=0, atol=0)
    trained = [n for n, p in m.named_parameters() if p.requires_grad]
    assert all(not torch.equal(e[n], w[n]) for n in trained)   # EMA values, not the raw weights
    fresh = build("toy", {})
    fresh.load_state_dict(e, strict=True)


class _SometimesLogs(torch.nn.Module):
    """Reports ``sometimes`` in one micro-batch of four (like ``loss_t_high``: only when such a level was drawn)."""

    def __init__(self):
        super().__init__()
        self.w = torch.nn.Linear(16, 1)
        self.calls = 0

    def loss(self, batch):
        self.calls += 1
        logs = {"always": 2.0}
        if self.calls % 4 == 1:
            logs["sometimes"] = 3.0
        return self.w(batch["x"]).pow(2).mean(), logs


def test_logs_are_averaged_over_the_micro_batches_that_report_them(tmp_path):
    Trainer(_SometimesLogs(), _cfg(steps=2, grad_accum_steps=4, save_final_weights=False), tmp_path).fit(_data(8))
    recs = [json.loads(line) for line in open(tmp_path / "metrics.jsonl")]
    assert [(r["always"], r["sometimes"]) for r in recs] == [(2.0, 3.0), (2.0, 3.0)]   # not 3.0 / 4


def test_partial_training_ema_export_samples_and_inits(world_dataset, tmp_path):
    """ReSim stage 2 shape (only the new modules train) with EMA: the export loads for sampling (EMA preferred)
    and as the next stage's init_weights."""
    from resim.cli import main
    from resim.sample.load import load_world_model
    from resim.train.tasks.world_model import build_world
    run = tmp_path / "run"
    assert main(["train", "world", "--preset", "tiny", "--shards", str(world_dataset), "--out", str(run),
                 "--steps", "1", "--set", "trainer.progress_bar=false", "--set", "trainer.tensorboard=false",
                 "--set", "trainer.loss_curve_png=false", "--set", "trainer.ema_decay=0.9",
                 "--set", "model.trainable=new"]) == 0
    model, info = load_world_model(run)
    assert info["weights"] == "ema.safetensors"
    e = load_file(str(run / "final" / "ema.safetensors"))
    for n, t in model.state_dict().items():
        torch.testing.assert_close(t, e[n].to(t.dtype), rtol=0, atol=0)
    nxt = build_world({"preset": "tiny", "init_weights": str(run / "final" / "ema.safetensors")})
    torch.testing.assert_close(nxt.state_dict()["patch_embed.proj.weight"], e["patch_embed.proj.weight"])
    # a next stage may add a new conditioning module (it starts at zero output); a missing DiT tensor still fails
    pooled = build_world({"preset": "tiny", "init_weights": str(run / "final" / "ema.safetensors"),
                          "overrides": {"text_pool": {"enabled": True}}})
    assert torch.count_nonzero(pooled.text_pooler.head.weight) == 0
    from resim.config import ConfigError
    from safetensors.torch import save_file
    save_file({k: v for k, v in e.items() if k != "proj_out.weight"}, str(tmp_path / "partial.safetensors"))
    with pytest.raises(ConfigError, match="proj_out.weight"):
        build_world({"preset": "tiny", "init_weights": str(tmp_path / "partial.safetensors")})


def _loader(workers):
    g = torch.Generator().manual_seed(3)
    ds = torch.utils.data.TensorDataset(torch.randn(12, 16, generator=g))
    return torch.utils.data.DataLoader(ds, batch_size=2, shuffle=True, num_workers=workers,
                                       collate_fn=lambda b: {"x": torch.stack([t[0] for t in b])})


@pytest.mark.parametrize("workers,first,ckpt_every", [(0, 4, 0), (0, 8, 0), (2, 3, 3)])
def test_resume_is_exact_for_a_shuffled_dataloader(tmp_path, workers, first, ckpt_every):
    """A plain DataLoader (6 batches an epoch) resumed mid-epoch 1 or mid-epoch 2 logs the uninterrupted losses.
    Before, iter(DataLoader) after the RNG restore drew its shuffle seed from the restored global RNG: another
    batch order, and the model's noise (the toy draws it from the global RNG) shifted."""
    def run(out, steps, resume=False):
        torch.manual_seed(0)
        m = build("toy", {})
        Trainer(m, _cfg(steps=steps, save_final_weights=False, checkpoint_every_steps=ckpt_every), out,
                resume=resume).fit(_loader(workers))
        return [(r["step"], r["loss"]) for r in map(json.loads, open(out / "metrics.jsonl"))]

    ref = run(tmp_path / "ref", 10)
    run(tmp_path / "res", first)
    assert run(tmp_path / "res", 10, resume=True) == ref       # bitwise


def test_max_wall_s_stops_exports_and_resumes(tmp_path):
    """A spent wall-clock budget stops the loop after the step in flight, with a checkpoint and final weights at
    that step; --resume then runs on to trainer.steps."""
    torch.manual_seed(0)
    s = Trainer(build("toy", {}), _cfg(steps=6, max_wall_s=0.0), tmp_path).fit(_data())
    assert s["final_step"] == 1 and s["stopped_by_max_wall_s"]
    assert ckpt.latest_complete(tmp_path) == ckpt.checkpoint_path(tmp_path, 1)
    assert (tmp_path / "final" / "model.safetensors").is_file()
    assert [json.loads(line)["step"] for line in open(tmp_path / "metrics.jsonl")] == [1]
    s = Trainer(build("toy", {}), _cfg(steps=6), tmp_path, resume=True).fit(_data())
    assert s["start_step"] == 1 and s["final_step"] == 6 and not s["stopped_by_max_wall_s"]
    assert [json.loads(line)["step"] for line in open(tmp_path / "metrics.jsonl")] == [1, 2, 3, 4, 5, 6]


def test_max_wall_s_is_validated():
    with pytest.raises(ConfigError, match="max_wall_s"):
        _cfg(max_wall_s=-1)


# --- the EMA's warm-up: diffusers' EMAModel decay rule, its effect on a short run, exact resume
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
