"""`resim eval closed-loop`'s parts (resim/eval/policy_ranking.py, idm_proxy.py, closed_loop_report.py): the IDM
proxy chains 4-s windows into one path, a path scored on the map gives the expert 100 and a path off the lane
less, the rank agreement reads Spearman's rho with a bootstrap over states, and the replay drives the world model
with the true loop's plans."""
from pathlib import Path

import numpy as np
import pytest
import torch

from resim.config import from_dict
from resim.eval.drive import itinerary
from resim.eval.idm_proxy import idm_path, path_score
from resim.eval.policy_ranking import (ClosedLoopConfig, ReplayPlans, closed_loop_eval, extra_policy_names,
                                       rank_agreement, reward_score, starting_states)
from resim.eval.policy_ranking_report import format_closed_loop
from resim.eval.simulate_policy import reward_over_time
from resim.media.encoders import VideoVAE
from resim.models.idm import IDMConfig
from resim.models.reward.config import RewardModelConfig
from resim.models.reward.model import Video2Reward
from resim.sample.reward_score import score_videos
from resim.sample.rollout import RolloutConfig
from resim.sample.simulate import WorldModelLoop
from resim.synthworld.closed_loop import Observation, drive
from resim.synthworld.drivers import simulate
from resim.synthworld.policies import ConstantVelocity, SteeringBias
from resim.train.tasks.world_model import build_world

VAE_DIR = Path(__file__).resolve().parents[2] / "configs/models/placeholder-cogvideox-vae-tiny"
TINY_REWARD = {"num_frames": 4, "frame_step": 2, "head_dim": 32, "num_heads": 2, "mlp_hidden_dim": 32}


class StraightIDM(torch.nn.Module):
    """Reads 2 m forward per 0.5 s whatever it sees, and counts its windows."""

    def __init__(self):
        super().__init__()
        self.cfg = IDMConfig(input_hw=(16, 24), channels=(8, 16))
        self.w = torch.nn.Parameter(torch.zeros(1))
        self.calls = 0

    def forward(self, video):
        self.calls += 1
        assert video.shape[1:3] == (21, 3)
        t = torch.arange(1, 9, dtype=torch.float32)
        return torch.stack([2.0 * t, 0 * t, 0 * t], -1)[None].expand(video.shape[0], -1, -1)


def test_the_idm_proxy_chains_windows_into_one_path():
    idm = StraightIDM()
    frames = np.zeros((9 + 80 + 1, 32, 48, 3), np.uint8)           # history, 8 s, and the last window's end
    path = idm_path(idm, frames, 8, 10.0, (32, 48))
    assert idm.calls == 2 and path.shape == (17, 3)
    assert np.allclose(path[:, 0], np.arange(17) * 2.0) and np.allclose(path[:, 1:], 0)
    # a partial last window is read from the window ending at the last frame; only its new part is kept
    idm.calls = 0
    path = idm_path(idm, frames[:9 + 60 + 1], 8, 10.0, (32, 48))
    assert idm.calls == 2 and path.shape == (13, 3) and np.allclose(np.diff(path[:, 0]), 2.0)


def test_a_path_on_the_map_scores_the_expert_100_and_a_drift_less():
    cfg = ClosedLoopConfig(states=3)
    st = starting_states(cfg)[1]
    ex = simulate(st.world, 8.8, 20.0, np.random.default_rng(0), "expert")
    start = ex.poses[16]
    c, s = np.cos(start[2]), np.sin(start[2])
    rel = ex.poses[16::10] - start
    ego = np.c_[c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1], rel[:, 2]]
    progress = float(ex.route_s_m[-1] - ex.route_s_m[16])
    good = path_score(st.world, start, ego, progress)
    assert good["inside"] == 1.0 and good["score"] > 95 and good["max_dev_m"] < 1.0
    drift = ego + np.c_[0 * ego[:, 0], np.linspace(0, 8, len(ego)), 0 * ego[:, 0]]   # 8 m to the left by the end
    bad = path_score(st.world, start, drift, progress)
    assert bad["inside"] < 0.8 and bad["score"] < good["score"]


