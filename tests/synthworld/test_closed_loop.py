"""The closed loop in the true synthetic world (resim/synthworld/closed_loop.py, policies.py): the loop itself drives
the expert's plans as cleanly as the expert, an episode replays exactly, degraded policies score in the order
they were degraded, and a broken plan fails loudly, naming the policy."""
import numpy as np
import pytest

from resim.synthworld.closed_loop import LoopConfig, PolicyError, WaypointFollower, drive
from resim.synthworld.drivers import simulate
from resim.synthworld.policies import ConstantVelocity, RoutePlanner, SteeringBias, SteeringNoise, bend, to_ego_frame
from resim.synthworld.render import Camera, Renderer
from resim.synthworld.score import score_trace
from resim.synthworld.world import build_road

CFG = LoopConfig(seconds=10.0, handover_s=1.0)


def world_and_renderer(i: int):
    rng = np.random.default_rng([91, i])
    world = build_road(rng, CFG.seconds, 8.0, first_turn_sign=1 if i % 2 == 0 else -1)
    return world, Renderer(world, Camera(32, 56, 80.0), np.random.default_rng([91, i, 1]))


@pytest.mark.parametrize("i", [0, 1])
def test_the_expert_plans_followed_in_closed_loop_drive_as_cleanly_as_the_expert(i):
    world, renderer = world_and_renderer(i)
    expert = simulate(world, CFG.seconds, CFG.sim_hz, np.random.default_rng(0), "expert")
    assert score_trace(expert, CFG.sim_hz).score_composed == 100.0
    r = drive(world, RoutePlanner(world), renderer, CFG)
    assert r.score.score_composed > 97.0 and not r.score.names(), (r.score.score_composed, r.score.names())
    assert np.abs(r.trace.lane_dev_m).max() < 1.0
    assert len(r.plans) == int((CFG.seconds - CFG.handover_s) * CFG.replan_hz)
    assert r.frames.shape == (int(CFG.seconds * CFG.fps_hz), 32, 56, 3) and r.frames.dtype == np.uint8
    # the expert's own first 1 s (the handover) is the recorded history: identical poses
    n = int(CFG.handover_s * CFG.sim_hz)
    assert np.allclose(r.trace.poses[:n], expert.poses[:n])


def test_a_deterministic_policy_gives_the_same_episode_twice():
    world, renderer = world_and_renderer(2)
    runs = [drive(world, SteeringNoise(RoutePlanner(world), 0.08, seed=5), renderer, CFG) for _ in range(2)]
    assert np.array_equal(runs[0].trace.poses, runs[1].trace.poses)
    assert np.array_equal(runs[0].frames, runs[1].frames)
    other = drive(world, SteeringNoise(RoutePlanner(world), 0.08, seed=6), renderer, CFG)
    assert not np.array_equal(other.trace.poses, runs[0].trace.poses)


def test_policies_degraded_by_design_score_in_that_order():
    scores = {k: [] for k in ("route", "bias 0.05", "bias 0.1")}
    for i in range(3):
        world, renderer = world_and_renderer(i)
        pols = {"route": RoutePlanner(world), "bias 0.05": SteeringBias(RoutePlanner(world), 0.05),
                "bias 0.1": SteeringBias(RoutePlanner(world), 0.1)}
        for k, p in pols.items():
            scores[k].append(drive(world, p, renderer, CFG).score.score_composed)
        # going straight on leaves the lane wherever the road bends (the expert turns by > 30 degrees)
        expert = simulate(world, CFG.seconds, CFG.sim_hz, np.random.default_rng(0), "expert")
        if np.ptp(expert.poses[:, 2]) > np.radians(30):
            cv = drive(world, ConstantVelocity(), renderer, CFG).score
            assert "outside_route_lanes" in cv.names() and cv.score_composed < 0.5 * scores["route"][-1]
    mean = {k: float(np.mean(v)) for k, v in scores.items()}
    assert mean["route"] > mean["bias 0.05"] > mean["bias 0.1"], mean


def test_a_broken_plan_fails_loudly_naming_the_policy():
    world, renderer = world_and_renderer(0)
    with pytest.raises(PolicyError, match=r"policy wobbly: plan has shape \(3, 2\)"):
        drive(world, lambda obs: np.zeros((3, 2)), renderer, CFG, name="wobbly")
    with pytest.raises(PolicyError, match="non-finite"):
        drive(world, lambda obs: np.full((8, 3), np.nan), renderer, CFG, name="nan")
    with pytest.raises(ValueError, match="privileged"):
        RoutePlanner(world)(type("O", (), {"pose": None})())
    with pytest.raises(ValueError, match="must divide sim_hz"):
        LoopConfig(fps_hz=3.0)


def test_the_policy_sees_the_last_frames_and_the_speedometer():
    world, renderer = world_and_renderer(0)
    seen = []

    def spy(obs):
        seen.append((obs.frames.shape, obs.speed_mps, obs.t_s))
        return ConstantVelocity()(obs)

    r = drive(world, spy, renderer, LoopConfig(seconds=3.0, handover_s=1.0, history_frames=4))
    assert seen[0][0] == (4, 32, 56, 3) and seen[0][2] == pytest.approx(1.0)
    assert seen[0][1] == pytest.approx(r.trace.speed_mps[20])
    # a constant-velocity plan keeps the speed (within the follower's acceleration limits)
    assert abs(r.trace.speed_mps[-1] - r.trace.speed_mps[20]) < 0.3


def test_bend_adds_curvature_and_a_stopping_plan_holds_the_wheel():
    t = np.arange(1, 9) * 0.5
    straight = np.c_[8.0 * t, 0 * t, 0 * t]
    assert np.allclose(bend(straight, 0.0), straight)
    arc = bend(straight, 0.02)                                   # a circle of radius 50 m
    s = 8.0 * t
    assert np.allclose(arc[:, 2], 0.02 * s)
    assert np.allclose(arc[:, 1], 50.0 * (1 - np.cos(0.02 * s)), rtol=0.02)
    f = WaypointFollower()
    f.set_plan(np.zeros((8, 3)), np.array([3.0, 4.0, 0.5]), 0.0)
    k, acc = f.command(3.0, 4.0, 0.5, 5.0, 0.0)
    assert k == 0.0 and acc < 0
    pose = np.array([1.0, 2.0, 0.3])
    back = to_ego_frame(np.array([[1.0 + np.cos(0.3), 2.0 + np.sin(0.3), 0.5]]), pose)
    assert np.allclose(back, [[1.0, 0.0, 0.2]])
