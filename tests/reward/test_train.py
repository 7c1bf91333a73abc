"""train_reward on small splits: the split is checked before training, undefined held-out metrics are nan
(not an exception after training), and every JSON the run writes is strict JSON (null, never NaN)."""
import json

import numpy as np
import pytest

from resim.config import from_dict
from resim.train.tasks.reward.config import RewardTrainConfig
from tests.support.reward_toy import toy_clips, toy_split
from resim.train.tasks.reward.train import SplitError, prepare_training, train_reward

TINY_MODEL = {"num_frames": 4, "frame_step": 2, "head_dim": 32, "num_heads": 2, "mlp_hidden_dim": 32}


def _cfg(**kw):
    return from_dict(RewardTrainConfig, {"epochs": 1, "batch_size_per_gpu": 8, "model": TINY_MODEL, **kw})


def _strict_json(path):
    def refuse(c):
        raise ValueError(f"non-standard JSON constant {c} in {path.name}")
    return json.loads(path.read_text(), parse_constant=refuse)


def test_unsplittable_episodes_are_refused_before_training(monkeypatch):
    """One episode: the dataset's split keeps it for training and holds nothing out. The error says why, before
    any training step runs."""
    import resim.train.tasks.reward.train as train_mod

    monkeypatch.setattr(train_mod, "fit", lambda *a, **k: pytest.fail("trained before the split was checked"))
    clips = toy_clips(1, 3, 8, seed=0)
    with pytest.raises(SplitError, match=r"no labelled clip \(3 usable\) of the 1 episode\(s\) it can use is on the "
                                         r"held-out side of the split \(toy clips\)"):
        train_reward(clips, _cfg(), toy_split(clips))


def test_one_heldout_clip_still_writes_the_checkpoint_with_null_metrics(tmp_path):
    """3 episodes (2 hazardous, 1 clean) hold out one clip: Spearman and AUC are undefined. The run used to
    raise in spearman() after training and write no checkpoint; meta.json used to get a bare NaN."""
    clips = toy_clips(3, 1, 8, seed=0, hazard_threshold=0.9)
    split = toy_split(clips)
    prepared = prepare_training(clips, _cfg(), split)
    assert len(prepared.held) == 1
    assert any("Spearman is undefined" in n for n in prepared.notes)
    assert any("hazard AUC is undefined" in n for n in prepared.notes)
    r = train_reward(clips, _cfg(), split, tmp_path, prepared=prepared)
    assert r["n_heldout"] == 1 and np.isnan(r["metrics"]["spearman"]) and np.isfinite(r["metrics"]["mae"])
    assert (tmp_path / "final" / "model.safetensors").is_file()
    meta = _strict_json(tmp_path / "final" / "meta.json")
    assert meta["heldout_metrics"]["spearman"] is None and meta["heldout_metrics"]["hazard_auc"] is None
    assert meta["heldout_metrics"]["mae"] == pytest.approx(r["metrics"]["mae"])
    assert meta["notes"] == r["notes"]
    for name in ("heldout_predictions.json", "history.json"):
        _strict_json(tmp_path / name)
    from resim.models.reward.checkpoint import load_checkpoint

    load_checkpoint(tmp_path)   # a meta.json with nulls loads


def test_json_safe_maps_non_finite_to_null():
    from resim.models.reward.checkpoint import json_safe

    got = json_safe({"a": float("nan"), "b": np.float32("inf"), "c": [np.float64(0.5), np.int64(3)], "d": np.bool_(1)})
    assert got == {"a": None, "b": None, "c": [0.5, 3], "d": True}
    json.dumps(got, allow_nan=False)