def test_a_policy_run_named_like_a_row_gets_its_own_row():
    # a run folder called "policy" beside the graded "policy" row once replaced that row's policy, silently
    taken = ["policy", "constant velocity"]
    assert extra_policy_names(taken, ["runs/policy-1-epoch"]) == ["policy-1-epoch"]
    assert extra_policy_names(taken, ["runs/policy", "runs/b/twin", "runs/c/twin"]) == ["runs/policy", "twin",
                                                                                         "runs/c/twin"]
    with pytest.raises(ValueError, match="given twice"):
        extra_policy_names(taken, ["runs/twin", "runs/twin"])
    with pytest.raises(ValueError, match="exists already"):   # a folder "policy" in the working dir
        extra_policy_names(taken, ["policy"])


def test_rank_agreement():
    true = np.array([[90, 80, 100.0], [50, 40, 60], [10, 20, 5]])
    rep = rank_agreement(true, true * 0.5 + 3, ["a", "b", "c"], bootstrap=200)
    assert rep["spearman"] == pytest.approx(1.0) and rep["largest_disagreements"] == []
    flipped = rank_agreement(true, true[::-1], ["a", "b", "c"], bootstrap=200)
    assert flipped["spearman"] == pytest.approx(-1.0) and set(flipped["largest_disagreements"]) == {"a", "c"}
    assert flipped["per_policy"]["a"]["model_rank"] == 3 and flipped["ci95"][1] <= -0.4


def test_starting_states_are_seeded_fork_worlds():
    a, b = starting_states(ClosedLoopConfig(states=3)), starting_states(ClosedLoopConfig(states=3))
    assert [s.name for s in a] == ["s5000-0-left", "s5000-1-straight", "s5000-2-right"]
    assert np.array_equal(a[2].world.route.xy, b[2].world.route.xy) and a[2].world.fork["branch"] == "right"
    with pytest.raises(ValueError, match="seconds"):
        ClosedLoopConfig(seconds=2.0)


def test_video2reward_scores_a_drive_over_time_one_window_per_second(one_torch_thread):
    reward = Video2Reward(from_dict(RewardModelConfig, TINY_REWARD)).eval()
    frames = np.random.default_rng(0).integers(0, 255, (9 + 40, 32, 48, 3), dtype=np.uint8)
    pts = reward_over_time(reward, frames, first=8, fps_hz=10.0)
    assert [p["t_s"] for p in pts] == [1.0, 2.0, 3.0, 4.0]
    # each point is the window of 7 frames ending one second after the previous one
    direct = score_videos(reward, [frames[19 - 7 + k * 10:19 + k * 10] for k in range(4)])
    assert np.allclose([p["score"] for p in pts], direct, atol=1e-4) and all(0 < p["score"] < 1 for p in pts)
    assert reward_over_time(reward, frames[:14], first=8, fps_hz=10.0) == []   # no second after the history yet
    # a drive cut short (a collision ends a true episode) holds its last frame up to one window
    held = np.concatenate([frames[8:12], np.repeat(frames[11:12], 3, axis=0)])
    assert reward_score(reward, frames[:12], 8, "short") == pytest.approx(100 * score_videos(reward, [held])[0], abs=1e-3)


def test_the_closed_loop_reads_each_drive_with_video2reward_too(one_torch_thread):
    """True world only: both readings (IDM proxy, Video2Reward) of every drive, and a rank agreement for each."""
    reward = Video2Reward(from_dict(RewardModelConfig, TINY_REWARD)).eval()
    cfg = ClosedLoopConfig(states=2, seconds=4.0, bootstrap=20)
    policies = {"cv": ConstantVelocity(), "cv + bias": SteeringBias(ConstantVelocity(), 0.1)}
    rep = closed_loop_eval(policies, cfg, StraightIDM(), (64, 96), reward=reward)
    assert {"proxy_vs_true_on_true_frames", "reward_vs_true_on_true_frames"} <= set(rep)
    assert "world_model_vs_true" not in rep and "world_model_reward_vs_true" not in rep
    assert len(rep["rows"]) == 4 and all(0 < row["true_frames_reward"] < 100 for row in rep["rows"])
    # the biased drive leaves the lane in the true world: the true score ranks it last
    assert rep["reward_vs_true_on_true_frames"]["per_policy"]["cv + bias"]["true_rank"] == 2
    assert "V2R, true frames" in format_closed_loop(rep)


