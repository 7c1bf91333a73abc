"""IDM: windows, loss masking, the Batch path, trajectory metrics and baselines in closed form, and the synthetic
world's waypoints against an independent closed form (tests.support.shards). The split by episode, the epoch batches and
the batched prediction are the shared harness's: tests/training/test_smallfit.py."""
import numpy as np
import pytest
import torch

from resim.config import ConfigError, from_dict
from tests.support.shards import dummy_trajectory
from resim.labeling.trajectory import trajectory_from_poses
from resim.models.idm import InverseDynamicsModel, idm_preset
from resim.train.tasks.idm import TrajClip, constant_velocity, load_idm, trajectory_errors


def test_windows():
    fut, hist = idm_preset("tiny"), idm_preset("tiny-history")
    assert fut.frame_indices(9, 49) == list(range(8, 49, 2))   # last history frame .. end, every 2nd
    assert hist.frame_indices(9, 49) == list(range(0, 9))      # history only
    with pytest.raises(ValueError, match="needs frames"):
        fut.frame_indices(9, 30)
    with pytest.raises(ConfigError, match="must equal future_frames"):
        idm_preset("tiny", num_frames=11)


def test_loss_masks_samples_without_trajectory_and_accepts_a_batch():
    from resim.train.data import Batch

    torch.manual_seed(0)
    m = InverseDynamicsModel(idm_preset("tiny-history"))
    frames = torch.randint(0, 256, (2, 21, 3, 32, 48), dtype=torch.uint8)
    traj = torch.from_numpy(np.stack([dummy_trajectory(20.0), dummy_trajectory(-5.0)]))
    b = Batch(latents=torch.zeros(2, 6, 4, 4, 6), prompt_table=torch.zeros(2, 4, 8),
              prompt_index=torch.tensor([0, 0]), null_index=torch.tensor([1, 1]),
              trajectory=traj, has_trajectory=torch.tensor([True, False]), command=torch.zeros(2, dtype=torch.long),
              source=["synthetic"] * 2, keys=["a", "b"], meta=[{"num_history_frames": 9}] * 2, frames=frames)
    loss, logs = m.loss(b)
    only_first = m.loss({"video": m.window(frames[:1], 9), "trajectory": traj[:1]})[0]
    assert loss.item() == pytest.approx(only_first.item(), rel=1e-5)
    loss.backward()
    assert all(p.grad is not None for p in m.parameters() if p.requires_grad)
    assert set(logs) == {"ade_m", "fde_m"}
    with pytest.raises(ValueError, match="load_frames"):
        m.loss(Batch(**{**b.__dict__, "frames": None}))


def test_trajectory_errors_and_constant_velocity_closed_form():
    gt = np.stack([dummy_trajectory(0.0, speed_mps=8.0), dummy_trajectory(30.0, speed_mps=8.0)])
    shifted = gt.copy()
    shifted[..., 0] += 3.0
    shifted[..., 1] += 4.0
    e = trajectory_errors(shifted, gt)
    assert e["ade_m"] == pytest.approx(5.0) and e["fde_m"] == pytest.approx(5.0) and e["yaw_err_deg"] == 0
    cv = constant_velocity(gt)
    # straight at 8 m/s for the straight path: exact; for the turning one the first-step chord speed, no turn
    assert trajectory_errors(cv[:1], gt[:1])["ade_m"] == pytest.approx(0.0, abs=1e-5)
    assert np.allclose(cv[1, :, 1:], 0) and cv[1, -1, 0] == pytest.approx(8 * np.linalg.norm(gt[1, 0, :2]), rel=1e-6)
    assert trajectory_errors(cv[1:], gt[1:])["fde_m"] > 1.0


def test_pose_waypoints_match_the_dummy_trajectorys_closed_form():
    """The shards' trajectories (labeling.trajectory_from_poses, as the pipeline and the road-world fixture make
    them) and tests.support.shards.dummy_trajectory agree on a constant-curvature drive."""
    v, yaw_total_deg, fps = 8.0, 24.0, 10.0
    rate = np.deg2rad(yaw_total_deg) / 4.0
    t = np.arange(0, 50) / fps
    th0 = 0.7  # an arbitrary world heading and origin: the ego frame must remove them
    yaw = th0 + rate * t
    x = 5.0 + v / rate * (np.sin(yaw) - np.sin(th0))
    y = -2.0 - v / rate * (np.cos(yaw) - np.cos(th0))
    poses = np.stack([x, y, yaw], -1)
    got = trajectory_from_poses(poses, 0, fps)
    assert np.allclose(got, dummy_trajectory(yaw_total_deg, speed_mps=v), atol=1e-4)


