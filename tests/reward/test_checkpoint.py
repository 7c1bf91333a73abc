"""Reward runs in the shared export layout (RUN/final/, resim.models.exported) and runs of the layout before it
(tests/data/reward-v1-run: RUN/config.yaml a RewardTrainConfig + RUN/reward.safetensors, made by the code of
that time): both load and score as they were saved."""
import dataclasses
import json
import shutil
from pathlib import Path

import pytest
import torch
import yaml
from safetensors.torch import load_file

from resim.models.reward.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from resim.train.tasks.reward.config import RewardTrainConfig
from resim.models.reward.model import Video2Reward
from resim.train.run import REWARD_RUN_FILES, check_out_dir, remove_run

OLD_RUN = Path(__file__).resolve().parents[1] / "data" / "reward-v1-run"


def _scores(model, video):
    with torch.no_grad():
        return model(video=video.float() / 255)


def test_a_run_of_the_older_layout_scores_as_it_did():
    ref = load_file(str(OLD_RUN / "reference.safetensors"))
    model = load_checkpoint(OLD_RUN)
    assert model.cfg.head_dim == 16 and model.cfg.num_blocks == 1
    assert torch.equal(_scores(model, ref["video"]), ref["scores"])


def test_saved_again_it_is_the_shared_layout_and_scores_the_same(tmp_path):
    ref = load_file(str(OLD_RUN / "reference.safetensors"))
    old = load_checkpoint(OLD_RUN)
    # its training config is of the older form (flat lr, no optim section): only its model is carried over
    train_cfg = RewardTrainConfig(model=old.cfg)
    save_checkpoint(old, tmp_path / "run", train_cfg, {"note": "re-saved"})
    run = tmp_path / "run"
    assert sorted(p.name for p in run.iterdir()) == ["config.yaml", "final"]
    assert sorted(p.name for p in (run / "final").iterdir()) == ["config.yaml", "meta.json", "model.safetensors"]
    exported = yaml.safe_load((run / "final" / "config.yaml").read_text())
    assert exported == {"model_name": "reward", "model": dataclasses.asdict(old.cfg)}
    meta = json.loads((run / "final" / "meta.json").read_text())
    assert meta["feature_id"] == old.feature_id and meta["note"] == "re-saved"
    # the frozen backbone is not stored: the head only, under the names the older layout used
    assert set(load_file(str(run / "final" / "model.safetensors"))) == set(load_file(str(OLD_RUN / "reward.safetensors")))
    for where in (run, run / "final"):
        assert torch.equal(_scores(load_checkpoint(where), ref["video"]), ref["scores"])


def test_a_fine_tuned_backbone_is_stored_and_loaded(tiny_train_cfg, tmp_path):
    cfg = dataclasses.replace(tiny_train_cfg.model, freeze_backbone=False)
    m = Video2Reward(cfg)
    with torch.no_grad():
        for p in m.backbone.parameters():
            p.add_(0.01)
    save_checkpoint(m, tmp_path, dataclasses.replace(tiny_train_cfg, model=cfg))
    assert any(k.startswith("backbone.") for k in load_file(str(tmp_path / "final" / "model.safetensors")))
    loaded = load_checkpoint(tmp_path)
    assert all(torch.equal(loaded.state_dict()[k], v) for k, v in m.state_dict().items())


def test_a_changed_backbone_is_refused_by_its_feature_id(tiny_train_cfg, tmp_path):
    save_checkpoint(Video2Reward(tiny_train_cfg.model), tmp_path, tiny_train_cfg)
    c = yaml.safe_load((tmp_path / "final" / "config.yaml").read_text())
    c["model"]["backbone_init_seed"] = 7
    (tmp_path / "final" / "config.yaml").write_text(yaml.safe_dump(c))
    with pytest.raises(CheckpointError, match=f"^{tmp_path / 'final'}: trained with backbone features"):
        load_checkpoint(tmp_path)


def test_overwrite_removes_a_run_of_either_layout(tmp_path):
    old = tmp_path / "old"
    shutil.copytree(OLD_RUN, old)
    assert check_out_dir("reward", old, overwrite=True).evidence == "reward.safetensors"
    remove_run(old, REWARD_RUN_FILES)
    assert sorted(p.name for p in old.iterdir()) == ["make_fixture.py", "reference.safetensors"]   # not a run's
    new = tmp_path / "new"
    save_checkpoint(load_checkpoint(OLD_RUN), new, RewardTrainConfig())
    (new / "config.yaml").unlink()   # the kind is read from final/config.yaml then
    assert check_out_dir("reward", new, overwrite=True).evidence == "final/model.safetensors"
    remove_run(new, REWARD_RUN_FILES)
    assert not new.exists() or not any(new.iterdir())
