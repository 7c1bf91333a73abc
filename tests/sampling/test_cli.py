"""`resim sample` and `resim plan` end to end on tiny placeholder models (world model, VAE, reward model)."""
import json

import numpy as np
import pytest
import torch
import yaml

from resim.cli import main


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    torch.set_num_threads(1)
    from safetensors.torch import save_file

    from resim.shards.schema import COMMANDS
    from tests.support.shards import add_dummy_prompts, make_dummy_sample, write_data_encode
    from resim.shards.writer import ShardWriter
    from resim.models.world.config import preset
    from resim.models.world.dit import WorldModel
    from resim.models.reward.checkpoint import save_checkpoint
    from resim.train.tasks.reward.config import RewardTrainConfig
    from resim.models.reward.model import Video2Reward

    root = tmp_path_factory.mktemp("sampling_cli")
    data = root / "shards"
    add_dummy_prompts(data, seq_len=16, dim=64)
    keys = []
    with ShardWriter(data, "d", max_samples_per_shard=4, config_hash="dummy") as w:
        for i in range(3):
            s = make_dummy_sample(item_id=f"ep{i}", command=COMMANDS[i], seed=i, latent_channels=16,
                                  latent_hw=(4, 6), frames_hw=(32, 48))
            keys.append(s["__key__"])
            w.write(s)
    torch.manual_seed(0)
    wm = WorldModel(preset("tiny"))
    with torch.no_grad():
        for n, p in wm.named_parameters():
            if n.startswith(("trajectory_encoder.", "action_encoder.")):
                p.normal_(0, 0.2)
    ck = root / "run" / "final"
    ck.mkdir(parents=True)
    (ck / "config.yaml").write_text(yaml.safe_dump({"model_name": "world", "model": {"preset": "tiny"}}))
    write_data_encode(ck)
    save_file({k: v.contiguous() for k, v in wm.state_dict().items()}, str(ck / "model.safetensors"))
    tc = RewardTrainConfig()
    save_checkpoint(Video2Reward(tc.model), root / "reward", tc)
    return {"root": root, "data": data, "keys": keys, "run": root / "run", "reward": root / "reward"}


def test_sample_cli(setup, capsys, request):
    out = setup["root"] / "s1"
    args = ["sample", "--checkpoint", str(setup["run"]), "--shards", str(setup["data"]), "--history",
            setup["keys"][0], "--command", "Turning left", "--trajectory", "turn_left", "--seconds", "1.2",
            "--steps", "3", "--seed", "1", "--device", "cpu", "--out", str(out)]
    assert main(args) == 0
    lat = np.load(out / "sample_latents.npy")
    assert lat.shape == (3 + 3, 16, 4, 6)                    # 3 history + ceil(1.2 s * 10 / 4) = 3 latent frames
    meta = json.loads((out / "sample_meta.json").read_text())
    assert meta["num_frames"] == 1 + 4 * 5 and meta["num_history_frames"] == 9
    for f in ("sample.mp4", "sample.gif", "sample_sheet.png", "rollout.yaml", "run.json"):
        assert (out / f).stat().st_size > 0
    run = json.loads((out / "run.json").read_text())
    assert run["prompts"] and set(run["prompts"].values()) == {"prompt_table"}
    # the same seed without the KV cache gives the same latents (within float tolerance)
    out2 = setup["root"] / "s2"
    assert main(args[:-2] + ["--set", "rollout.kv_cache=off", "--out", str(out2)]) == 0
    np.testing.assert_allclose(np.load(out2 / "sample_latents.npy"), lat, rtol=1e-4, atol=1e-4)
    assert "KV cache off" in capsys.readouterr().out
    assert run["attention_backend"] == "sdpa"                # the checkpoint's setting, recorded
    # runtime.attention=flex: the same rollout through flex_attention (uncompiled on a CPU), recorded in run.json
    out3 = setup["root"] / "s3"
    assert main(args[:-2] + ["--set", "runtime.attention=flex", "--out", str(out3)]) == 0
    np.testing.assert_allclose(np.load(out3 / "sample_latents.npy"), lat, rtol=1e-4, atol=1e-4)
    assert json.loads((out3 / "run.json").read_text())["attention_backend"] == "flex"
    # runtime.compile: eager by default on a CPU (recorded); on, the compiled blocks give the same rollout
    assert (run["compile"], run["compile_flag"]) == (False, "auto")
    request.getfixturevalue("needs_inductor")   # skips the rest where inductor cannot build kernels
    out4 = setup["root"] / "s4"
    assert main(args[:-2] + ["--set", "runtime.compile=on", "--out", str(out4)]) == 0
    np.testing.assert_allclose(np.load(out4 / "sample_latents.npy"), lat, rtol=1e-4, atol=1e-4)
    assert json.loads((out4 / "run.json").read_text())["compile"] is True


