"""LoRA in the world model (peft, ``resim.models.world.lora``): checkpoints of the hand-written ``LoRALinear`` it
replaced still load and compute what they did (``tests/data/lora-v1-world``, made by that code); a seeded build
draws the same initial weights; stage-1 weights initialise a LoRA model; the ``trainable`` modes; a LoRA run
trains, resumes exactly from its DCP checkpoint and exports weights that sampling and the next stage load."""
import json
import shutil
from pathlib import Path

import pytest
import torch
import yaml
from safetensors.torch import load_file, save_file

from resim.cli import main
from resim.config import ConfigError
from resim.models.world.dit import NEW_MODULE_PREFIXES
from resim.models.world.lora import is_lora_param, to_peft_layout
from resim.sample.load import load_world_model
from resim.train.tasks.world_model import build_world

V1 = Path(__file__).resolve().parents[1] / "data" / "lora-v1-world"
V1_MODEL = yaml.safe_load((V1 / "config.yaml").read_text())["model"]
# the tensors make_fixture.py set after building (the rest is the seeded build's initial state)
V1_SET = (".lora_B", "trajectory_encoder.head.", "action_encoder.proj_out.")


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _reference():
    r = load_file(str(V1 / "reference.safetensors"))
    return (r["x"], r["t"], r["text"], r["trajectory"], r["actions"]), r["v"]


def test_unusable_world_checkpoints_are_one_line_naming_the_file(tmp_path):
    """resim.models.exported's errors, as the sampler's SamplingInputError ("checkpoint ...")."""
    from resim.sample.load import SamplingInputError, run_objective

    run = tmp_path / "run"
    shutil.copytree(V1, run)
    (run / "config.yaml").write_text(yaml.safe_dump({"model_name": "world", "model": {**V1_MODEL, "lora_rank": 2}}))
    with pytest.raises(SamplingInputError, match=f"^checkpoint {run / 'model.safetensors'}: weights do not match "
                                                 "config.yaml"):
        load_world_model(run)
    (run / "config.yaml").write_text("model: [\n")
    for f in (load_world_model, run_objective):
        with pytest.raises(SamplingInputError, match=f"^checkpoint {run / 'config.yaml'}: invalid YAML"):
            f(run)
    with pytest.raises(SamplingInputError, match=f"^checkpoint {tmp_path}: expected config.yaml \\+ model.safetensors"):
        load_world_model(tmp_path)


def test_old_layout_checkpoint_reproduces_its_reference_output():
    model, info = load_world_model(V1)
    assert info["weights"] == "model.safetensors"
    assert type(model.transformer_blocks[0].ff.net[2]).__module__.startswith("peft.")
    inputs, v = _reference()
    with torch.no_grad():
        out = model(*inputs)
        torch.testing.assert_close(out, v, rtol=1.3e-6, atol=1e-5)
        for n, p in model.named_parameters():   # the adapters matter: without them the output is another
            if ".lora_B." in n:
                p.zero_()
        assert (model(*inputs) - v).abs().max() > 1e-3


def test_old_layout_keys_map_one_to_one_onto_the_peft_model():
    torch.manual_seed(0)
    model = build_world(V1_MODEL)
    old = load_file(str(V1 / "model.safetensors"))
    assert any(k.endswith(".to_q.lora_A") for k in old)      # the file really is in the old layout
    new = to_peft_layout(old, model)
    assert len(new) == len(old) and set(new) == set(model.state_dict())
    assert torch.equal(new["transformer_blocks.0.ff.net.2.lora_B.default.weight"],
                       old["transformer_blocks.0.ff.net.2.lora_B"])
    assert torch.equal(new["transformer_blocks.0.attn1.to_q.base_layer.weight"],
                       old["transformer_blocks.0.attn1.to_q.weight"])
    assert to_peft_layout(new, model) == new                 # the new layout passes unchanged


