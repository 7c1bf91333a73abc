"""Counterfactual branches: a rollout is scored by the recorded sibling future it lands on (no labeler)."""
import numpy as np
import pytest
import torch

from resim.eval.branches import (branch_matching, counterfactual_groups, format_branches, sibling_trajectory_requests,
                                    trajectory_groups)
from resim.eval.command_following import trajectory_branch_eval
from resim.eval.worldeval import EvalClip
from resim.shards.schema import COMMANDS

LEVEL = {c: float(k - 1) for k, c in enumerate(COMMANDS)}          # left -1, forward 0, right +1


def _forks(histories=3, commands=COMMANDS, f=4):
    """``histories`` forks, each recorded once under every command: same history frames, future latents the
    command's constant plus posterior-like noise."""
    rng = np.random.default_rng(0)
    clips, rec = [], []
    for hi in range(histories):
        for c in commands:
            frames = np.full((9, 8, 8, 3), hi, np.uint8)
            lat = rng.normal(0, 0.3, (3 + f, 2, 2, 2)).astype(np.float32)
            lat[3:] += LEVEL[c]
            clips.append(EvalClip(f"h{hi}-{c}", f"ep{hi}-{c}", lat, frames, None, c, 9, 10.0, False))
            rec.append(lat[3:])
    return clips, np.stack(rec)


def test_a_model_that_follows_the_command_lands_on_its_branch_and_one_that_ignores_it_does_not():
    clips, rec = _forks()
    groups = counterfactual_groups(clips)
    assert len(groups) == 3 and all(len(g) == 3 for g in groups)
    cmds = [c.command for c in clips]
    rng = np.random.default_rng(1)
    noisy = lambda v: np.full(rec.shape, v, np.float32) + rng.normal(0, 0.3, rec.shape).astype(np.float32)
    follows = {c: noisy(LEVEL[c]) for c in COMMANDS}
    follows["null"] = noisy(0.0)
    rep = branch_matching(follows, rec, cmds, groups, null_key="null")
    assert rep["commanded"]["accuracy"] == 1.0 and rep["commanded"]["n"] == 27     # 3 histories x 3 siblings x 3
    assert rep["chance"] == pytest.approx(1 / 3)
    assert rep["null_prompt"]["accuracy"] == pytest.approx(1 / 3)                  # always lands on "forward"
    assert rep["mean_distance"]["own_branch"] < rep["mean_distance"]["other_branches"]
    # the same futures whatever the command (a model that ignores it): always the same branch, chance
    ignores = {c: noisy(1.0) for c in COMMANDS}
    r = branch_matching(ignores, rec, cmds, groups)
    assert r["commanded"]["matrix"] == [[0, 0, 9], [0, 0, 9], [0, 0, 9]] and r["commanded"]["accuracy"] == pytest.approx(1 / 3)
    # turns swapped: every turn lands on the opposite branch
    swapped = {"Turning left": follows["Turning right"], "Moving forward": follows["Moving forward"],
               "Turning right": follows["Turning left"]}
    assert branch_matching(swapped, rec, cmds, groups)["commanded"]["accuracy"] == pytest.approx(1 / 3)
    assert "counterfactual branches (3 shared histories" in format_branches(rep)


def test_only_the_commands_a_fork_recorded_are_asked_and_chance_follows():
    clips, rec = _forks(2, commands=COMMANDS[:2])                  # forks of two branches: chance 1/2
    groups = counterfactual_groups(clips)
    gen = {c: np.full(rec.shape, LEVEL[c], np.float32) for c in COMMANDS}
    rep = branch_matching(gen, rec, [c.command for c in clips], groups)
    assert rep["chance"] == 0.5 and rep["commanded"]["n"] == 8 and rep["commanded"]["accuracy"] == 1.0
    assert rep["commanded"]["per_command"]["Turning right"] is None
    with pytest.raises(ValueError, match="no counterfactual groups"):
        branch_matching(gen, rec, [c.command for c in clips], [])


class _TrajectoryFollower:
    """Stands in for WorldRollouts: the generated future is the level its trajectory carries (or, with
    ``follows=False``, always the straight branch), plus noise; records what it was asked."""

    def __init__(self, follows=True):
        self.follows, self.asked = follows, []

    def generate_latents(self, clips, trajectories, commands, offset=0, num_future_latents=None):
        self.asked += list(zip(trajectories, commands))
        rng = np.random.default_rng(len(self.asked))
        out = np.stack([c.latents.copy() for c in clips])
        for k, t in enumerate(trajectories):
            out[k, 3:] = (float(t[0, 0]) if self.follows else 0.0) + rng.normal(0, 0.3, out[k, 3:].shape)
        return torch.from_numpy(out)


