"""Commands from yaw and from trajectories; trajectories from poses (closed forms)."""
import math

import numpy as np
import pytest

from resim.config import ConfigError, from_dict
from resim.labeling.commands import command_from_trajectory, command_from_yaw
from resim.labeling.config import CommandConfig, LabelerConfig, preset
from resim.labeling.trajectory import trajectory_from_poses

L, F, R = "Turning left", "Moving forward", "Turning right"


def test_command_from_yaw_thresholds_and_confidence():
    c = CommandConfig(turn_threshold_deg=10.0, confidence_scale_deg=4.0)
    assert command_from_yaw(25.0, c)[0] == L
    assert command_from_yaw(-25.0, c)[0] == R
    assert command_from_yaw(3.0, c)[0] == F
    assert command_from_yaw(10.0, c) == (L, 0.5)            # at the threshold: a coin flip
    assert command_from_yaw(-9.99, c)[0] == F
    confs = [command_from_yaw(y, c)[1] for y in (10.5, 12, 16, 30)]
    assert confs == sorted(confs) and confs[-1] > 0.99
    assert command_from_yaw(0.0, c)[1] == pytest.approx(0.5 + 0.5 * math.tanh(10 / 4))
    assert command_from_yaw(20.0, LabelerConfig(command=c))[0] == L
    with pytest.raises(ValueError):
        command_from_yaw(float("nan"), c)


def test_turn_threshold_is_a_rate_a_steady_curve_is_a_turn_at_any_window():
    """A steady 6.5 deg/s curve: 13 deg over 2 s was "Moving forward" against 15.5 deg per window; the threshold
    now scales with the window (15.5 deg per 4 s = 3.875 deg/s), so it is a turn at 2 s and at 4 s."""
    from resim.labeling.flow import FlowLabeler

    fps = 10.0
    for window_s in (2.0, 4.0):
        c = CommandConfig(window_s=window_s)
        rates = np.full(int(window_s * fps), 6.5)                      # deg/s, one per frame pair
        assert FlowLabeler(LabelerConfig(command=c)).label_from_rates(rates, fps).command == L
        assert FlowLabeler(LabelerConfig(command=c)).label_from_rates(-rates, fps).command == R
        assert command_from_yaw(6.5 * window_s, CommandConfig(), window_s)[0] == L   # the window passed wins
        assert command_from_yaw(3.5 * window_s, c)[0] == F                          # under 3.875 deg/s
        assert c.turn_rate_threshold_deg_s == 3.875
    assert CommandConfig(window_s=2.0).turn_threshold_for() == 7.75
    assert command_from_yaw(7.75, CommandConfig(window_s=2.0)) == (L, 0.5)        # the coin flip moved with it
    # confidence is the same function of the yaw rate at any window
    assert command_from_yaw(10.0, CommandConfig(window_s=2.0))[1] == command_from_yaw(20.0, CommandConfig())[1]


def test_default_window_thresholds_are_bit_identical_to_before():
    """At window_s = 4 the scale factor is exactly 1: shipped datasets' labels do not move by one ulp."""
    c = CommandConfig()
    assert (c.window_s, c.turn_threshold_deg, c.confidence_scale_deg) == (4.0, 15.5, 4.0)
    assert c.turn_threshold_for() == 15.5 and c.window_factor() == 1.0
    assert command_from_yaw(15.5, c) == (L, 0.5) and command_from_yaw(-15.5, c) == (R, 0.5)
    assert command_from_yaw(15.499999, c)[0] == F
    for y in (-40.0, -15.6, -3.3, 0.0, 7.1, 15.4, 15.51, 22.2, 90.0):
        old = 0.5 + 0.5 * math.tanh(abs(abs(y) - 15.5) / 4.0)         # the formula before the scaling
        assert command_from_yaw(y, c)[1] == old
        assert command_from_yaw(y, c, 4.0) == command_from_yaw(y, c)


def _arc(v, omega, n, fps, x0=3.0, y0=-2.0, a0=0.7):
    t = np.arange(n) / fps
    if omega == 0:
        xl, yl = v * t, 0 * t
    else:
        xl, yl = v / omega * np.sin(omega * t), v / omega * (1 - np.cos(omega * t))
    c, s = math.cos(a0), math.sin(a0)
    return np.stack([x0 + c * xl - s * yl, y0 + s * xl + c * yl, a0 + omega * t], 1), t


def test_trajectory_from_poses_matches_circular_arc():
    fps, v, om = 10.0, 8.0, math.radians(12)
    poses, _ = _arc(v, om, 80, fps)
    traj = trajectory_from_poses(poses, 10, fps)
    assert traj.shape == (8, 3) and traj.dtype == np.float32
    tw = np.arange(1, 9) * 0.5
    np.testing.assert_allclose(traj[:, 0], v / om * np.sin(om * tw), atol=1e-3)
    np.testing.assert_allclose(traj[:, 1], v / om * (1 - np.cos(om * tw)), atol=1e-3)
    np.testing.assert_allclose(traj[:, 2], om * tw, atol=1e-5)