def test_seeded_build_draws_the_old_initial_weights_and_rng_stream():
    """A seeded run (``trainer.seed``) builds bit-identical weights, LoRA A included, and leaves the RNG where the
    hand-written LoRA left it: make_fixture.py built the same config under ``torch.manual_seed(0)``."""
    torch.manual_seed(0)
    model = build_world(V1_MODEL)
    own = model.state_dict()
    old = to_peft_layout(load_file(str(V1 / "model.safetensors")), model)
    kept = [k for k in own if not any(s in k for s in V1_SET)]
    assert any(".lora_A." in k for k in kept)
    for k in kept:
        torch.testing.assert_close(own[k], old[k], rtol=0, atol=0, msg=k)
    assert all(torch.count_nonzero(t) == 0 for k, t in own.items() if ".lora_B." in k)


def test_init_from_old_layout_and_from_stage1_weights(tmp_path):
    nxt = build_world({**V1_MODEL, "trainable": "all", "init_weights": str(V1 / "model.safetensors")})
    inputs, v = _reference()
    with torch.no_grad():
        torch.testing.assert_close(nxt.eval()(*inputs), v, rtol=1.3e-6, atol=1e-5)

    stage1 = {k: t for k, t in load_file(str(V1 / "model.safetensors")).items() if not k.endswith(("lora_A", "lora_B"))}
    save_file(stage1, str(tmp_path / "stage1.safetensors"))
    plain = build_world({"preset": "tiny", "overrides": {"num_layers": 1},
                         "init_weights": str(tmp_path / "stage1.safetensors")}).eval()
    lora = build_world({**V1_MODEL, "init_weights": str(tmp_path / "stage1.safetensors")}).eval()
    with torch.no_grad():   # B = 0: the LoRA model computes what stage 1 did
        torch.testing.assert_close(lora(*inputs), plain(*inputs), rtol=0, atol=0)
    del stage1["transformer_blocks.0.attn1.to_k.weight"]
    save_file(stage1, str(tmp_path / "partial.safetensors"))
    with pytest.raises(ConfigError, match=r"to_k\.base_layer\.weight"):
        build_world({**V1_MODEL, "init_weights": str(tmp_path / "partial.safetensors")})


@pytest.mark.parametrize("mode", ["all", "dit", "lora+new", "new"])
def test_trainable_modes(mode):
    model = build_world({"preset": "tiny", "lora_rank": 2, "trainable": mode})
    kind = {n: "new" if n.startswith(NEW_MODULE_PREFIXES) else "lora" if is_lora_param(n) else "dit"
            for n, _ in model.named_parameters()}
    assert set(kind.values()) == {"new", "lora", "dit"}
    want = {"all": {"new", "lora", "dit"}, "dit": {"dit"}, "lora+new": {"lora", "new"}, "new": {"new"}}[mode]
    for n, p in model.named_parameters():
        assert p.requires_grad == (kind[n] in want), n


def _train(ds, out, steps, *extra):
    return main(["train", "world", "--preset", "tiny", "--shards", str(ds), "--out", str(out), "--steps", str(steps),
                 "--checkpoint-every", "2", "--set", "data.num_workers=0", "--set", "trainer.progress_bar=false",
                 "--set", "trainer.tensorboard=false", "--set", "trainer.loss_curve_png=false",
                 "--set", "trainer.ema_decay=0.9", "--set", "model.lora_rank=4", "--set", "model.trainable=lora+new",
                 *extra])


