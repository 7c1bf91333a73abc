"""User mistakes in `resim score`, `resim train reward`, `resim shards features`: one line on stderr naming
the item and the reason, a non-zero exit, no traceback."""
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml

from resim.cli import main
from resim.shards import split
from tests.support.reward_toy import toy_episode_frames

TINY = {"num_frames": 4, "frame_step": 2, "head_dim": 32, "num_heads": 2, "mlp_hidden_dim": 32}
TINY_SETS = [a for k, v in TINY.items() for a in ("--set", f"model.{k}={v}")]


@pytest.fixture(scope="module")
def ckpt(tmp_path_factory):
    """An untrained tiny checkpoint (scoring plumbing only) and a 20-frame video."""
    import cv2

    from resim.config import from_dict
    from resim.models.reward.checkpoint import save_checkpoint
    from resim.train.tasks.reward.config import RewardTrainConfig
    from resim.models.reward.model import Video2Reward

    root = tmp_path_factory.mktemp("ck")
    tc = from_dict(RewardTrainConfig, {"epochs": 1, "model": TINY})
    save_checkpoint(Video2Reward(tc.model), root / "ck", tc)
    vid = root / "v.avi"
    w = cv2.VideoWriter(str(vid), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (32, 24))
    for i in range(20):
        w.write(np.full((24, 32, 3), i * 10, np.uint8))
    w.release()
    return root / "ck", vid


@pytest.fixture(scope="module")
def two_episodes(tmp_path_factory):
    """Shards of two labelled episodes, one hazardous and one clean, whose split holds none out (a tiny fraction
    and no minimum): nothing to evaluate on."""
    from resim.shards.schema import ClipSpec
    from tests.support.shards import make_dummy_sample
    from resim.shards.video import encode_mp4
    from resim.shards.writer import ShardWriter

    root = tmp_path_factory.mktemp("two")
    spec = ClipSpec(num_history_frames=1, num_future_frames=8)
    rng = np.random.default_rng(0)
    with ShardWriter(root, "toy", max_samples_per_shard=8) as w:
        for e, score in enumerate((0.1, 1.0)):
            s = make_dummy_sample(item_id=f"toy/ep{e}", start_frame=0, spec=spec, hazard=bool(score < 0.5), seed=e)
            s["frames.mp4"] = encode_mp4(toy_episode_frames(score, 9, 32, 48, rng), 10.0)
            s["meta.json"]["infraction_score"] = score
            w.write(s)
    split.write(root, split.SplitConfig(heldout_fraction=1e-12, min_heldout_episodes=0))
    return root


def _one_line_error(capsys, *needles):
    err = capsys.readouterr().err.strip()
    assert "Traceback" not in err and len(err.splitlines()) == 1, err
    for n in needles:
        assert n in err, err
    return err


def _corrupt(src, dst, edit):
    shutil.copytree(src, dst)
    edit(dst)
    return dst


OLD_RUN = Path(__file__).resolve().parents[1] / "data" / "reward-v1-run"   # the layout before final/