def test_road_world_clips_render_and_move(road_world):
    clips = road_world.clips(1, 49, seed=2)
    assert len(clips) == 1
    c = clips[0]
    assert c["frames"].shape == (49, 32, 48, 3) and c["frames"].dtype == np.uint8
    assert np.abs(c["frames"][1:].astype(int) - c["frames"][:-1]).mean() > 1.0   # the camera moves
    assert c["traj"].shape == (8, 3) and c["traj"][-1, 0] > 4 * 2.0             # >= 2 m/s forward


def test_odometry_head_integrates_constant_curvature_exactly():
    """SE(2) composition of equal chord steps reproduces the circular arc (closed form), and the waypoints are
    read at their window positions (2.5 window frames per 0.5 s at frame_step 2)."""
    from resim.models.idm import OdometryHead

    cfg = idm_preset("tiny")
    assert cfg.head == "odometry" and cfg.waypoint_positions() == [2.5 * k for k in range(1, 9)]
    v, rate, dt = 8.0, np.deg2rad(6.0), 0.2
    r, dth = v / rate, rate * dt
    chord = 2 * r * np.sin(dth / 2)
    steps = torch.tensor([[chord * np.cos(dth / 2), chord * np.sin(dth / 2), dth]] * 20, dtype=torch.float64)[None]
    poses = OdometryHead.integrate(steps)[0].numpy()
    t = np.arange(21) * dt
    exact = np.stack([r * np.sin(rate * t), r * (1 - np.cos(rate * t)), rate * t], -1)
    assert np.abs(poses - exact).max() < 1e-9
    # read-out: a model whose per-step motions are forced to those chords gives the arc at 0.5 s steps
    head = OdometryHead(cfg, 48).double()
    head.steps = lambda tokens: steps.expand(tokens.shape[0], -1, -1)
    wp = head(torch.zeros(1, 21 * 4, 48, dtype=torch.float64))[0].numpy()
    tw = 0.5 * np.arange(1, 9)
    arc = np.stack([r * np.sin(rate * tw), r * (1 - np.cos(rate * tw)), rate * tw], -1)
    assert np.abs(wp - arc).max() < 0.01          # linear interpolation between window frames 0.2 s apart


def test_odometry_head_needs_the_future_window_and_trains():
    with pytest.raises(ConfigError, match="odometry"):
        idm_preset("tiny-history", head="odometry")
    torch.manual_seed(0)
    m = InverseDynamicsModel(idm_preset("tiny"))
    video = torch.rand(2, 21, 3, 32, 48)
    traj = torch.from_numpy(np.stack([dummy_trajectory(20.0), dummy_trajectory(-5.0)]))
    loss, logs = m.loss({"video": video, "trajectory": traj})
    loss.backward()
    assert all(p.grad is not None for p in m.parameters())
    assert m(video).shape == (2, 8, 3)


def test_mirror_augmentation_flips_frames_and_negates_y_and_yaw():
    from resim.train.tasks.idm import collate

    cfg = idm_preset("tiny")
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 256, (49, 32, 48, 3), dtype=np.uint8)
    traj = dummy_trajectory(20.0)
    clip = TrajClip("k", "ep", frames, traj, 9, 10.0)
    b = collate([clip, clip], cfg, flip=[False, True])
    assert torch.equal(b["video"][1], b["video"][0].flip(-1))
    assert torch.allclose(b["trajectory"][1], torch.from_numpy(traj * np.array([1, -1, -1], np.float32)))
    assert torch.equal(b["trajectory"][0], torch.from_numpy(traj))