def _forks_with_trajectories(histories=3):
    clips, rec = _forks(histories)
    clips = [EvalClip(c.key, c.item_id, c.latents, c.frames, np.full((8, 3), LEVEL[c.command], np.float32),
                      c.command, 9, 10.0, False) for c in clips]
    return clips, rec


def test_trajectory_branches_land_where_the_siblings_trajectory_points_and_the_command_is_withheld():
    clips, rec = _forks_with_trajectories()
    clips.append(EvalClip("z-lone", "ep-lone", clips[0].latents, np.full((9, 8, 8, 3), 99, np.uint8),
                          None, "Turning left", 9, 10.0, False))               # no fork, no trajectory: not asked
    groups = counterfactual_groups(clips)
    null = np.zeros((len(clips),) + rec.shape[1:], np.float32)                  # the null prompt: straight on
    runner = _TrajectoryFollower()
    rep = trajectory_branch_eval(runner, clips, groups, null, h=3)
    assert len(runner.asked) == 27 and all(c is None for _, c in runner.asked)  # 9 clips x 3 siblings, null prompt
    assert rep["commanded"]["accuracy"] == 1.0 and rep["clips"] == 9 and rep["histories"] == 3
    assert rep["null_prompt"]["accuracy"] == pytest.approx(1 / 3)
    ignores = trajectory_branch_eval(_TrajectoryFollower(follows=False), clips, groups, null, h=3)
    assert ignores["commanded"]["accuracy"] == pytest.approx(1 / 3)
    assert "trajectory given" in format_branches(rep, given="trajectory given")


def test_forks_without_trajectories_are_left_out_of_the_trajectory_branches():
    clips, rec = _forks(2)                                                      # OpenDV-like: no trajectories
    groups = counterfactual_groups(clips)
    assert trajectory_groups(clips, groups) == []
    rep = trajectory_branch_eval(_TrajectoryFollower(), clips, groups, np.zeros_like(rec), h=3)
    assert "skipped" in rep and "trajectory" in rep["skipped"]
    # a fork with one sibling lacking its trajectory is left out whole: its branches could not all be named
    tclips, _ = _forks_with_trajectories(2)
    tclips[0] = EvalClip(tclips[0].key, tclips[0].item_id, tclips[0].latents, tclips[0].frames, None,
                         tclips[0].command, 9, 10.0, False)
    assert trajectory_groups(tclips, counterfactual_groups(tclips)) == [[3, 4, 5]]
    assert len(sibling_trajectory_requests(tclips, [[3, 4, 5]])) == 9


def test_the_swap_test_reads_the_condition_through_a_pull_that_defeats_nearest_branch_scoring():
    clips, rec = _forks()
    groups = counterfactual_groups(clips)
    cmds = [c.command for c in clips]
    rng = np.random.default_rng(2)
    noise = lambda: rng.normal(0, 0.05, rec.shape).astype(np.float32)
    # every rollout pulled 80 % of the way to the left branch, but still moved 20 % towards its own
    pulled = {c: (0.8 * LEVEL["Turning left"] + 0.2 * LEVEL[c]) + noise() for c in COMMANDS}
    rep = branch_matching(pulled, rec, cmds, groups)
    assert rep["commanded"]["accuracy"] == pytest.approx(1 / 3)        # nearest sibling: always "left"
    sw = rep["swap_test"]
    assert sw["accuracy"] == 1.0 and sw["n"] == 27 and sw["left_right"]["n"] == 9    # 9 clips x 3 pairs
    assert sw["histories_above_chance"] == 3 and sw["mean_cosine"] > 0.5
    # blind to the condition, same noise for every command (as commands_eval draws it): all ties, exactly chance
    same = noise()
    blind = {c: 0.7 + same for c in COMMANDS}
    sb = branch_matching(blind, rec, cmds, groups)["swap_test"]
    assert sb["accuracy"] == 0.5 and sb["mean_cosine"] == 0.0 and sb["histories_above_chance"] == 0
    # blind, independent noise per command: near chance, not above it
    indep = {c: 0.7 + rng.normal(0, 0.3, rec.shape).astype(np.float32) for c in COMMANDS}
    assert abs(branch_matching(indep, rec, cmds, groups)["swap_test"]["mean_cosine"]) < 0.2
    # turns swapped: every left/right pair wrong
    swapped = {"Turning left": pulled["Turning right"], "Moving forward": pulled["Moving forward"],
               "Turning right": pulled["Turning left"]}
    assert branch_matching(swapped, rec, cmds, groups)["swap_test"]["left_right"]["accuracy"] == 0.0
    assert "swap test" in format_branches(rep)
