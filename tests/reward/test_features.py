import dataclasses

import numpy as np
import pytest
import torch

from resim.models.reward.model import Video2Reward
from resim.train.tasks.reward.features import add_clip_features, features_for_frames
from resim.train.tasks.reward.train import fit, predict


def test_stored_features_are_float16_window_features(tiny_cfg, toy):
    m = Video2Reward(tiny_cfg)
    clips = add_clip_features(m, toy[:2])
    d = clips[0].dino
    assert d.dtype == np.float16 and d.shape == m.feature_shape
    assert clips[0].dino_id == m.feature_id and "placeholder" in clips[0].dino_id
    # the live path over the window's frames gives the same numbers
    live = m.encode(torch.from_numpy(toy[0].frames[[1, 3, 5, 7]]).permute(0, 3, 1, 2)[None].float() / 255)
    np.testing.assert_array_equal(live[0].numpy(), d.astype(np.float32))
    ft = Video2Reward(dataclasses.replace(tiny_cfg, freeze_backbone=False))
    with pytest.raises(ValueError, match="frozen backbone"):
        features_for_frames(ft, [toy[0].frames])


def test_training_on_stored_features_matches_training_through_backbone(tiny_train_cfg, toy, tmp_path):
    """Issue 8 done-when: same seed, frozen backbone -> same predictions within float tolerance."""
    train, held = toy[:16], toy[16:]
    preds = {}
    for use_features in (True, False):
        torch.manual_seed(0)
        m = Video2Reward(tiny_train_cfg.model)
        tr = add_clip_features(m, train) if use_features else train
        ho = add_clip_features(m, held) if use_features else held
        res = fit(m, tr, tiny_train_cfg, use_features=use_features, run_dir=tmp_path / str(use_features))
        assert res["steps"] == 3 * 2 and len(res["history"]) == 6  # through the common Trainer
        preds[use_features] = predict(m, ho, use_features)
    assert preds[True].shape == (len(held),)
    assert np.abs(preds[True] - preds[False]).max() < 1e-4, (preds[True], preds[False])
    # and the predictions are not trivially equal to the untrained model's
    untrained = predict(Video2Reward(tiny_train_cfg.model), held, False)
    assert np.abs(untrained - preds[False]).max() > 1e-2
