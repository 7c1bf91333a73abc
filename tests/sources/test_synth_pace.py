"""Pace forks of the synthetic world: one history, three futures that differ only in speed."""
import json

import numpy as np
import pytest

from resim.config import ConfigError
from resim.labeling.trajectory import trajectory_from_poses
from resim.pipeline.sources.synth.generate import generate, plan_episodes, preset, render_planned
from resim.synthworld.pace import PACE_BRANCHES, pace_fork
from resim.synthworld.world import build_road

HISTORY_FRAMES = 9


@pytest.mark.parametrize("seed", [3, 11])
def test_branches_share_the_history_frame_for_frame_then_drive_slower_same_faster(seed):
    cfg = preset("demo", height_px=32, width_px=56, pace_fork_fraction=1.0)
    plans = plan_episodes(3, cfg)
    assert [p.pace_branch for p in plans] == list(PACE_BRANCHES) and {p.pace_group for p in plans} == {0}
    assert {p.part for p in plans} == {"carla"}
    drives = {p.pace_branch: render_planned(p, seed, cfg) for p in plans}   # (frames, poses)
    n = min(len(f) for f, _ in drives.values())
    same = [all(np.array_equal(drives["same"][0][k], drives[b][0][k]) for b in PACE_BRANCHES) for k in range(n)]
    split = same.index(False)
    assert all(same[:split]) and not any(same[split:])     # identical up to the split, different from it on
    assert split >= HISTORY_FRAMES
    # a clip whose history ends at the split: the trajectories go the same way, over distances in the order
    # of the speeds (what the world model must read off the trajectory), and by clearly more than the IDM's error
    t = split - 1
    ends = {b: trajectory_from_poses(drives[b][1], t, 10.0)[-1] for b in PACE_BRANCHES}
    dist = {b: float(np.hypot(*ends[b][:2])) for b in PACE_BRANCHES}
    assert dist["slower"] + 5 < dist["same"] < dist["faster"] - 5, dist
    assert max(abs(float(ends[b][2] - ends["same"][2])) for b in PACE_BRANCHES) < np.radians(30)


def test_pace_fork_draws_the_same_whatever_the_branch():
    worlds, states = [], []
    for b in PACE_BRANCHES:
        rng = np.random.default_rng(5)
        worlds.append(pace_fork(build_road(rng, 16.0, 8.0), rng, 16.0, b))
        states.append(rng.bit_generator.state)
    assert all(s == states[0] for s in states)
    assert len({w.pace["split_t_s"] for w in worlds}) == 1
    assert [w.pace["factor"] for w in worlds] == [0.5, 1.0, 1.5]
    with pytest.raises(ValueError, match="pace branch"):
        pace_fork(build_road(np.random.default_rng(5), 16.0, 8.0), np.random.default_rng(5), 16.0, "reverse")


def test_generate_writes_pace_triples_last_and_leaves_the_other_episodes_alone(tmp_path):
    cfg = preset("tiny", episode_s=8.0, height_px=32, width_px=56, pace_fork_fraction=0.75)
    summary = generate(tmp_path / "w", 4, seed=2, cfg=cfg, progress=False)
    gt = json.loads((tmp_path / "w" / "ground_truth.json").read_text())["episodes"]
    assert summary["pace_triples"] == 1 and summary["fork_triples"] == 0
    assert [e["pace"] is None for e in gt] == [True, False, False, False]
    assert [e["pace"]["branch"] for e in gt[1:]] == list(PACE_BRANCHES)
    assert all(e["layout"]["reader"] == "carla" and e["driver"] == "expert" for e in gt[1:])
    plain = generate(tmp_path / "p", 1, seed=2, cfg=preset("tiny", episode_s=8.0, height_px=32, width_px=56),
                     progress=False)
    assert json.loads((tmp_path / "p" / "ground_truth.json").read_text())["episodes"][0]["x_m"] == gt[0]["x_m"]


def test_pace_fork_fraction_is_validated():
    with pytest.raises(ConfigError, match="pace_fork_fraction"):
        preset("tiny", pace_fork_fraction=1.5)
    with pytest.raises(ConfigError, match="pace_fork_fraction"):
        preset("tiny", fork_fraction=0.6, pace_fork_fraction=0.6)
