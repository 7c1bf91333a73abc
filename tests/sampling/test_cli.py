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

    from shards.schema import COMMANDS
    from shards.testing import add_dummy_prompts, make_dummy_sample
    from shards.writer import ShardWriter
    from training.models.config import preset
    from training.models.dit import WorldModel
    from training.reward.checkpoint import save_checkpoint
    from training.reward.config import RewardTrainConfig
    from training.reward.model import Video2Reward

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
    save_file({k: v.contiguous() for k, v in wm.state_dict().items()}, str(ck / "model.safetensors"))
    tc = RewardTrainConfig()
    save_checkpoint(Video2Reward(tc.model), root / "reward", tc)
    return {"root": root, "data": data, "keys": keys, "run": root / "run", "reward": root / "reward"}


def test_sample_cli(setup, capsys):
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
    assert main(args[:-2] + ["--no-kv-cache", "--out", str(out2)]) == 0
    np.testing.assert_allclose(np.load(out2 / "sample_latents.npy"), lat, rtol=1e-4, atol=1e-4)
    assert "KV cache off" in capsys.readouterr().out
    assert run["attention_backend"] == "sdpa"                # the checkpoint's setting, recorded
    # --attention flex: the same rollout through flex_attention (uncompiled on a CPU), recorded in run.json
    out3 = setup["root"] / "s3"
    assert main(args[:-2] + ["--attention", "flex", "--out", str(out3)]) == 0
    np.testing.assert_allclose(np.load(out3 / "sample_latents.npy"), lat, rtol=1e-4, atol=1e-4)
    assert json.loads((out3 / "run.json").read_text())["attention_backend"] == "flex"


def test_sample_cli_errors(setup, capsys):
    base = ["sample", "--checkpoint", str(setup["run"]), "--out", str(setup["root"] / "bad")]
    assert main(base + ["--history", "nope", "--shards", str(setup["data"]), "--steps", "1"]) == 2
    assert "not found" in capsys.readouterr().err
    assert main(base + ["--history", setup["keys"][0], "--shards", str(setup["data"]), "--command", "Fly"]) == 2
    with pytest.raises(SystemExit):
        main(base + ["--history", "nope"])


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
    from shards.testing import dummy_frames
    from shards.video import encode_mp4

    video = setup["root"] / "clip.mp4"
    video.write_bytes(encode_mp4(dummy_frames(12, 48, 64, yaw_deg=10.0), 10.0))
    out = setup["root"] / "v"
    assert main(["sample", "--checkpoint", str(setup["run"]), "--history", str(video), "--size", "32x48",
                 "--trajectory", "swerve", "--command", "Moving forward", "--preset", "vid2world",
                 "--actions-from-trajectory", "--max-text-tokens", "8", "--seconds", "0.8", "--steps", "2",
                 "--device", "cpu", "--out", str(out)]) == 0
    assert np.load(out / "sample_latents.npy").shape == (5, 16, 4, 6)
    run = json.loads((out / "run.json").read_text())
    assert run["history"] == "video:clip.mp4" and all(v.startswith("t5:") for v in run["prompts"].values())
    assert run["rollout"]["chunk_frames"] == 1 and run["rollout"]["guidance"]["drop_recent_actions"]