@pytest.mark.parametrize("layout", ["final", "old"])
def test_score_corrupt_checkpoints_name_the_file(ckpt, tmp_path, capsys, layout):
    """Both layouts: a run's final/ (config.yaml in the run config form, model.safetensors) and a run written
    before it (RUN/config.yaml a RewardTrainConfig, RUN/reward.safetensors)."""
    ck, vid = ckpt
    if layout == "old":
        ck = OLD_RUN
    cfg_f, weights_f = ("final/config.yaml", "final/model.safetensors") if layout == "final" else \
        ("config.yaml", "reward.safetensors")
    assert main(["score", str(vid), "--checkpoint", str(ck)]) == 0
    capsys.readouterr()

    def bad_config(d):
        head = "model_name: reward\n" if layout == "final" else ""
        (d / cfg_f).write_text(head + "model: {num_frames: 0}\n")

    def truncated_weights(d):
        (d / weights_f).write_bytes((d / weights_f).read_bytes()[:100])

    def gone_backbone(d):
        c = yaml.safe_load((d / cfg_f).read_text())
        c["model"]["backbone_dir"] = "/nonexistent/dinov2"
        (d / cfg_f).write_text(yaml.safe_dump(c))

    def other_head(d):   # config.yaml no longer matches the stored weights
        c = yaml.safe_load((d / cfg_f).read_text())
        c["model"]["head_dim"] = 64
        (d / cfg_f).write_text(yaml.safe_dump(c))

    cases = [(bad_config, cfg_f, "num_frames and frame_step must be >= 1"),
             (truncated_weights, weights_f, "not a readable safetensors file"),
             (gone_backbone, cfg_f, "/nonexistent/dinov2"),
             (other_head, weights_f, "do not match config.yaml")]
    if layout == "final":
        def world_run(d):   # another model's export in the reward's place
            c = yaml.safe_load((d / cfg_f).read_text())
            (d / cfg_f).write_text(yaml.safe_dump({**c, "model_name": "world"}))

        cases.append((world_run, cfg_f, "model_name is 'world', not a reward run"))
    for edit, name, reason in cases:
        d = _corrupt(ck, tmp_path / edit.__name__, edit)
        assert main(["score", str(vid), "--checkpoint", str(d)]) == 1, edit.__name__
        _one_line_error(capsys, f"{d / name}", reason)
    assert main(["score", str(vid), "--checkpoint", str(tmp_path / "nope")]) == 1
    _one_line_error(capsys, "no such checkpoint folder")
    (tmp_path / "empty").mkdir()
    assert main(["score", str(vid), "--checkpoint", str(tmp_path / "empty")]) == 1
    _one_line_error(capsys, "is not a reward checkpoint: no config.yaml + model.safetensors in it")


def test_score_stride_zero_is_refused(ckpt, capsys):
    """--stride 0 used to score with the default stride (`stride or default`) and exit 0."""
    from resim.models.reward.checkpoint import load_checkpoint
    from resim.sample.reward_score import ScoreError, score_videos

    ck, vid = ckpt
    with pytest.raises(SystemExit) as e:
        main(["score", str(vid), "--checkpoint", str(ck), "--stride", "0"])
    assert e.value.code == 2 and "--stride: must be >= 1, got 0" in capsys.readouterr().err
    import torch

    with pytest.raises(ScoreError, match="stride must be >= 1, got 0"):
        score_videos(load_checkpoint(ck), [torch.rand(8, 3, 16, 16)], stride=0)


def test_train_bad_config_is_a_one_line_error(two_episodes, tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["train", "reward", "--preset", "bogus", "--shards", str(two_episodes), "--out", str(out)]) == 2
    _one_line_error(capsys, "config error", "unknown preset 'bogus'")
    assert main(["train", "reward", "--shards", str(two_episodes), "--out", str(out),
                 "--set", "model.num_heads=0"]) == 2
    _one_line_error(capsys, "num_heads must be >= 1")
    assert main(["train", "reward", "--shards", str(two_episodes), "--out", str(out),
                 "--config", str(tmp_path / "missing.yaml")]) == 2
    _one_line_error(capsys, "missing.yaml does not exist")
    assert main(["train", "reward", "--shards", str(two_episodes), "--out", str(out), *TINY_SETS,
                 "--set", "model.backbone_dir=/nonexistent/dinov2"]) == 2
    _one_line_error(capsys, "/nonexistent/dinov2")
    assert main(["train", "reward", "--shards", str(tmp_path / "nope"), "--out", str(out)]) == 1
    _one_line_error(capsys, "no such folder")
    assert not out.exists()


def test_train_unsplittable_data_fails_before_training(two_episodes, tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["train", "reward", "--shards", str(two_episodes), "--out", str(out), *TINY_SETS]) == 1
    _one_line_error(capsys, str(two_episodes), "of the 2 episode(s) it can use is on the held-out side of the split")
    assert not out.exists()   # nothing written, nothing trained


