"""Guidance + step distillation (resim/train/tasks/distill.py, `resim train distill`): the student learns the teacher's guided
many-step output in a few unguided steps, its export samples like any world model at its own step count, and the
teacher's trajectories depend on each clip's key alone (so a resumed run makes the same pairs)."""
import json

import numpy as np
import pytest
import torch
import yaml
from safetensors.torch import save_file

from resim.cli import main
from resim.config import ConfigError, from_dict
from resim.diffusion.ddim import DDIMSchedule
from resim.diffusion.guidance import guidance_preset
from resim.models.world.config import preset
from resim.models.world.dit import WorldModel
from resim.sample.load import load_world_model, resolve_steps_and_guidance, sampling_defaults
from resim.sample.rollout import Condition, RolloutConfig, rollout
from resim.train.config import DataConfig
from resim.train.data import StreamLoader
from resim.train.tasks.distill import DistillConfig, TeacherPairs, build_distill
from tests.support.training import write_world_dataset

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """8 tiny clips (3 + 10 latent frames) and a random tiny world model exported as a teacher."""
    root = tmp_path_factory.mktemp("distill")
    data = write_world_dataset(root / "data", num_samples=8, per_shard=4)
    torch.manual_seed(0)
    wm = WorldModel(preset("tiny"))
    final = root / "teacher" / "final"
    final.mkdir(parents=True)
    (final / "config.yaml").write_text(yaml.safe_dump({"model_name": "world", "model": {"preset": "tiny"}}))
    save_file({k: v.contiguous() for k, v in wm.state_dict().items()}, str(final / "model.safetensors"))
    return {"root": root, "data": data, "teacher": root / "teacher"}


def _batch(data, n=8):
    dl = StreamLoader(from_dict(DataConfig, {"shards": str(data), "batch_size_per_gpu": n, "num_workers": 0}),
                      verbose=False)
    return next(iter(dl))


def _student_error(model, pairs, batch, x0, steps):
    """Mean squared distance of ``model``'s unguided ``steps``-step rollouts to the teacher's guided output, from the
    same starting noise and conditions as the teacher's trajectories."""
    rc = RolloutConfig(num_steps=steps, history_frames=3, frames_per_round=10, chunk_frames=10,
                       guidance=guidance_preset("none"))
    errs = []
    for i, key in enumerate(batch.keys):
        null, keep, seed = pairs.draws(key, bool(batch.has_trajectory[i]))
        text = batch.null_text[i:i + 1] if null else batch.text[i:i + 1]
        res = rollout(model, batch.latents[i:i + 1, :3].float(), Condition(
            text=text, trajectory=batch.trajectory[i:i + 1] if keep else None), 10, rc, seeds=[seed])
        errs.append(float(((res.future - x0[i:i + 1]) ** 2).mean()))
    return float(np.mean(errs))


def test_schedule_stops_at_the_student_levels():
    sched = DDIMSchedule(50, include=(749, 499, 249))
    assert len(sched) == 52 and {749, 499, 249} <= set(sched.timesteps)    # 499 is on the 50-step grid already
    assert sched.timesteps == sorted(sched.timesteps, reverse=True) and sched.steps[-1].t_prev == -1
    assert DDIMSchedule(40, include=(749, 499, 249)).timesteps == DDIMSchedule(40).timesteps   # already on the grid
    with pytest.raises(ValueError, match="not in"):
        DDIMSchedule(4, include=(1000,))


def test_teacher_pairs_depend_on_the_clip_alone(world):
    teacher, _ = load_world_model(world["teacher"])
    cfg = DistillConfig(teacher=world["teacher"], student_steps=2, teacher_steps=8)
    batch = _batch(world["data"], 4)
    together = TeacherPairs(teacher, cfg)
    st, x0, null, keep = together.get(batch, 3)
    assert st.shape == (4, 2, 10, 16, 8, 12) and x0.shape == (4, 10, 16, 8, 12)
    alone = TeacherPairs(teacher, cfg)
    sub = _batch(world["data"], 4)
    # the last clip of the batch, rolled out on its own, gets the same trajectory
    one = type(sub)(**{**sub.__dict__, "latents": sub.latents[3:], "prompt_index": sub.prompt_index[3:],
                       "null_index": sub.null_index[3:], "trajectory": sub.trajectory[3:],
                       "has_trajectory": sub.has_trajectory[3:], "command": sub.command[3:],
                       "source": sub.source[3:], "keys": sub.keys[3:], "meta": sub.meta[3:]})
    st1, x01, _, _ = alone.get(one, 3)
    torch.testing.assert_close(st1[0], st[3], atol=1e-3, rtol=1e-3)    # float16 cache
    torch.testing.assert_close(x01[0], x0[3], atol=1e-3, rtol=1e-3)
    # the first recorded state is the starting noise, the last output is the guided teacher rollout's
    null3, keep3, seed3 = together.draws(batch.keys[3], bool(batch.has_trajectory[3]))
    gen = torch.Generator().manual_seed(seed3)
    noise = torch.randn((10, 16, 8, 12), generator=gen)
    torch.testing.assert_close(st[3, 0], noise, atol=2e-3, rtol=1e-3)
    assert together.made == len(set(batch.keys)) and alone.made == 1   # a key twice in a batch: rolled out once