def test_early_stopping_keeps_the_best_validation_epoch(tmp_path, road_world):
    """fit() with validation clips: the record lists every epoch and the weights left in the model (and in
    final/) are the best epoch's, not the last one's."""
    from safetensors.torch import load_file

    from resim.train.tasks.idm import IDMTrainConfig, collate, fit, load_idm, predict

    clips = [{"item_id": c["item_id"], "frames": c["frames"], "traj": c["traj"]}
             for c in road_world.clips(3, 59, seed=4)]
    tc = [TrajClip(f"k{i}", c["item_id"], c["frames"], c["traj"], 9, 10.0) for i, c in enumerate(clips)]
    torch.set_num_threads(1)
    torch.manual_seed(0)
    cfg = from_dict(IDMTrainConfig, {"preset": "tiny", "epochs": 3, "batch_size_per_gpu": 4,
                                     "optim": {"lr": 3e-3, "warmup_steps": 1}})
    m = InverseDynamicsModel(cfg.model_cfg())
    res = fit(m, tc[2:], cfg, tmp_path, val=tc[:2])["early_stopping"]
    hist = res["val_ade_per_epoch"]
    assert [h["epoch"] for h in hist] == [1, 2, 3]
    best = min(hist, key=lambda h: h["val_ade_m"])
    assert res["best_epoch"] == best["epoch"] and res["best_val_ade_m"] == best["val_ade_m"]
    gt = np.stack([c.trajectory for c in tc[:2]])
    assert trajectory_errors(predict(m, tc[:2]), gt)["ade_m"] == pytest.approx(best["val_ade_m"], rel=1e-5)
    saved = load_file(str(tmp_path / "final" / "model.safetensors"))
    assert all(torch.equal(saved[k], v) for k, v in m.state_dict().items())
    # the run stores the resolved config: it loads as the same network, with the best weights
    loaded, _ = load_idm(tmp_path)
    assert loaded.cfg == m.cfg
    assert torch.allclose(loaded(collate(tc[:2], m.cfg)["video"]), m(collate(tc[:2], m.cfg)["video"]))


def test_runs_written_before_the_odometry_head_still_load(tmp_path):
    """Old runs stored {"preset": "tiny"} with query-head weights; "tiny" is an odometry IDM now."""
    import yaml
    from safetensors.torch import save_file

    old = InverseDynamicsModel(idm_preset("tiny-queries"))
    (tmp_path / "final").mkdir()
    save_file({k: v.contiguous() for k, v in old.state_dict().items()}, str(tmp_path / "final/model.safetensors"))
    (tmp_path / "final/config.yaml").write_text(yaml.safe_dump({"model_name": "idm", "model": {"preset": "tiny"}}))
    loaded, _ = load_idm(tmp_path)
    assert loaded.cfg.head == "queries"
    (tmp_path / "final/config.yaml").write_text(yaml.safe_dump({"model_name": "world", "model": {}}))
    with pytest.raises(ValueError, match="not an IDM run"):
        load_idm(tmp_path)


def test_a_missing_or_corrupt_idm_run_is_named(tmp_path):
    """No files: FileNotFoundError naming both places; files that cannot be used: ValueError naming the file."""
    import yaml
    from safetensors.torch import save_file

    with pytest.raises(FileNotFoundError, match=f"IDM checkpoint {tmp_path}: expected config.yaml \\+ "
                                                "model.safetensors in it or in .*written by `resim train idm`"):
        load_idm(tmp_path)
    (tmp_path / "final").mkdir()
    m = InverseDynamicsModel(idm_preset("tiny"))
    save_file({k: v.contiguous() for k, v in m.state_dict().items()}, str(tmp_path / "final/model.safetensors"))
    (tmp_path / "final/config.yaml").write_text(yaml.safe_dump({"model_name": "idm", "model": {"preset": "tiny"}}))
    loaded, info = load_idm(tmp_path)
    assert info["checkpoint"] == str(tmp_path / "final") and len(info["weights_sha256"]) == 64
    (tmp_path / "final/config.yaml").write_text(yaml.safe_dump({"model_name": "idm", "model": {"preset": "nosuch"}}))
    with pytest.raises(ValueError, match=f"^{tmp_path / 'final' / 'config.yaml'}: .*nosuch"):
        load_idm(tmp_path)
    (tmp_path / "final/config.yaml").write_text(yaml.safe_dump({"model_name": "idm", "model": {"preset": "tiny"}}))
    w = tmp_path / "final/model.safetensors"
    w.write_bytes(w.read_bytes()[:64])
    with pytest.raises(ValueError, match=f"^{w}: not a readable safetensors file"):
        load_idm(tmp_path)