def test_trajectory_interpolates_between_frames_and_wraps_yaw():
    poses, _ = _arc(5.0, 0.0, 60, 4.0, a0=math.pi - 0.01)     # 4 Hz: 0.5 s = 2 frames; yaw near +pi
    poses[:, 2] = np.where(np.arange(60) % 2, poses[:, 2] - 2 * np.pi, poses[:, 2])   # wrapped input
    traj = trajectory_from_poses(poses, 0, 4.0)
    np.testing.assert_allclose(traj[:, 0], 5.0 * 0.5 * np.arange(1, 9), atol=1e-4)
    np.testing.assert_allclose(traj[:, 1:], 0.0, atol=1e-4)
    poses3, _ = _arc(5.0, 0.0, 30, 3.0)                       # 3 Hz: waypoints between frames
    traj3 = trajectory_from_poses(poses3, 0, 3.0)
    np.testing.assert_allclose(traj3[:, 0], 2.5 * np.arange(1, 9), atol=1e-4)


def test_trajectory_errors():
    poses, _ = _arc(5.0, 0.0, 20, 10.0)
    with pytest.raises(ValueError, match="last waypoint"):
        trajectory_from_poses(poses, 0, 10.0)
    with pytest.raises(ValueError, match="shape"):
        trajectory_from_poses(poses[:, :2], 0, 10.0)


def test_command_from_trajectory_rules():
    c = CommandConfig()                                       # lateral offset, 2 m
    fps = 10.0
    for om, v, expect in [(math.radians(10), 8.0, L), (-math.radians(10), 8.0, R), (0.0, 15.0, F)]:
        poses, _ = _arc(v, om, 60, fps)
        cmd, yaw = command_from_trajectory(trajectory_from_poses(poses, 0, fps), c)
        assert cmd == expect and yaw == pytest.approx(math.degrees(om) * 4, abs=1e-3)
    lane_change = np.zeros((8, 3), np.float32)
    lane_change[:, 0] = np.arange(1, 9) * 12
    lane_change[-1, 1] = 3.5                                   # +3.5 m, heading back to 0
    assert command_from_trajectory(lane_change, c)[0] == L
    assert command_from_trajectory(lane_change, CommandConfig(trajectory_rule="heading"))[0] == F
    assert command_from_trajectory(lane_change, CommandConfig(trajectory_rule="either"))[0] == L
    with pytest.raises(ValueError):
        command_from_trajectory(np.zeros((8, 2)), c)


def test_config_validation_and_presets():
    assert preset("accurate").flow.flow_preset == "medium" and preset("accurate").flow.dis_finest_scale is None
    with pytest.raises(ConfigError, match="hfov_deg"):
        from_dict(LabelerConfig, {"flow": {"hfov_deg": 200}})
    with pytest.raises(ConfigError, match="flow.nope"):
        from_dict(LabelerConfig, {"flow": {"nope": 1}})
    with pytest.raises(ConfigError, match="unknown labeler preset"):
        preset("nope")
    assert preset("default").flow.camera_ahead_m is None          # OpenDV: the rig is unknown
    with pytest.raises(ConfigError, match="camera_ahead_m"):
        from_dict(LabelerConfig, {"flow": {"camera_ahead_m": 40.0}})
    with pytest.raises(ConfigError, match="camera_height_m"):
        from_dict(LabelerConfig, {"flow": {"camera_ahead_m": 1.0, "camera_height_m": 0.0}})
    assert preset("default").flow.foe_model == "pooled"
    with pytest.raises(ConfigError, match="foe_model"):
        from_dict(LabelerConfig, {"flow": {"foe_model": "global"}})
    with pytest.raises(ConfigError, match="foe_min_straight_s"):
        from_dict(LabelerConfig, {"flow": {"foe_min_straight_s": -1.0}})


def test_heading_rule_unwraps_a_u_turn_past_180_deg():
    """A tight left U-turn (50 deg/s for 4 s = 200 deg): the wrapped last yaw alone (-160) read as a right turn."""
    fps, rate, v = 10.0, math.radians(50.0), 5.0
    t = np.arange(0, 4.01, 1 / fps)
    r = v / rate
    poses = np.stack([r * np.sin(rate * t), r * (1 - np.cos(rate * t)), rate * t], axis=1)
    traj = trajectory_from_poses(poses, 0, fps)
    for rule in ("heading", "either"):
        cmd, yaw = command_from_trajectory(traj, CommandConfig(trajectory_rule=rule))
        assert cmd == "Turning left" and yaw == pytest.approx(200.0, abs=0.5), (rule, cmd, yaw)