def test_features_bad_source_or_destination(two_episodes, tmp_path, capsys):
    assert main(["shards", "features", str(two_episodes), "--out", str(two_episodes), *TINY_SETS]) == 1
    _one_line_error(capsys, "is the source dataset")
    assert main(["shards", "features", str(tmp_path / "nope"), "--out", str(tmp_path / "o"), *TINY_SETS]) == 1
    _one_line_error(capsys, "no such dataset folder")
    (tmp_path / "empty").mkdir()
    assert main(["shards", "features", str(tmp_path / "empty"), "--out", str(tmp_path / "o"), *TINY_SETS]) == 1
    _one_line_error(capsys, "no committed shards")
    assert main(["shards", "features", str(two_episodes), "--out", str(tmp_path / "o"), "--preset", "bogus"]) == 2
    _one_line_error(capsys, "unknown preset 'bogus'")


def _fake_world_run(d):
    (d / "checkpoints" / "step_00000020").mkdir(parents=True)
    (d / "checkpoints" / "step_00000020" / "meta.json").write_text('{"step": 20}')
    (d / "config.yaml").write_text("model_name: world\ntrainer:\n  steps: 20\n")
    return d


def _fake_reward_run(d):
    d.mkdir(parents=True)
    (d / "config.yaml").write_text("model:\n  num_frames: 8\nepochs: 20\n")
    (d / "reward.safetensors").write_bytes(b"old")
    (d / "meta.json").write_text("{}")
    return d


def test_train_into_another_kind_of_run_is_refused(two_episodes, tmp_path, capsys):
    wm = _fake_world_run(tmp_path / "wm")
    before = sorted(p.relative_to(wm) for p in wm.rglob("*"))
    for flags in ([], ["--overwrite"]):
        assert main(["train", "reward", "--shards", str(two_episodes), "--out", str(wm), *TINY_SETS, *flags]) == 2
        _one_line_error(capsys, "resim train reward:", f"{wm} holds a world run (checkpoints/step_00000020)",
                        "not a reward run", "choose a new --out")
    assert sorted(p.relative_to(wm) for p in wm.rglob("*")) == before   # nothing written into the world run


def test_train_into_a_reward_run_needs_overwrite(two_episodes, tmp_path, capsys):
    rw = _fake_reward_run(tmp_path / "rw")
    assert main(["train", "reward", "--shards", str(two_episodes), "--out", str(rw), *TINY_SETS]) == 2
    _one_line_error(capsys, "resim train reward:", f"{rw} holds a reward run (reward.safetensors)", "--overwrite")
    # --overwrite: the old run stays until the new one's data is known to be usable (here it is not: exit 1)
    assert main(["train", "reward", "--shards", str(two_episodes), "--out", str(rw), *TINY_SETS, "--overwrite"]) == 1
    _one_line_error(capsys, "is on the held-out side of the split")
    assert (rw / "reward.safetensors").read_bytes() == b"old"


@pytest.mark.parametrize("flag, instead", [(["--carla", "W/carla"], ""),
                                           (["--clip-frames", "80"], "clip.num_history_frames"),
                                           (["--clip-stride-frames", "80"], "clip.stride_frames"),
                                           (["--hold-last"], "clip.max_held_frames")])
def test_the_removed_carla_path_is_refused_with_the_two_commands_instead(tmp_path, capsys, flag, instead):
    """Training reads only shards (docs/architecture.md): the old CARLA-folder flags say how to get shards."""
    out = tmp_path / "run"
    for shards in ([], ["--shards", str(tmp_path)]):
        assert main(["train", "reward", *shards, "--out", str(out), *TINY_SETS, *flag]) == 2
        _one_line_error(capsys, "resim train reward:", f"{flag[0]} was removed", instead,
                        "resim pipeline run configs/pipeline/carla-reward.yaml --set sources.carla.root=DIR",
                        "resim train reward --shards SHARDS")
    assert not out.exists()


def test_train_without_shards_is_refused(tmp_path, capsys):
    assert main(["train", "reward", "--out", str(tmp_path / "run"), *TINY_SETS]) == 2
    _one_line_error(capsys, "resim train reward:", "--shards DIR is required")
    assert not (tmp_path / "run").exists()
