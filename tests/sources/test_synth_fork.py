"""Counterfactual forks of the synthetic world: one history, three futures, told apart only by the command."""
import json

import numpy as np
import pytest

from resim.config import ConfigError
from resim.labeling.commands import command_from_trajectory
from resim.labeling.config import LabelerConfig
from resim.labeling.trajectory import trajectory_from_poses
from resim.pipeline.sources.synth.generate import generate, plan_episodes, preset, render_planned
from resim.synthworld.fork import FORK_BRANCHES, build_fork_world

HISTORY_FRAMES = 9    # ReSim's clip at 10 Hz: 9 history + 40 future frames


@pytest.mark.parametrize("seed", [3, 11])
def test_branches_share_the_history_frame_for_frame_then_go_left_straight_right(seed):
    cfg = preset("demo", height_px=32, width_px=56, fork_fraction=1.0)
    plans = plan_episodes(3, cfg)
    assert [p.fork_branch for p in plans] == list(FORK_BRANCHES) and {p.fork_group for p in plans} == {0}
    drives = {p.fork_branch: render_planned(p, seed, cfg) for p in plans}   # (frames, poses)
    n = min(len(f) for f, _ in drives.values())
    same = [all(np.array_equal(drives["left"][0][k], drives[b][0][k]) for b in FORK_BRANCHES) for k in range(n)]
    split = same.index(False)          # the first frame where any two branches differ
    assert all(same[:split]) and not any(same[split:])  # identical up to the split, different from it on
    assert split > 3 * 10              # well into the episode: there is a shared history to condition on
    # a ReSim clip whose 9 history frames end just before the split: its future is the branch's, and the
    # trajectory command (what the pipeline labels CARLA/NAVSIM clips with) reads each branch as driven
    t = split - 1
    assert t - HISTORY_FRAMES + 1 >= 0
    read = {b: command_from_trajectory(trajectory_from_poses(drives[b][1], t, 10.0), LabelerConfig())[0]
            for b in FORK_BRANCHES}
    assert read == {"left": "Turning left", "straight": "Moving forward", "right": "Turning right"}
    for b, (_, poses) in drives.items():
        turned = np.degrees(poses[-1, 2] - poses[t, 2])
        assert {"left": turned > 60, "straight": abs(turned) < 30, "right": turned < -60}[b], (b, turned)


def test_one_world_whatever_the_branch():
    worlds = [build_fork_world(np.random.default_rng(4), 16.0, 8.0, b) for b in FORK_BRANCHES]
    a = worlds[0]
    for w in worlds[1:]:
        assert np.array_equal(w.props.xy, a.props.xy) and w.cars == a.cars and w.appearance == a.appearance
        assert all(np.array_equal(r.xy, q.xy) for r, q in zip(w.roads, a.roads))
        assert w.fork["route_s_m"] == a.fork["route_s_m"] and w.fork["centre_xy"] == a.fork["centre_xy"]
    assert [w.fork["branch"] for w in worlds] == list(FORK_BRANCHES)
    assert not np.array_equal(worlds[0].route.xy[-1], worlds[2].route.xy[-1])
    with pytest.raises(ValueError, match="fork branch"):
        build_fork_world(np.random.default_rng(4), 16.0, 8.0, "u-turn")


def test_generate_writes_triples_after_the_ordinary_episodes(tmp_path):
    cfg = preset("tiny", episode_s=6.0, height_px=32, width_px=56, fork_fraction=0.75)
    summary = generate(tmp_path / "w", 4, seed=2, cfg=cfg, progress=False)
    gt = json.loads((tmp_path / "w" / "ground_truth.json").read_text())["episodes"]
    assert summary["fork_triples"] == 1
    assert [e["fork"] is None for e in gt] == [True, False, False, False]
    forks = gt[1:]
    assert [e["fork"]["branch"] for e in forks] == list(FORK_BRANCHES)
    assert {e["fork"]["group"] for e in forks} == {0} and len({e["layout"]["reader"] for e in forks}) == 1
    assert all(e["driver"] == "expert" and 0 < e["fork"]["reach_t_s"] < 6.0 for e in forks)
    # the ordinary episode is the one a run without forks writes
    plain = generate(tmp_path / "p", 1, seed=2, cfg=preset("tiny", episode_s=6.0, height_px=32, width_px=56),
                     progress=False)
    assert plain["fork_triples"] == 0
    assert json.loads((tmp_path / "p" / "ground_truth.json").read_text())["episodes"][0]["x_m"] == gt[0]["x_m"]


def test_fork_fraction_is_validated():
    with pytest.raises(ConfigError, match="fork_fraction"):
        preset("tiny", fork_fraction=1.5)
