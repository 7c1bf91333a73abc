"""Stored features in real shards (ShardWriter / reader), training from them, and the CLI end to end."""
import json

import numpy as np
import pytest

from resim.cli import main
from resim.shards.reader import iter_samples
from resim.shards.schema import ClipSpec
from tests.support.shards import make_dummy_sample
from resim.models.reward.model import Video2Reward
from resim.shards.writer import ShardWriter
from resim.train.tasks.reward.data import clips_from_samples
from resim.train.tasks.reward.features import add_features_to_dataset
from tests.support.reward_toy import toy_episode_frames

TINY_SETS = ["--set", "model.num_frames=4", "--set", "model.frame_step=2", "--set", "model.head_dim=32",
             "--set", "model.num_heads=2", "--set", "model.mlp_hidden_dim=32"]


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    """8 labelled episodes x 2 clips (toy frames whose content follows the score), 1 unlabelled, 1 too short."""
    from resim.shards.video import encode_mp4

    root = tmp_path_factory.mktemp("ds")
    spec = ClipSpec(num_history_frames=1, num_future_frames=8)  # 9 frames
    rng = np.random.default_rng(0)
    with ShardWriter(root, "toy", max_samples_per_shard=7) as w:
        for e, score in enumerate(np.linspace(0.0, 1.0, 8)):
            frames = toy_episode_frames(float(score), 12, 32, 48, rng)
            for c, start in enumerate((0, 3)):
                s = make_dummy_sample(item_id=f"toy/ep{e}", start_frame=start, spec=spec, hazard=bool(score < 0.5),
                                      seed=e * 10 + c)
                s["frames.mp4"] = encode_mp4(frames[start:start + 9], 10.0)
                s["meta.json"]["infraction_score"] = float(score)
                w.write(s)
        w.write(make_dummy_sample(item_id="unlabelled/ep", spec=spec, hazard=None))
        short = ClipSpec(num_history_frames=1, num_future_frames=4)  # 5 frames < the window of 7
        w.write(make_dummy_sample(item_id="short/ep", spec=short, hazard=True))
    return root


def test_features_step_writes_dino_and_quarantines(dataset, tmp_path, tiny_cfg):
    model = Video2Reward(tiny_cfg)
    out = tmp_path / "with_dino"
    summary = add_features_to_dataset(dataset, out, model)
    assert summary["samples"] == 18 and summary["with_features"] == 16 and summary["quarantined"] == 1
    assert summary["dino_bytes_per_sample"] == 4 * 50 * 32 * 2
    samples = list(iter_samples(out, attach_prompts=False, latent_as="stored"))
    assert len(samples) == 18
    labelled = [s for s in samples if s["meta.json"]["dino_id"]]
    assert len(labelled) == 16 and all(s["dino.npy"].dtype == np.float16 for s in labelled)
    assert all(s["meta.json"]["dino_id"] == model.feature_id for s in labelled)
    # stored features equal the live backbone on the decoded frames' window
    clips = list(clips_from_samples(labelled[:1]))
    live = model.encode(__import__("torch").from_numpy(
        clips[0].clip_frames()[[2, 4, 6, 8]]).permute(0, 3, 1, 2)[None].float() / 255)[0]
    np.testing.assert_array_equal(live.numpy(), clips[0].dino.astype(np.float32))
    import pyarrow.parquet as pq

    q = pq.read_table(out / "quarantine" / "reward-features.parquet").to_pylist()
    assert q[0]["stage"] == "reward-features" and "5 frames" in q[0]["reason"] and "short" in q[0]["item"]