def test_lora_run_resumes_exactly_and_exports_loadable_weights(world_dataset, tmp_path, capsys):
    run, resumed = tmp_path / "run", tmp_path / "resumed"
    assert _train(world_dataset, run, 4) == 0
    losses = [json.loads(line)["loss"] for line in open(run / "metrics.jsonl")]
    assert len(losses) == 4
    shutil.copytree(run, resumed)
    shutil.rmtree(resumed / "checkpoints" / "step_00000004")
    shutil.rmtree(resumed / "final")
    capsys.readouterr()
    assert _train(world_dataset, resumed, 4, "--resume") == 0
    assert "done: steps 2 -> 4" in capsys.readouterr().err          # from the DCP checkpoint of step 2
    assert [json.loads(line)["loss"] for line in open(resumed / "metrics.jsonl")] == losses

    for name in ("model.safetensors", "ema.safetensors"):
        saved = load_file(str(run / "final" / name))
        assert "transformer_blocks.0.attn1.to_q.base_layer.weight" in saved
        assert any(torch.count_nonzero(t) for k, t in saved.items() if ".lora_B." in k)   # the adapters trained
        torch.testing.assert_close(load_file(str(resumed / "final" / name)), saved, rtol=0, atol=0)
    model, info = load_world_model(run)
    assert info["weights"] == "ema.safetensors"
    nxt = build_world({"preset": "tiny", "lora_rank": 4, "trainable": "all",
                       "init_weights": str(run / "final" / "ema.safetensors")})
    for k, t in nxt.state_dict().items():
        torch.testing.assert_close(t, model.state_dict()[k], rtol=0, atol=0)


def _stepped(model, lr=1e-3):
    """An AdamW over the trainable parameters after one step (every one of them gets state: the null embeddings
    get a zero gradient)."""
    params = [p for p in model.parameters() if p.requires_grad]
    opt = torch.optim.AdamW(params, lr=lr)
    (model(*_reference()[0]).square().mean() + 0 * sum(p.sum() for p in params)).backward()
    opt.step()
    return opt


def test_pre_peft_dcp_checkpoint_resumes_under_the_new_names(tmp_path):
    """A DCP checkpoint of a LoRA run written before peft (model, optimizer and EMA state under the old names)
    loads into the peft model through ``legacy_name`` (what ``Trainer._load`` passes). The old names are pinned by
    the pre-peft fixture's keys; a run of the old code resumed this way logged bitwise its uninterrupted losses."""
    from torch.distributed.checkpoint.state_dict import get_state_dict, set_state_dict

    from resim.train import checkpoint as ckpt
    from resim.models.world.lora import pre_peft_name

    def trained():
        torch.manual_seed(0)
        m = build_world({**V1_MODEL, "init_weights": str(V1 / "model.safetensors")})
        return m, _stepped(m)

    model, opt = trained()
    msd, osd = get_state_dict(model, opt)
    ema = {n: p.detach().clone() for n, p in model.named_parameters() if p.requires_grad}
    current = {"model": msd, "optim": osd, "ema": ema}
    old = ckpt._renamed(current, pre_peft_name)
    assert set(old["model"]) == set(load_file(str(V1 / "model.safetensors")))
    assert any(k.endswith(".lora_A") for k in old["optim"]["state"]) and any(k.endswith(".lora_B") for k in old["ema"])
    path = ckpt.save(tmp_path, 2, old, rank_state={}, meta={}, rank=0, barrier=lambda: None)

    fresh = build_world(V1_MODEL)
    fresh_opt = _stepped(fresh, lr=5e-4)   # state to load into, as a resumed run has it; its lr is replaced
    msd2, osd2 = get_state_dict(fresh, fresh_opt)
    state = {"model": msd2, "optim": osd2, "ema": {n: torch.zeros_like(t) for n, t in ema.items()}}
    with pytest.raises(ckpt.CheckpointError, match="RuntimeError: Missing key"):   # without the old names: not read
        ckpt.load(path, state, rank=0)
    ckpt.load(path, state, rank=0, legacy_name=pre_peft_name)
    set_state_dict(fresh, fresh_opt, model_state_dict=state["model"], optim_state_dict=state["optim"])
    for k, t in model.state_dict().items():
        torch.testing.assert_close(fresh.state_dict()[k], t, rtol=0, atol=0, msg=k)
    for k, t in ema.items():
        torch.testing.assert_close(state["ema"][k], t, rtol=0, atol=0, msg=k)
    want, got = get_state_dict(model, opt)[1], get_state_dict(fresh, fresh_opt)[1]
    assert want["param_groups"] == got["param_groups"] and set(want["state"]) == set(got["state"])
    for k, s in want["state"].items():
        for name, t in s.items():
            torch.testing.assert_close(got["state"][k][name], t, rtol=0, atol=0, msg=f"{k}.{name}")
