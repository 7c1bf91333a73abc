"""The flow yaw estimator on video rendered with a known yaw rate (tests/labeling/conftest.py)."""
import cv2
import numpy as np
import pytest

from resim.config import ConfigError
from resim.labeling.config import FlowConfig, LabelerConfig
from resim.labeling.flow import FlowLabeler
from resim.shards.schema import COMMANDS

FPS = 10.0


def _cfg(**kw):
    # the renderer's camera has a 70 deg field of view; tell the labeler so (unknown on real video)
    return LabelerConfig(flow=FlowConfig(hfov_deg=70.0, **kw))


@pytest.mark.parametrize("yaw_rate_deg_s", [0.0, 6.0, -6.0, 15.0])
def test_heading_change_matches_rendered_truth(render, yaw_rate_deg_s):
    frames, poses = render(41, FPS, yaw_rate_deg_s, speed_mps=6.0, seed=1)
    lab = FlowLabeler(_cfg())
    rates = lab.yaw_rates_deg(frames, FPS)
    assert rates.shape == (40,)
    est = rates.sum() / FPS
    true = np.degrees(poses[-1, 2] - poses[0, 2])
    # tolerance: DIS at 256 px on this crude renderer (aliased far ground, pixel-snapped posts) reads
    # within ~3 % and +-1 deg on straight road; calibrated numbers are in docs/labeling.md
    assert abs(est - true) <= max(1.0, 0.06 * abs(true)), (est, true)
    if yaw_rate_deg_s:  # every pair has the right sign (left +)
        assert (np.sign(rates) == np.sign(yaw_rate_deg_s)).mean() > 0.9


def test_camera_ahead_of_the_rear_axle_does_not_inflate_yaw(render):
    # In a turn the camera moves along the chord and, 2 m ahead of the rear axle, sideways: the focus
    # of expansion shifts towards the turn with the yaw rate. A FOE held fixed (foe_iters=0: the
    # first labeler) reads that shift as extra yaw (+(d/2 + L)/Z, > 10 % here); the per-pair FOE fit must not.
    frames, poses = render(41, FPS, 15.0, speed_mps=8.0, seed=5, cam_forward_m=2.0)
    true = np.degrees(poses[-1, 2] - poses[0, 2])
    est = FlowLabeler(_cfg()).yaw_rates_deg(frames, FPS).sum() / FPS
    fixed = FlowLabeler(_cfg(foe_iters=0)).yaw_rates_deg(frames, FPS).sum() / FPS
    assert abs(est - true) <= 0.06 * abs(true), (est, true)
    assert fixed - true > 0.10 * true, (fixed, true)


def test_known_rig_places_the_foe_by_kinematics(render):
    # With the rig known (flow.camera_ahead_m), the FOE's x is not fitted but follows the car:
    # e_x = -f yaw (1/2 + L/d), d from the ground-plane flow and the camera height. Told the right lever
    # arm the turn is read right; told the camera sits on the axle (L = 0, truly 2 m), the sideways
    # motion of the camera is read as rotation (+(L/Z): > 10 % high); told 3 m, lower than with 2 m.
    frames, poses = render(41, FPS, 15.0, speed_mps=8.0, seed=5, cam_forward_m=2.0)
    true = np.degrees(poses[-1, 2] - poses[0, 2])
    lab = FlowLabeler(_cfg(camera_ahead_m=2.0, camera_height_m=1.5))
    est = lab.yaw_rates_deg(frames, FPS).sum() / FPS
    assert abs(est - true) <= 0.06 * abs(true), (est, true)
    # distance per pair over the camera height, from the ground plane: 0.8 m / 1.5 m
    dh = np.nanmedian(lab.last_distance_over_height)
    assert dh == pytest.approx(0.8 / 1.5, rel=0.2), dh     # d / Z instead of d / (Z - d) read +25 %
    on_axle = FlowLabeler(_cfg(camera_ahead_m=0.0)).yaw_rates_deg(frames, FPS).sum() / FPS
    assert on_axle - true > 0.10 * true, (on_axle, true)
    further = FlowLabeler(_cfg(camera_ahead_m=3.0)).yaw_rates_deg(frames, FPS).sum() / FPS
    assert further < est, (further, est)


def test_known_rig_straight_road_reads_straight(render):
    frames, _ = render(41, FPS, 0.0, speed_mps=6.0, seed=1, cam_forward_m=2.0)
    est = FlowLabeler(_cfg(camera_ahead_m=2.0)).yaw_rates_deg(frames, FPS).sum() / FPS
    assert abs(est) <= 1.0, est