def test_distilled_student_follows_the_teacher_in_few_steps(world, capsys):
    """The effect: 40 steps of distillation bring the student's 2 unguided steps at least twice as close to the
    teacher's 8 guided steps as the teacher's own 2 unguided steps are; the export samples at 2 steps."""
    run = world["root"] / "run"
    assert main(["train", "distill", "--preset", "tiny", "--shards", str(world["data"]), "--out", str(run),
                 "--set", f"model.teacher={world['teacher']}", "--set", "trainer.steps=40",
                 "--set", "trainer.progress_bar=false"]) == 0
    teacher, _ = load_world_model(world["teacher"])
    student, info = load_world_model(run)
    assert info["model_name"] == "world"                        # a plain world-model export
    cfg = DistillConfig(teacher=world["teacher"], student_steps=2, teacher_steps=8)
    pairs = TeacherPairs(teacher, cfg)
    batch = _batch(world["data"])
    _, x0, _, _ = pairs.get(batch, 3)
    before = _student_error(teacher, pairs, batch, x0, 2)
    after = _student_error(student, pairs, batch, x0, 2)
    assert after < 0.5 * before, (before, after)
    logs = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert logs[-1]["teacher_clips"] <= 8                       # each of the 8 clips rolled out once at most

    d = sampling_defaults(run)
    assert d["num_steps"] == 2 and d["guidance"] == "none" and d["teacher_steps"] == 8
    assert (run / "final" / "distill.yaml").is_file()
    # the samplers take the student's steps and no guidance unless told otherwise
    assert resolve_steps_and_guidance(run, None, "resim", False, None)[:2] == (2, "none")
    assert resolve_steps_and_guidance(run, 6, "resim", False, 3.0)[:2] == (6, "resim")
    assert resolve_steps_and_guidance(world["teacher"], None, "resim", False, None)[:2] == (None, "resim")
    out = world["root"] / "sample"
    key = batch.keys[0]
    assert main(["sample", "--checkpoint", str(run), "--shards", str(world["data"]), "--history", key,
                 "--command", "Turning left", "--seconds", "1.2", "--device", "cpu", "--out", str(out)]) == 0
    ro = yaml.safe_load((out / "rollout.yaml").read_text())
    assert ro["num_steps"] == 2 and ro["guidance"]["enabled"] is False
    assert "distilled student" in capsys.readouterr().err


def test_bad_distill_configs(world, tmp_path):
    with pytest.raises(ConfigError, match="teacher is required"):
        DistillConfig()
    with pytest.raises(ConfigError, match="student_steps"):
        DistillConfig(teacher=world["teacher"], student_steps=8, teacher_steps=8)
    with pytest.raises(ConfigError, match="model.teacher"):
        build_distill({"teacher": str(tmp_path / "nowhere")})
    student = tmp_path / "student" / "final"
    student.mkdir(parents=True)
    (student / "config.yaml").write_text(yaml.safe_dump({"model_name": "world", "model": {"preset": "tiny"},
                                                         "sampling": {"num_steps": 2, "guidance": "none"}}))
    (student / "model.safetensors").write_bytes((world["teacher"] / "final" / "model.safetensors").read_bytes())
    with pytest.raises(ConfigError, match="already a distilled student"):
        build_distill({"teacher": str(tmp_path / "student")})


def test_resumed_distillation_equals_an_uninterrupted_one(world, tmp_path):
    """The pairs are remade after a resume (the cache is not checkpointed): seeded by each clip's key, they are the
    same, so 6 + 6 steps end where 12 steps do."""
    from safetensors.torch import load_file

    def run(out, steps, resume=False):
        assert main(["train", "distill", "--preset", "tiny", "--shards", str(world["data"]), "--out", str(out),
                     "--set", f"model.teacher={world['teacher']}", "--steps", str(steps),
                     "--checkpoint-every", "6", "--set", "trainer.progress_bar=false",
                     *(["--resume"] if resume else [])]) == 0
        return load_file(str(out / "final" / "model.safetensors"))

    whole = run(tmp_path / "a", 12)
    run(tmp_path / "b", 6)
    resumed = run(tmp_path / "b", 12, resume=True)
    for k in whole:
        torch.testing.assert_close(resumed[k], whole[k], rtol=0, atol=0, msg=k)


def test_dry_run_builds_the_student_on_the_meta_device(world):
    """`resim train launch --dry-run` builds models on the meta device: the student's shape only, no teacher."""
    m = build_distill({"teacher": str(world["teacher"])}, device="meta")
    assert all(p.device.type == "meta" for p in m.parameters())
    assert sum(p.numel() for p in m.parameters()) == sum(p.numel() for p in WorldModel(preset("tiny")).parameters())


def test_a_teacher_without_a_trajectory_encoder_is_distilled_without_trajectories(world, tmp_path):
    """The clips carry trajectories, the teacher takes none: neither the teacher's rollouts nor the student's loss
    may feed them (the model refuses a trajectory it has no encoder for)."""
    wm = WorldModel(preset("tiny", trajectory={"enabled": False}))
    final = tmp_path / "t" / "final"
    final.mkdir(parents=True)
    (final / "config.yaml").write_text(yaml.safe_dump({"model_name": "world", "model": {
        "preset": "tiny", "overrides": {"trajectory": {"enabled": False}}}}))
    save_file({k: v.contiguous() for k, v in wm.state_dict().items()}, str(final / "model.safetensors"))
    student = build_distill({"teacher": str(tmp_path / "t"), "student_steps": 2, "teacher_steps": 4})
    batch = _batch(world["data"], 4)
    assert bool(batch.has_trajectory.all())
    loss, _ = student.loss(batch)
    assert torch.isfinite(loss)
