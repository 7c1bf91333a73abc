"""`resim train vae`: diffusers' CogVideoX VAE trained by the common trainer, exported as a diffusers folder
that the pipeline's VideoVAE loads like CogVideoX-2B's."""
import json

import numpy as np
import pytest
import torch

from resim.cli import main
from resim.config import ConfigError
from training.testing import write_world_dataset
from training.vae import build_vae, psnr_db

ARGS = ["--set", "trainer.progress_bar=false", "--set", "trainer.tensorboard=false",
        "--set", "trainer.loss_curve_png=false"]


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _smooth_video(seed=0, t=9, h=32, w=48):
    """A moving colour gradient, (1, T, 3, H, W) uint8: learnable by a tiny VAE in a few dozen steps."""
    g = torch.Generator().manual_seed(seed)
    base = torch.rand(3, 1, 1, generator=g)
    y = torch.linspace(0, 1, h)[:, None]
    x = torch.linspace(0, 1, w)[None, :]
    frames = [(0.5 + 0.4 * torch.sin(6 * (x + 0.05 * k) + 3 * y + 6 * base)).clamp(0, 1) for k in range(t)]
    v = torch.stack(frames) * (0.5 + 0.5 * base[None])
    return (v * 255).round().to(torch.uint8)[None]


def test_loss_learns_a_video():
    torch.manual_seed(0)
    vae = build_vae({"block_out_channels": [8, 8, 8, 8], "norm_num_groups": 2, "clip_frames": 9})
    batch = {"frames": _smooth_video()}
    opt = torch.optim.AdamW(vae.parameters(), lr=3e-3)
    first = None
    for _ in range(40):
        loss, logs = vae.loss(batch)
        opt.zero_grad()
        loss.backward()
        opt.step()
        first = first if first is not None else float(logs["psnr_db"])
    assert float(logs["psnr_db"]) > first + 6.0, (first, float(logs["psnr_db"]))


def test_config_checked():
    with pytest.raises(ConfigError, match="clip_frames"):
        build_vae({"clip_frames": 12})
    with pytest.raises(ConfigError, match="multiples of norm_num_groups"):
        build_vae({"block_out_channels": [8, 12, 16, 16], "norm_num_groups": 8})
    vae = build_vae({"block_out_channels": [8, 8, 8, 8], "norm_num_groups": 2, "clip_frames": 9})
    with pytest.raises(ConfigError, match="load_frames"):
        vae.loss({"frames": None})


def test_detail_terms_and_three_levels():
    """The optional L1 and gradient terms add to the loss and are logged; a 3-level VAE compresses 4x in space."""
    torch.manual_seed(0)
    base = {"block_out_channels": [8, 8, 8, 8], "norm_num_groups": 2, "clip_frames": 9}
    batch = {"frames": _smooth_video()}
    torch.manual_seed(0)
    plain, logs = build_vae(base).loss(batch)
    torch.manual_seed(0)
    more, logs2 = build_vae({**base, "l1_weight": 1.0, "gradient_weight": 2.0}).loss(batch)
    assert float(more) > float(plain) and {"l1", "gradient_l1"} <= set(logs2) and "l1" not in logs
    assert abs(float(more) - float(plain) - float(logs2["l1"]) - 2 * float(logs2["gradient_l1"])) < 1e-5
    with pytest.raises(ConfigError, match="gradient_weight"):
        build_vae({**base, "gradient_weight": -1})
    vae3 = build_vae({**base, "block_out_channels": [8, 8, 8]})
    x = torch.zeros(1, 3, 9, 32, 48)
    assert tuple(vae3.encode(x).latent_dist.mean.shape) == (1, 16, 3, 8, 12)     # 4x spatial, 4x temporal
    with pytest.raises(ConfigError, match="4 widths"):
        build_vae({**base, "block_out_channels": [8, 8]})


def test_spatial_crop_trains_on_a_window_of_the_frames(monkeypatch):
    """model.crop_hw: each step sees one random [h, w] window of the clip (drawn from the global RNG, so exact
    resume holds); the loss is the loss of that window; crops must fit the spatial compression and the clips."""
    base = {"block_out_channels": [8, 8, 8, 8], "norm_num_groups": 2, "clip_frames": 9}
    video = _smooth_video(t=9, h=32, w=48)
    monkeypatch.setattr(torch, "randn_like", torch.zeros_like)      # the posterior mean: only the crop is random
    torch.manual_seed(0)
    vae = build_vae({**base, "crop_hw": [16, 24]})
    torch.manual_seed(1)
    cropped, _ = vae.loss({"frames": video})
    # the same draws by hand: temporal start, top, left
    torch.manual_seed(1)
    start = int(torch.randint(0, 1, ()).item())
    top, left = int(torch.randint(0, 17, ()).item()), int(torch.randint(0, 25, ()).item())
    vae.train_cfg = build_vae(base).train_cfg
    by_hand, _ = vae.loss({"frames": video[:, start:, :, top:top + 16, left:left + 24].contiguous()})
    assert abs(float(cropped) - float(by_hand)) < 1e-6
    with pytest.raises(ConfigError, match="multiples of the spatial compression 8"):
        build_vae({**base, "crop_hw": [12, 24]})
    with pytest.raises(ConfigError, match="larger than the clips"):
        build_vae({**base, "crop_hw": [64, 24]}).loss({"frames": video})


def test_psnr_of_mse_in_minus_one_one():
    # an error of 0.1 in [-1, 1] is 0.05 in [0, 1]: 26.02 dB
    assert abs(float(psnr_db(torch.tensor(0.01))) - 26.0206) < 1e-3


def test_train_export_load_and_exact_resume(tmp_path):
    from media.encoders import VideoVAE

    ds = write_world_dataset(tmp_path / "ds", num_samples=4, per_shard=2)
    full, part = tmp_path / "full", tmp_path / "part"
    common = ["train", "vae", "--preset", "tiny", "--shards", str(ds), *ARGS]
    assert main([*common, "--out", str(full), "--steps", "4"]) == 0
    assert main([*common, "--out", str(part), "--steps", "2"]) == 0
    assert main([*common, "--out", str(part), "--steps", "4", "--resume"]) == 0
    losses = [[json.loads(line)["loss"] for line in open(r / "metrics.jsonl")] for r in (full, part)]
    assert losses[0] == losses[1] and len(losses[0]) == 4

    exported = full / "final" / "vae"
    meta = json.loads((exported / "export.json").read_text())
    cfg = json.loads((exported / "config.json").read_text())
    assert cfg["_class_name"] == "AutoencoderKLCogVideoX"
    assert abs(cfg["scaling_factor"] - 1 / meta["latent_std"]) < 1e-5
    vae = VideoVAE(exported, device="cpu")
    assert not vae.info.placeholder and abs(vae.info.scaling_factor - cfg["scaling_factor"]) < 1e-9
    frames = np.random.default_rng(0).integers(0, 255, (1, 9, 16, 24, 3), dtype=np.uint8)
    assert vae.encode(frames, seeds=[0]).shape == (1, 3, 16, 2, 3)
