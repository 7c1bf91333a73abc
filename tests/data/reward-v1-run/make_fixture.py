"""How ``tests/data/reward-v1-run/`` was made: a tiny Video2Reward run of ``resim train reward`` in the layout
it wrote before reward runs moved to the shared export layout (``RUN/final/{config.yaml, model.safetensors,
meta.json}``, ``resim/models/exported.py``). Run on commit 4a56242 (with the working tree of that morning); it
writes the old layout only with that code, which is the point: the files keep the old format.

* ``config.yaml``: the resolved ``RewardTrainConfig`` (model config under ``model``, no ``model_name``).
* ``reward.safetensors``: the head's weights as ``head.*`` (the backbone is frozen, so not saved).
* ``meta.json``: ``model.metadata()`` (``feature_id``, ...) + the run's held-out metrics.
* ``reference.safetensors``: two fixed 4-frame videos (``video``, uint8 (2, 4, 3, 24, 32)) and the loaded
  model's float32 CPU scores for them (``scores``, of ``model(video=video / 255)``).

The run: 4 toy episodes (``tests.support.reward_toy``, scores 0, 1/3, 2/3, 1), one 9-frame clip each, 2 epochs,
features of the placeholder DINOv2 computed from the frames, a 1-block head of width 16.

    .venv/bin/python tests/data/reward-v1-run/make_fixture.py
"""
import shutil
import tempfile
from pathlib import Path

import numpy as np
import torch
from safetensors.torch import save_file

from resim.cli import main as resim
from resim.shards.schema import ClipSpec
from tests.support.shards import make_dummy_sample
from resim.models.reward.checkpoint import load_checkpoint
from resim.shards.video import encode_mp4
from resim.shards.writer import ShardWriter
from tests.support.reward_toy import toy_episode_frames

HERE = Path(__file__).parent
SETS = {"model.num_frames": 4, "model.frame_step": 2, "model.head_dim": 16, "model.num_heads": 2,
        "model.num_blocks": 1, "model.mlp_hidden_dim": 16, "epochs": 2, "batch_size_per_gpu": 2,
        "data.heldout_fraction": 0.5}


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        ds, run = Path(tmp) / "ds", Path(tmp) / "run"
        spec = ClipSpec(num_history_frames=1, num_future_frames=8)
        rng = np.random.default_rng(0)
        with ShardWriter(ds, "toy", max_samples_per_shard=8) as w:
            for e, score in enumerate(np.linspace(0.0, 1.0, 4)):
                s = make_dummy_sample(item_id=f"toy/ep{e}", spec=spec, hazard=bool(score < 0.5), seed=e)
                s["frames.mp4"] = encode_mp4(toy_episode_frames(float(score), 9, 32, 48, rng), 10.0)
                s["meta.json"]["infraction_score"] = float(score)
                w.write(s)
        sets = [a for k, v in SETS.items() for a in ("--set", f"{k}={v}")]
        assert resim(["train", "reward", "--shards", str(ds), "--out", str(run), "--no-progress", *sets]) == 0
        for f in ("config.yaml", "reward.safetensors", "meta.json"):
            shutil.copy(run / f, HERE / f)
    video = torch.from_numpy(np.random.default_rng(1).integers(0, 256, (2, 4, 3, 24, 32), dtype=np.uint8))
    with torch.no_grad():
        scores = load_checkpoint(HERE)(video=video.float() / 255)
    save_file({"video": video.contiguous(), "scores": scores.contiguous()}, str(HERE / "reference.safetensors"))


if __name__ == "__main__":
    main()