def test_cli_features_train_score(dataset, tmp_path, capsys):
    feats = tmp_path / "feats"
    assert main(["shards", "features", str(dataset), "--out", str(feats), *TINY_SETS]) == 0
    run = tmp_path / "run"
    rc = main(["train", "reward", "--shards", str(feats), "--out", str(run), "--set", "epochs=4",
               "--set", "batch_size_per_gpu=4", *TINY_SETS])
    assert rc == 0
    cap = capsys.readouterr()
    assert "held-out: MAE" in cap.out and "stored features" in cap.out
    assert "skipped clip synthetic_short" in cap.err and "5 frames" in cap.err  # named, and the run went on
    meta = json.loads((run / "final" / "meta.json").read_text())
    assert meta["backbone_placeholder"] is True and meta["used_stored_features"] is True
    # final/ is the export every trained model has: the run config form (model_name, model = the reward
    # model's config, the trainer's sections), loadable as a RunConfig; the run's own config beside it
    import yaml

    from resim.config import from_dict
    from resim.train.config import RunConfig

    exported = from_dict(RunConfig, yaml.safe_load((run / "final" / "config.yaml").read_text()))
    assert exported.model_name == "reward" and exported.trainer.steps == 12
    assert exported.model == yaml.safe_load((run / "config.yaml").read_text())["model"]
    assert not (run / "reward.safetensors").exists() and (run / "final" / "model.safetensors").is_file()
    assert (run / "heldout_pred_vs_true.png").stat().st_size > 1000
    preds = json.loads((run / "heldout_predictions.json").read_text())
    held_items = {p["item_id"] for p in preds}
    assert held_items == set(meta["heldout_items"]) and len(held_items) >= 2
    # score a shard sample by key and a video file; both with the trained checkpoint
    key = next(s["__key__"] for s in iter_samples(dataset, attach_prompts=False)
               if s["meta.json"]["item_id"] == "toy/ep0")
    vid = tmp_path / "v.avi"
    import cv2

    w = cv2.VideoWriter(str(vid), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (48, 32))
    for f in toy_episode_frames(0.0, 15, 32, 48, np.random.default_rng(1)):
        w.write(cv2.cvtColor(f, cv2.COLOR_RGB2BGR))
    w.release()
    assert main(["score", key, str(vid), "--checkpoint", str(run), "--shards", str(dataset), "--json"]) == 0
    res = json.loads(capsys.readouterr().out)["results"]
    assert [r["kind"] for r in res] == ["shard sample", "video"] and res[1]["frames"] == 15
    assert all(np.isfinite(r["score"]) for r in res)
    short_key = next(s["__key__"] for s in iter_samples(dataset, attach_prompts=False)
                     if s["meta.json"]["item_id"] == "short/ep")
    assert main(["score", short_key, "--checkpoint", str(run), "--shards", str(dataset)]) == 1
    assert "shorter than the model's window of 7" in capsys.readouterr().err
    assert main(["score", "no-such-key", "--checkpoint", str(run), "--shards", str(dataset)]) == 1


def test_cli_train_overwrite_replaces_a_reward_run(dataset, tmp_path, capsys):
    """A second `train reward` into the same --out is refused; with --overwrite the old run's files (trainer
    checkpoints included) are replaced, so nothing of the first run is left mixed in."""
    run = tmp_path / "run"
    args = ["train", "reward", "--shards", str(dataset), "--out", str(run), "--no-progress",
            "--set", "batch_size_per_gpu=4", *TINY_SETS]
    assert main([*args, "--set", "epochs=2"]) == 0
    steps_first = sorted(p.name for p in (run / "trainer" / "checkpoints").iterdir())
    capsys.readouterr()
    assert main([*args, "--set", "epochs=1"]) == 2
    assert f"holds a reward run (trainer/checkpoints/{steps_first[-1]}); use --overwrite" in capsys.readouterr().err
    assert main([*args, "--set", "epochs=1", "--overwrite"]) == 0
    steps_second = sorted(p.name for p in (run / "trainer" / "checkpoints").iterdir())
    assert len(steps_second) == 1 and steps_second[0] < steps_first[-1]   # only the new run's checkpoint
    import yaml

    assert yaml.safe_load((run / "config.yaml").read_text())["epochs"] == 1
    assert len(json.loads((run / "history.json").read_text())) == int(steps_second[0][len("step_"):])
