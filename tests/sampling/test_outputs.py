"""Decoding and output files: frame counts of the causal VAE, round-by-round decoding, sheet/GIF/MP4/npy."""
from pathlib import Path

import numpy as np
import pytest
import torch

from resim.sample.outputs import contact_sheet, decode_latents, decode_rollout, write_rollout

VAE_DIR = Path(__file__).resolve().parents[2] / "configs/models/placeholder-cogvideox-vae-tiny"


@pytest.fixture(scope="module")
def vae():
    torch.set_num_threads(1)
    from resim.media.encoders import VideoVAE
    return VideoVAE(VAE_DIR, device="cpu")


def test_decode_frame_counts(vae):
    z = torch.randn(1, 5, 16, 2, 3, generator=torch.Generator().manual_seed(0))
    f3 = decode_latents(vae, z[:, :3])
    f4 = decode_latents(vae, z[:, :4])
    assert f3.shape == (1, 9, 16, 24, 3) and f3.dtype == np.uint8
    assert f4.shape == (1, 13, 16, 24, 3)
    # the even-length padding does not touch the frames of the first (odd) decode batch
    np.testing.assert_array_equal(f4[:, :9], f3)


def test_decode_rollout_count(vae):
    z = torch.randn(1, 3 + 12, 16, 2, 3)
    f = decode_rollout(vae, z, num_history=3, frames_per_round=10, history_frames=3)
    assert f.shape[1] == 9 + 4 * 12            # 9 history pixel frames + 4 per generated latent frame
    first = decode_latents(vae, z[:, :13])
    np.testing.assert_array_equal(f[:, :49], first)


def test_write_rollout(tmp_path):
    frames = (np.random.default_rng(0).random((21, 32, 48, 3)) * 255).astype(np.uint8)
    traj = np.stack([np.arange(1, 9) * 4.0, np.arange(1, 9) * 0.5, np.arange(1, 9) * 0.1], 1)
    p = write_rollout(tmp_path, "x", frames, np.zeros((6, 16, 4, 6), np.float32), num_history_px=9, fps_hz=10,
                      title="Turning left", trajectory=traj)
    for k in ("mp4", "gif", "sheet", "latents", "meta"):
        assert p[k].is_file() and p[k].stat().st_size > 0
    from PIL import Image
    assert Image.open(p["gif"]).n_frames == 21
    from resim.shards.video import decode_mp4
    assert decode_mp4(p["mp4"].read_bytes()).shape[0] == 21
    sheet = contact_sheet(frames, 9, 10.0, title="t", trajectory=traj, count=8)
    assert sheet.width > 8 * 160