def test_sample_cli_errors(setup, capsys):
    base = ["sample", "--checkpoint", str(setup["run"]), "--out", str(setup["root"] / "bad")]
    assert main(base + ["--history", "nope", "--shards", str(setup["data"]), "--steps", "1"]) == 2
    assert "not found" in capsys.readouterr().err
    assert main(base + ["--history", setup["keys"][0], "--shards", str(setup["data"]), "--command", "Fly"]) == 2
    assert main(base + ["--history", "nope"]) == 2          # a key without --shards: one line, exit 2
    assert "resim sample: --history nope: not a file" in capsys.readouterr().err


def test_plan_cli(setup, capsys):
    out = setup["root"] / "plan"
    assert main(["plan", "--checkpoint", str(setup["run"]), "--reward", str(setup["reward"]), "--shards",
                 str(setup["data"]), "--history", setup["keys"][1], "--seconds", "0.8", "--steps", "2",
                 "--device", "cpu", "--out", str(out)]) == 0
    ranking = json.loads((out / "ranking.json").read_text())
    assert [r["rank"] for r in ranking] == [1, 2, 3, 4, 5]
    assert sorted(r["name"] for r in ranking) == sorted(["keep_lane", "turn_left", "turn_right", "brake", "swerve"])
    scores = [r["reward"] for r in ranking]
    assert scores == sorted(scores, reverse=True) and all(np.isfinite(scores))
    assert len(set(scores)) > 1                               # different futures, different rewards
    assert (out / "plan_grid.png").stat().st_size > 0
    assert np.load(out / "plan_latents.npy").shape == (5, 3 + 2, 16, 4, 6)
    assert "| rank | candidate |" in capsys.readouterr().out


def test_sample_cli_video_history_vid2world(setup):
    """A video file as history (encoded by the VAE), prompts from the T5 placeholder, frame by frame with
    actions derived from the trajectory and causal action guidance."""
    from tests.support.shards import dummy_frames
    from resim.shards.video import encode_mp4

    video = setup["root"] / "clip.mp4"
    video.write_bytes(encode_mp4(dummy_frames(12, 48, 64, yaw_deg=10.0), 10.0))
    out = setup["root"] / "v"
    assert main(["sample", "--checkpoint", str(setup["run"]), "--history", str(video),
                 "--set", "runtime.size_hw=[32, 48]",
                 "--trajectory", "swerve", "--command", "Moving forward", "--preset", "vid2world",
                 "--set", "runtime.actions_from_trajectory=true", "--set", "runtime.max_text_tokens=8",
                 "--seconds", "0.8", "--steps", "2",
                 "--device", "cpu", "--out", str(out)]) == 0
    assert np.load(out / "sample_latents.npy").shape == (5, 16, 4, 6)
    run = json.loads((out / "run.json").read_text())
    assert run["history"] == "video:clip.mp4" and all(v.startswith("t5:") for v in run["prompts"].values())
    assert run["rollout"]["chunk_frames"] == 1 and run["rollout"]["guidance"]["drop_recent_actions"]


def _coded_video(path, fps, n, bits=8):
    """n frames whose index is written in binary as 8-px-wide black/white columns (survives mp4 compression)."""
    from resim.shards.video import encode_mp4
    frames = np.zeros((n, 32, 8 * bits, 3), np.uint8)
    for i in range(n):
        for b in range(bits):
            if i >> b & 1:
                frames[i, :, 8 * b:8 * (b + 1)] = 255
    path.write_bytes(encode_mp4(frames, fps))
    return path


def _decode_ids(frames, bits=8):
    return [sum(1 << b for b in range(bits) if f[:, 8 * b:8 * (b + 1)].mean() > 127) for f in frames]


@pytest.mark.parametrize("fps,expected_back", [(30.0, [24, 21, 18, 15, 12, 9, 6, 3, 0]),
                                               (25.0, [20, 18, 15, 12, 10, 8, 5, 2, 0]),
                                               (10.0, [8, 7, 6, 5, 4, 3, 2, 1, 0])])