def test_known_rig_without_visible_ground_falls_back_to_the_free_fit(render):
    # the distance per pair needs textured ground below the horizon; with the lower half blanked there
    # is none, and the known-rig fit must hand back the per-pair FOE fit unchanged (not zeros, not NaN)
    frames, _ = render(21, FPS, 10.0, speed_mps=6.0, seed=4, cam_forward_m=1.0)
    frames = frames.copy()
    frames[:, frames.shape[1] // 2 + 4:] = 128
    free = FlowLabeler(_cfg()).yaw_rates_deg(frames, FPS)
    lab = FlowLabeler(_cfg(camera_ahead_m=1.0))
    rig = lab.yaw_rates_deg(frames, FPS)
    assert np.isnan(lab.last_distance_over_height).all()
    assert np.abs(free).sum() > 0
    np.testing.assert_array_equal(rig, free)


def test_pooled_foe_finds_the_mount_yaw_and_the_lever_arm(render):
    # Rig unknown (OpenDV): the FOE's x is placed at a - f k yaw, a = the FOE of straight driving (here the
    # camera looks 3 deg left of the car's axis: a = f tan 3 deg, right of centre), k = 1/2 + L/d (2 m ahead,
    # 0.8 m per pair: 3.0) regressed from the per-pair FOEs. Both must come out near the truth, and the turn
    # after 3.5 s of straight driving must read within 3 % (the per-pair fit reads 4-5 % short here).
    rates = np.r_[np.zeros(35), np.full(40, 12.0)]
    frames, poses = render(76, FPS, rates, speed_mps=8.0, seed=5, cam_forward_m=2.0, cam_yaw_deg=3.0)
    lab = FlowLabeler(_cfg())
    inc = lab.yaw_rates_deg(frames, FPS) / FPS
    true = np.degrees(np.diff(poses[:, 2]))
    assert lab.last_foe_sources == ["pooled", "pooled"]
    a, k = lab.last_foe_model
    assert a == pytest.approx(lab.focal_px(256) * np.tan(np.radians(3.0)), abs=1.5), a
    assert k == pytest.approx(0.5 + 2.0 / 0.8, rel=0.25), k
    assert abs(inc[:35].sum()) <= 1.0, inc[:35].sum()      # a held at 0 instead reads -9.2 deg over these 3.5 s
    assert inc[35:].sum() == pytest.approx(true[35:].sum(), rel=0.03)


def test_pooled_foe_is_applied_to_chunks_seen_before_the_straight_driving(render):
    # a turn first, then straight road; chunks of 20 pairs, so the first ones come before 3 s of straight
    # driving: they are held back and re-fitted once the FOE of straight driving is known
    rates = np.r_[np.full(25, 12.0), np.zeros(50)]
    frames, poses = render(76, FPS, rates, speed_mps=8.0, seed=5, cam_forward_m=2.0, cam_yaw_deg=3.0)
    lab = FlowLabeler(_cfg(chunk_pairs=20))
    pooled = lab.yaw_rates_deg(frames, FPS) / FPS
    per_pair = FlowLabeler(_cfg(chunk_pairs=20, foe_model="per_pair")).yaw_rates_deg(frames, FPS) / FPS
    assert lab.last_foe_sources == ["pooled"] * 4
    assert lab.last_foe_model[0] == pytest.approx(lab.focal_px(256) * np.tan(np.radians(3.0)), abs=1.5)
    assert not np.allclose(pooled[:20], per_pair[:20])              # the first chunk was re-fitted
    true = np.degrees(np.diff(poses[:, 2]))
    # 33.4 for a true 30.0 (per pair: 31.0): one short turn at 12 deg/s among noisy straight pairs leaves
    # the regressed k at 1.3 where the truth is 3.0 (docs/labeling.md, "Short clips that open with a turn")
    assert pooled[:25].sum() == pytest.approx(true[:25].sum(), rel=0.15)


def test_pooled_foe_needs_straight_driving_first(render):
    # a clip that is one curve from start to end shows no FOE of straight driving: every chunk keeps the
    # per-pair fit (bit for bit), and says so
    frames, _ = render(41, FPS, 8.0, speed_mps=6.0, seed=2, cam_forward_m=1.0)
    lab = FlowLabeler(_cfg())
    pooled = lab.yaw_rates_deg(frames, FPS)
    assert lab.last_foe_sources == ["per_pair"] and lab.last_foe_model is None
    np.testing.assert_array_equal(pooled, FlowLabeler(_cfg(foe_model="per_pair")).yaw_rates_deg(frames, FPS))


def test_label_window_command_and_confidence(render):
    frames, _ = render(41, FPS, -8.0, speed_mps=6.0, seed=2)
    lab = FlowLabeler(_cfg())
    out = lab.label(frames, FPS)
    assert out.command == COMMANDS[2]            # Turning right
    assert -36 < out.yaw_deg < -28
    assert 0.5 < out.confidence <= 1.0


def test_hood_and_burnt_in_overlay_do_not_bias_yaw(render):
    frames, poses = render(31, FPS, 10.0, speed_mps=6.0, seed=3)
    frames = frames.copy()
    h, w = frames.shape[1:3]
    frames[:, int(0.9 * h):] = 30                                   # static hood
    frames[:, 4:16, 4:90] = 255                                     # burnt-in timestamp box
    frames[:, 7:13, 10:80:6] = 0
    est = FlowLabeler(_cfg()).yaw_rates_deg(frames, FPS).sum() / FPS
    true = np.degrees(poses[-1, 2])
    assert abs(est - true) <= 0.15 * abs(true), (est, true)     # hood + overlay cost a few % here


def test_assumed_fov_scales_the_estimate_like_tan(render):
    frames, poses = render(21, FPS, 10.0, speed_mps=4.0, seed=4)
    est70 = FlowLabeler(_cfg()).yaw_rates_deg(frames, FPS).sum()
    est90 = FlowLabeler(LabelerConfig(flow=FlowConfig(hfov_deg=90.0))).yaw_rates_deg(frames, FPS).sum()
    ratio = est90 / est70
    assert ratio == pytest.approx(np.tan(np.radians(45)) / np.tan(np.radians(35)), rel=0.08)


def test_frame_size_change_is_an_error(render):
    frames, _ = render(3, FPS, 0.0)
    small = frames[:, :100, :180]
    with pytest.raises(ValueError, match="frame size changed"):
        FlowLabeler(_cfg()).yaw_rates_deg([frames[0], small[1]], FPS)


def test_dark_low_contrast_video_is_equalised(render):
    # night: the synthetic world's night episodes lost track (quality ~0.01) before the working frame
    # was histogram-equalised; here the rendered drive is dimmed to 1/12 of its contrast
    frames, poses = render(31, FPS, 10.0, speed_mps=6.0, seed=6)
    dark = (frames.astype(np.float32) / 12.0 + 4).astype(np.uint8)
    true = np.degrees(poses[-1, 2])
    lab = FlowLabeler(_cfg())
    est = lab.yaw_rates_deg(dark, FPS).sum() / FPS
    assert abs(est - true) <= 0.10 * abs(true), (est, true)
    raw = FlowLabeler(_cfg(contrast="none"))
    raw.yaw_rates_deg(dark, FPS)
    assert np.median(lab.last_quality) > 3 * np.median(raw.last_quality)


def test_camera_roll_does_not_leak_into_yaw(render):
    # body roll in and out of a turn: each frame rolled about the image centre (a pure rotation about the
    # optical axis), +-2 deg; roll is the third rotation of the fit and is discarded
    frames, poses = render(41, FPS, 10.0, speed_mps=6.0, seed=8)
    h, w = frames.shape[1:3]
    rolled = np.stack([
        cv2.warpAffine(fr, cv2.getRotationMatrix2D(((w - 1) / 2, (h - 1) / 2), 2.0 * np.sin(2 * np.pi * k / 8), 1.0),
                       (w, h), borderMode=cv2.BORDER_REPLICATE)
        for k, fr in enumerate(frames)])
    true = np.degrees(poses[-1, 2] - poses[0, 2])
    plain = FlowLabeler(_cfg()).yaw_rates_deg(frames, FPS).sum() / FPS
    est = FlowLabeler(_cfg()).yaw_rates_deg(rolled, FPS).sum() / FPS
    assert abs(est - true) <= 0.06 * abs(true), (est, plain, true)
    assert abs(est - plain) <= 0.03 * abs(true), (est, plain, true)


@pytest.mark.xfail(strict=True, reason="known limitation (docs/labeling.md): in a scene with little far texture a "
                   "strongly textured object crossing below the horizon is taken for rotation (reads ~34 deg)")
def test_crossing_vehicle_is_an_outlier(render):
    # straight road; a textured box (a car crossing at an intersection) slides 4 px per frame across the
    # lower middle of the image, ~7 % of it. Read as rotation it would be ~1.3 deg per pair, ~50 deg over the
    # 4 s: the robust fit should ignore it, and today does not (strict xfail: this test fails loudly the day
    # it passes, so the limitation note can go)
    frames, poses = render(41, FPS, 0.0, speed_mps=6.0, seed=9)
    frames = frames.copy()
    h, w = frames.shape[1:3]
    rng = np.random.default_rng(3)
    box = cv2.GaussianBlur(rng.integers(0, 256, (40, 60), dtype=np.uint8), (0, 0), 1.0)
    for k in range(len(frames)):
        x0 = 20 + 4 * k
        r0 = int(0.55 * h)
        x1 = min(w, x0 + 60)
        if x0 < w:
            frames[k, r0:r0 + 40, x0:x1] = box[:, : x1 - x0, None]
    est = FlowLabeler(_cfg()).yaw_rates_deg(frames, FPS).sum() / FPS
    assert abs(est) <= 1.5, est


@pytest.mark.xfail(strict=True, reason="known limitation (docs/labeling.md 'Speed'): a gentle curve at highway speed "
                   "(6 deg/s at 20 m/s, radius ~190 m) reads ~17 of 24 deg on this renderer (13.5 without the DIS warm start)")
def test_gentle_curve_at_highway_speed(render):
    # the synthetic world never drives faster than ~10 m/s; this pins what happens above it (strict xfail:
    # fails loudly the day it passes, so the limitation note can go)
    frames, poses = render(41, FPS, 6.0, speed_mps=20.0, seed=7, cam_forward_m=1.5)
    true = np.degrees(poses[-1, 2] - poses[0, 2])
    est = FlowLabeler(_cfg()).yaw_rates_deg(frames, FPS).sum() / FPS
    assert abs(est - true) <= 0.10 * abs(true), (est, true)


def test_dis_warm_start_reads_large_displacements_better(render):
    # each pair's DIS starts from the previous pair's flow (flow.dis_warm_start): at 20 m/s the ground moves far
    # per pair and the cold coarse-to-fine search loses part of it (6 deg/s curve: cold 13.5, warm 17.2 of 24 deg)
    frames, poses = render(41, FPS, 6.0, speed_mps=20.0, seed=7, cam_forward_m=1.5)
    true = np.degrees(poses[-1, 2] - poses[0, 2])
    warm, cold = (FlowLabeler(_cfg(dis_warm_start=ws)).yaw_rates_deg(frames, FPS).sum() / FPS for ws in (True, False))
    assert abs(warm - true) < abs(cold - true) - 2.0, (warm, cold, true)


def test_dis_warm_start_survives_a_scene_cut(render):
    # edited video (OpenDV is YouTube): after a cut the previous flow is a wrong start; OpenCV keeps it only where
    # it matches better than its own search, so the pairs after the cut read as if the video began there
    a, _ = render(30, FPS, 0.0, speed_mps=6.0, seed=1)
    b, poses = render(41, FPS, 10.0, speed_mps=8.0, seed=3)
    joined = FlowLabeler(_cfg()).yaw_rates_deg(np.concatenate([a, b]), FPS) / FPS    # pair 29 spans the cut
    alone = FlowLabeler(_cfg()).yaw_rates_deg(b, FPS) / FPS
    true = np.degrees(poses[-1, 2] - poses[0, 2])
    assert joined[30:].sum() == pytest.approx(true, rel=0.06)
    assert joined[31:].sum() == pytest.approx(alone[1:].sum(), abs=1.0)


def test_one_labeler_gives_each_video_the_same_result_as_a_fresh_one(render):
    # the pipeline's label stage keeps one FlowLabeler for every clip it sees (Ray actors see them in any order).
    # OpenCV's DIS keeps the last warm start's flow inside the object and tries it on later calls, so without a
    # fresh DIS per video the first pair of a clip depended on the clip labelled before it (found by the pipeline's
    # kill-and-rerun test: shards not byte-identical)
    a, _ = render(21, FPS, 12.0, speed_mps=9.0, seed=4)
    b, _ = render(21, FPS, -5.0, speed_mps=6.0, seed=6)
    other, _ = render(11, FPS, 3.0, speed_mps=6.0, seed=8, size_hw=(96, 160))      # 256 x 154 at working size
    lab = FlowLabeler(_cfg())
    lab.yaw_rates_deg(a, FPS)
    np.testing.assert_array_equal(lab.yaw_rates_deg(b, FPS), FlowLabeler(_cfg()).yaw_rates_deg(b, FPS))
    lab.yaw_rates_deg(b, FPS)                        # then a video of another size: no stale buffer is read
    np.testing.assert_array_equal(lab.yaw_rates_deg(other, FPS), FlowLabeler(_cfg()).yaw_rates_deg(other, FPS))


def test_pooled_foe_keeps_a_bounded_trailing_pool_of_straight_pairs():
    # an hour-long video must not grow the per-chunk work: a is the median over the last foe_straight_pool_pairs
    # straight pairs, so it also follows a camera that was re-mounted (FOE of straight driving 10 px -> -6 px)
    lab = FlowLabeler(_cfg(foe_straight_pool_pairs=300))
    lab._start_video(FPS)
    P, f = 60, lab.focal_px(256)
    theta = np.zeros((P, 3))                       # straight driving
    for i in range(40):
        e = np.zeros((P, 2))
        e[:, 0] = 10.0 if i < 20 else -6.0
        lab._pool_add(theta, e, np.ones(P))
        assert sum(len(s[0]) for s in lab._straight) <= 300 + P
    a, _ = lab._pool_params(f)
    assert a == -6.0
    with pytest.raises(ConfigError, match="foe_straight_pool_pairs"):
        _cfg(foe_straight_pool_pairs=10)          # cannot hold the 3 s of straight driving the model needs
