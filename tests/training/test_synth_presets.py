"""The synthetic world's named world-model presets resolve to valid configs, and the shipped model's recipe is
the one its card names: `resim train world --preset synth-fork-plan` gives the objective, learning rate and step
count that configs/models/synth-world (stage 9, with stage 8b's recipe; docs/models/synth-world.md) was trained with."""
import pytest
import yaml

from resim.config import from_dict
from resim.diffusion.config import ObjectiveConfig
from resim.shipped import SYNTH_WORLD, shipped_dir
from resim.train.presets import WORLD_PRESETS
from resim.train.run import resolve_config


@pytest.mark.parametrize("preset", [p for p in WORLD_PRESETS if p.startswith("synth")])
def test_synth_world_presets_resolve_to_valid_objectives(preset):
    cfg = resolve_config("world", preset)
    objective = from_dict(ObjectiveConfig, cfg.model["objective"])
    # the from-scratch recipe trains with Diffusion Forcing (configs/train/world/synth-world.yaml); the stage
    # chain's presets with ReSim's history noise
    assert objective.noise_mode == ("diffusion_forcing" if preset == "synth-world" else "resim_cond_aug")


def test_synth_fork_plan_reproduces_the_shipped_world_models_recipe():
    shipped = yaml.safe_load((shipped_dir(SYNTH_WORLD) / "config.yaml").read_text())
    assert shipped["preset"] == "synth-fork-plan"
    cfg = resolve_config("world", "synth-fork-plan")
    assert cfg.model["objective"] == shipped["model"]["objective"]
    assert (cfg.optim.lr, cfg.trainer.steps, cfg.data.batch_size_per_gpu) == (
        shipped["optim"]["lr"], shipped["trainer"]["steps"], shipped["data"]["batch_size_per_gpu"])
    # stages 4a-4c: the command the only condition (on a fork clip the trajectory would say which branch it is)
    fork = from_dict(ObjectiveConfig, resolve_config("world", "synth-fork").model["objective"])
    assert fork.trajectory_drop_prob == 1.0 and fork.action_drop_prob == 1.0 and 0 < fork.text_drop_prob < 0.5
    # stage 5: the trajectory and the command each half the time, independently, so a quarter of the CARLA-layout
    # fork clips have only the trajectory to tell the branches apart; never per-frame actions (ReSim's encoder only)
    traj = from_dict(ObjectiveConfig, resolve_config("world", "synth-fork-traj").model["objective"])
    assert traj.trajectory_drop_prob == traj.text_drop_prob == 0.5 and traj.action_drop_prob == 1.0
    assert traj.trajectory_keep_sources == () and traj.cond_aug_max_t == fork.cond_aug_max_t
    # stages 8b and 9 (shipped): the plan kept on 90 % of the clips that carry one, the command still half the time
    plan = from_dict(ObjectiveConfig, cfg.model["objective"])
    assert plan.trajectory_drop_prob == 0.1 and plan.text_drop_prob == 0.5 and plan.action_drop_prob == 1.0
    assert plan.trajectory_keep_sources == () and plan.cond_aug_max_t == fork.cond_aug_max_t