def test_video_history_is_resampled_to_the_clip_rate(tmp_path, fps, expected_back):
    """The 9 history frames are 0.1 s apart whatever the file's rate (they were the last 9 source frames: 0.27 s
    of a 30 fps clip), and the history reports the clip rate (--seconds is converted with it)."""
    import types

    from resim.sample.load import history_from_video
    vae = types.SimpleNamespace(encode=lambda clip, seeds: np.zeros((1, 3, 16, 4, 8), np.float32),
                                info=types.SimpleNamespace(temporal_compression=4))
    n = 60
    h = history_from_video(_coded_video(tmp_path / "v.mp4", fps, n), vae, 3, (32, 64))
    assert _decode_ids(h.frames) == [n - 1 - d for d in expected_back]
    assert h.fps_hz == 10.0 and h.meta["source_fps_hz"] == pytest.approx(fps)


def test_video_history_slower_than_the_clip_rate_is_refused(tmp_path):
    import types

    from resim.sample.load import SamplingInputError, history_from_video
    vae = types.SimpleNamespace(encode=lambda clip, seeds: np.zeros((1, 3, 16, 4, 8), np.float32),
                                info=types.SimpleNamespace(temporal_compression=4))
    with pytest.raises(SamplingInputError, match="5 fps is below the 10 Hz"):
        history_from_video(_coded_video(tmp_path / "slow.mp4", 5.0, 30), vae, 3, (32, 64))
    with pytest.raises(SamplingInputError, match="readable frames at 30 fps"):   # 0.8 s needed, 0.5 s given
        history_from_video(_coded_video(tmp_path / "short.mp4", 30.0, 15), vae, 3, (32, 64))


def test_sample_cli_30fps_video_seconds_at_the_clip_rate(setup, tmp_path, capsys):
    """--seconds 0.8 from a 30 fps clip: 2 latent frames (8 frames at 10 Hz), not ceil(0.8 * 30 / 4) = 6."""
    video = _coded_video(tmp_path / "clip30.mp4", 30.0, 40)
    out = tmp_path / "out"
    assert main(["sample", "--checkpoint", str(setup["run"]), "--history", str(video),
                 "--set", "runtime.size_hw=[32, 48]",
                 "--command", "Moving forward", "--set", "runtime.max_text_tokens=8", "--seconds", "0.8",
                 "--steps", "1",
                 "--no-guidance", "--device", "cpu", "--out", str(out)]) == 0
    assert np.load(out / "sample_latents.npy").shape == (3 + 2, 16, 4, 6)
    run = json.loads((out / "run.json").read_text())
    assert run["history_fps_hz"] == 10.0 and run["latent_frame_dt_s"] == pytest.approx(0.4)
    # every wait says what it is doing; "total" is the wall clock of the whole command, set-up included
    cap = capsys.readouterr()
    assert "[resim sample] loading the world model" in cap.err and "[resim sample] decoding" in cap.err
    assert "s wall clock (set-up and history" in cap.out