def test_replay_answers_the_recorded_plan_of_each_decision_and_standstill_after_a_drive_ended():
    plans = [(0.8 + 0.4 * k, np.full((8, 3), float(k))) for k in range(3)]
    rp = ReplayPlans(plans, 0.4)
    obs = lambda t: Observation(frames=np.zeros((1, 4, 4, 3), np.uint8), speed_mps=5.0, t_s=t)  # noqa: E731
    assert np.array_equal(rp(obs(0.8)), plans[0][1]) and np.array_equal(rp(obs(1.6000001)), plans[2][1])
    assert np.array_equal(rp(obs(2.0)), np.zeros((8, 3)))            # the recorded drive had ended
    with pytest.raises(ValueError, match="no recorded plan near t = 0.40"):
        rp(obs(0.4))


class LooksAtFrames:
    """Steers by the brightness of the last frame it sees: acts differently on different frames."""

    def __call__(self, obs):
        y = float(obs.frames[-1].mean()) / 255.0 * 4.0 - 2.0
        return np.c_[np.arange(1, 9) * 4.0, np.full(8, y), np.zeros(8)]


def test_replay_drives_the_world_model_with_the_true_loops_plans(one_torch_thread):
    """The replay batch is conditioned on the true drive's plans, decision by decision; a policy that ignores its
    frames acts alike in both loops (plan gap 0), one that reads them does not."""
    vae = VideoVAE(VAE_DIR, device="cpu")
    batches = []

    class SpyLoop(WorldModelLoop):
        def run_batch(self, *a, **kw):
            batches.append(super().run_batch(*a, **kw))
            return batches[-1]

    torch.manual_seed(0)
    loop = SpyLoop(build_world({"preset": "tiny"}).eval(), vae, lambda c: torch.zeros(1, 3, 64),
                   RolloutConfig(num_steps=2, history_frames=3))
    cfg = ClosedLoopConfig(states=2, seconds=4.0, bootstrap=20)
    fixed = lambda obs: np.c_[np.arange(1, 9) * 4.0, np.zeros(8), np.zeros(8)]  # noqa: E731
    policies = {"fixed": fixed, "looks": LooksAtFrames()}
    rep = closed_loop_eval(policies, cfg, StraightIDM(), (32, 48), loop=loop, vae=vae, replay=True)
    assert len(batches) == 4                                       # per state: the closed loop, then the replay
    st = starting_states(cfg)[0]
    total = cfg.history_s + cfg.seconds + 0.1
    true = drive(st.world, policies["looks"], st.renderer(cfg), cfg.loop_cfg(total), "looks",
                 command_at=itinerary(st.world, total, cfg.sim_hz))
    replayed = batches[1][1].plans
    assert len(replayed) == 10 and len(true.plans) >= 10
    for (t, plan), (t_true, plan_true) in zip(replayed, true.plans):
        assert t == pytest.approx(t_true) and np.array_equal(plan, plan_true)
    closed = batches[0][1].plans                                   # the policy on the world model's own frames
    assert not all(np.array_equal(a, b) for (_, a), (_, b) in zip(closed, true.plans))
    assert rep["gaps"]["fixed"]["plan_gap_m"] == 0.0 and rep["gaps"]["looks"]["plan_gap_m"] > 0.05
    assert all(r["replay_idm_proxy"]["path_gap_m"] >= 0 for r in rep["rows"])
    assert "replay_vs_true" in rep and "proxy, WM replay" in format_closed_loop(rep)
    with pytest.raises(ValueError, match="replay needs the world model"):
        closed_loop_eval(policies, cfg, StraightIDM(), (32, 48), replay=True)
