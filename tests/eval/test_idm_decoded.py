"""The IDM's decoded-frame augmentation (``resim train idm --decoded-vae``): the frames are the clip's own latents
through the shipped VAE, an epoch shows them with their probability, and the mirror flags of runs without them
are unchanged."""
from pathlib import Path

import numpy as np
import pytest
import torch

from resim.config import ConfigError
from tests.support.shards import dummy_trajectory
from resim.models.idm import idm_preset
from resim.train.tasks.idm import (IDMDataError, IDMTrainConfig, TrajClip, attach_decoded, augment_draws, collate,
                                     prepare_idm_data)

HELDOUT = Path(__file__).resolve().parents[1] / "data" / "synth-heldout"


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return float(10 * np.log10(255.0 ** 2 / mse))


def test_collate_shows_the_decoded_frames_where_asked_and_fails_loudly_without_them():
    cfg = idm_preset("tiny")
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 256, (49, 32, 48, 3), dtype=np.uint8)
    dec = 255 - frames
    clip = TrajClip("k", "ep", frames, dummy_trajectory(10.0), 9, 10.0, decoded=dec)
    b = collate([clip, clip], cfg, flip=[False, False], decoded=[False, True])
    assert torch.allclose(b["video"][1], 1 - b["video"][0], atol=1e-6)   # frames_to_tensor: [0, 1]
    assert torch.equal(b["trajectory"][0], b["trajectory"][1])            # the recorded trajectory either way
    with pytest.raises(AssertionError, match="never attached"):
        collate([TrajClip("k2", "ep", frames, dummy_trajectory(0.0), 9, 10.0)], cfg, decoded=[True])


def test_draws_keep_the_mirror_flags_and_show_decoded_frames_at_their_rate():
    plain = IDMTrainConfig(preset="tiny")
    with_dec = IDMTrainConfig(preset="tiny", decoded_vae="synth-vae", decoded_prob=0.3)
    n = 20000
    a = augment_draws(plain, np.random.default_rng(7), n)
    b = augment_draws(with_dec, np.random.default_rng(7), n)
    assert np.array_equal(a[:, 0], np.random.default_rng(7).random(n) < 0.5)   # as before the option existed
    assert np.array_equal(a[:, 0], b[:, 0]) and not a[:, 1].any()
    assert b[:, 1].mean() == pytest.approx(0.3, abs=0.02)


def test_config_checks_the_vae_and_the_probability():
    with pytest.raises(ConfigError, match="decoded_prob"):
        IDMTrainConfig(decoded_prob=1.5)
    with pytest.raises(ConfigError, match="no such folder or shipped model"):
        IDMTrainConfig(decoded_vae="no-such-vae")


@pytest.mark.skipif(not HELDOUT.is_dir(), reason="tests/data/synth-heldout is missing from this checkout")
def test_decoded_frames_are_the_clips_latents_through_the_shipped_vae(one_torch_thread):
    cfg = IDMTrainConfig(preset="tiny", decoded_vae="synth-vae", val_fraction=0)
    data = prepare_idm_data(HELDOUT, cfg)
    clips = data.train + data.held
    assert len(clips) == 6
    for c in clips:
        assert c.decoded is not None and c.decoded.shape == c.frames.shape and c.latents is None
        # close to the recorded frames (the VAE reconstructs; a wrong latent scale or frame order would not),
        # and not the recorded frames themselves (the same clip 4 frames off reads ~23 dB)
        p = _psnr(c.decoded, c.frames)
        assert 25.0 < p < 60.0, (c.key, p)
    # a dataset without latents is named, not decoded to nothing
    bare = [TrajClip("k", "ep", clips[0].frames, clips[0].trajectory, 9, 10.0)]
    with pytest.raises(IDMDataError, match="latent.npy"):
        attach_decoded(bare, "synth-vae", (32, 48))