def test_policy_actions_follow_the_history_rate_as_in_training(setup, tmp_path, monkeypatch):
    """runtime.actions_from_trajectory on a 5 Hz shard history (latent frame = 0.8 s): the actions are those training
    derives for the same clip geometry (Batch.latent_frame_dt_s), frames past the 4-s trajectory get the null
    action, and the rollout is told they are derived (guidance drops them with the trajectory)."""
    from resim.shards.schema import ClipSpec
    from tests.support.shards import add_dummy_prompts, make_dummy_sample
    from resim.shards.writer import ShardWriter
    from resim.train.data import Batch
    from resim.models.world.conditioning import actions_from_trajectory
    from resim.sample import rollout as rollout_mod
    from resim.sample.plan import make_candidate

    data = tmp_path / "shards5"
    add_dummy_prompts(data, seq_len=16, dim=64)
    spec = ClipSpec(fps_hz=5.0, num_history_frames=9, num_future_frames=8)      # 17 frames = 5 latent frames
    s = make_dummy_sample(item_id="ep5", seed=0, spec=spec, latent_channels=16, latent_hw=(4, 6),
                          frames_hw=(32, 48))
    with ShardWriter(data, "d", max_samples_per_shard=4, config_hash="dummy") as w:
        w.write(s)
    seen = {}
    real = rollout_mod.rollout

    def spy(*a, **kw):
        seen["kw"] = kw
        seen["res"] = real(*a, **kw)
        return seen["res"]

    monkeypatch.setattr(rollout_mod, "rollout", spy)
    assert main(["sample", "--checkpoint", str(setup["run"]), "--shards", str(data), "--history", s["__key__"],
                 "--trajectory", "keep_lane",
                 "--set", "runtime.actions_from_trajectory=true", "--seconds", "8", "--steps", "1",
                 "--device", "cpu", "--out", str(tmp_path / "out")]) == 0
    res = seen["res"]
    assert seen["kw"]["actions_from_trajectory"] is True
    assert res.future.shape[1] == 10                                  # 8 s at 5 Hz = 40 frames = 10 latent frames
    traj = torch.from_numpy(make_candidate("keep_lane").trajectory)[None]
    b = Batch(latents=torch.zeros(1, 3 + 10, 16, 4, 6), prompt_table=torch.zeros(1, 1, 1),
              prompt_index=torch.zeros(1, dtype=torch.long), null_index=torch.zeros(1, dtype=torch.long),
              trajectory=traj, has_trajectory=torch.ones(1, dtype=torch.bool), command=torch.zeros(1, dtype=torch.long),
              source=["x"], keys=["k"], meta=[{"num_history_frames": 9, "num_frames": 9 + 40, "fps_hz": 5.0}])
    assert b.latent_frame_dt_s == pytest.approx(0.8)
    want, want_valid = actions_from_trajectory(traj, 13, b.num_history_latent_frames, b.latent_frame_dt_s)
    assert want_valid[0, 3:].tolist() == [True] * 5 + [False] * 5      # 5 x 0.8 s = the trajectory's 4 s
    assert torch.equal(res.action_valid[:, 3:], want_valid[:, 3:])
    torch.testing.assert_close(res.actions[:, 3:], want[:, 3:])
    assert json.loads((tmp_path / "out" / "run.json").read_text())["latent_frame_dt_s"] == pytest.approx(0.8)


def test_video_history_takes_the_training_clips_size_and_crop(setup, tmp_path, capsys):
    """A run whose data was encoded at 32x48: a video history is encoded at 32x48 by default, cover-resized
    and centre-cropped as the pipeline cut its clips (a 32x96 frame keeps its middle, it is not squeezed), and
    a runtime.size_hw that disagrees is refused in one line."""
    import shutil
    import types

    from resim.shards.video import encode_mp4
    from resim.sample.load import history_from_video, trained_size_hw

    run = tmp_path / "run"
    shutil.copytree(setup["run"], run)
    (run / "final" / "data_encode.yaml").write_text(yaml.safe_dump({"encode": {"height_px": 32, "width_px": 48}}))
    assert trained_size_hw(run) == (32, 48) and trained_size_hw(setup["run"]) is None
    frames = np.zeros((12, 32, 96, 3), np.uint8)
    frames[:, :, :24] = 255                     # white outer quarters: a centre crop drops them, a squeeze keeps them
    frames[:, :, 72:] = 255
    video = tmp_path / "wide.mp4"
    video.write_bytes(encode_mp4(frames, 10.0))
    vae = types.SimpleNamespace(encode=lambda clip, seeds: np.zeros((1, 3, 16, 4, 6), np.float32),
                                info=types.SimpleNamespace(temporal_compression=4))
    h = history_from_video(video, vae, 3, (32, 48))
    assert h.frames.shape[1:3] == (32, 48) and h.frames.mean() < 40
    common = ["sample", "--checkpoint", str(run), "--history", str(video), "--command", "Moving forward",
              "--set", "runtime.max_text_tokens=8", "--seconds", "0.4", "--steps", "1", "--no-guidance",
              "--device", "cpu"]
    assert main([*common, "--out", str(tmp_path / "o")]) == 0
    assert np.load(tmp_path / "o" / "sample_latents.npy").shape[-2:] == (4, 6)     # 32x48 px / 8
    capsys.readouterr()
    assert main([*common, "--set", "runtime.size_hw=[64, 96]", "--out", str(tmp_path / "o2")]) == 2
    err = capsys.readouterr().err
    assert "trained on 32x48 clips" in err and "Traceback" not in err
