"""`resim train vae`: diffusers' CogVideoX VAE trained by the common trainer, exported as a diffusers folder
that the pipeline's VideoVAE loads like CogVideoX-2B's."""
import json

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from safetensors.torch import load_file

from resim.cli import main
from resim.config import ConfigError
from resim.media.encoders import VideoVAE
from tests.support.training import write_world_dataset
from resim.train.tasks.vae import build_vae, psnr_db
from resim.train.tasks.vae_gan import PatchDiscriminator3D, adversarial_losses

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
        build_vae({**base, "block_out_channels": [8]})
    # 2 levels halve time once at most: a 4x temporal ratio needs 3, a per-frame VAE may have 2 (2x spatial)
    with pytest.raises(ConfigError, match="temporal_compression_ratio=4 needs at least 3 widths"):
        build_vae({**base, "block_out_channels": [8, 8]})
    vae2 = build_vae({**base, "block_out_channels": [8, 8], "temporal_compression_ratio": 1})
    assert tuple(vae2.encode(x).latent_dist.mean.shape) == (1, 16, 9, 16, 24)   # 2x spatial, per frame


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


def test_adversarial_terms_reach_only_their_own_player():
    """One backward of the summed loss gives the VAE the generator's gradient and the discriminator its own:
    the generator term leaves the discriminator's weights untouched, the discriminator term the VAE's."""
    base = {"block_out_channels": [8, 8, 8, 8], "norm_num_groups": 2, "clip_frames": 9}
    torch.manual_seed(0)
    vae = build_vae({**base, "adversarial_weight": 0.5, "discriminator_width": 8})
    x = _smooth_video().permute(0, 2, 1, 3, 4).float() / 127.5 - 1.0
    rec = vae.decode(vae.encode(x).latent_dist.mean).sample
    g_loss, d_loss = adversarial_losses(vae.discriminator, x, rec)
    disc = list(vae.discriminator.parameters())
    own = [p for n, p in vae.named_parameters() if not n.startswith("discriminator.")]
    g_grads = torch.autograd.grad(g_loss, own + disc, retain_graph=True, allow_unused=True)
    assert all(g is None for g in g_grads[len(own):])
    assert sum(float(g.abs().sum()) for g in g_grads[:len(own)] if g is not None) > 0
    d_grads = torch.autograd.grad(d_loss, own + disc, allow_unused=True)
    assert all(g is None for g in d_grads[:len(own)])
    # (the last bias gets -1 + 1 = 0 while every hinge is active: check the weights)
    assert all(g is not None for g in d_grads[len(own):])
    assert all(float(g.abs().sum()) > 0 for g, (n, _) in zip(d_grads[len(own):], vae.discriminator.named_parameters())
               if n.endswith("weight"))
    # the summed loss that the trainer back-propagates holds both terms and logs them
    torch.manual_seed(1)
    loss, logs = vae.loss({"frames": _smooth_video()})
    assert {"g_loss", "d_loss"} <= set(logs) and torch.isfinite(loss)
    with pytest.raises(ConfigError, match="adversarial_weight"):
        build_vae({**base, "adversarial_weight": -1})


def test_discriminator_learns_to_tell_a_blurred_video_from_the_real_one():
    """The discriminator is trained by the summed loss alone: after some steps its hinge loss on real vs
    box-blurred frames falls well below the value of a discriminator that cannot tell them apart (2.0)."""
    torch.manual_seed(0)
    real = torch.rand(2, 3, 5, 32, 48) * 2 - 1                               # texture: noise
    fake = F.avg_pool3d(real, (1, 5, 5), stride=1, padding=(0, 2, 2))          # the mean a blurred decoder returns
    disc = PatchDiscriminator3D(8)
    opt = torch.optim.AdamW(disc.parameters(), lr=2e-3)
    for _ in range(40):
        _, d_loss = adversarial_losses(disc, real, fake)
        opt.zero_grad()
        d_loss.backward()
        opt.step()
    assert float(d_loss) < 1.0, float(d_loss)


def test_adversarial_run_exports_a_plain_diffusers_vae_and_restarts_from_it(tmp_path):
    """A run with the adversarial term keeps the discriminator in its weights, exports the VAE without it
    (the folder loads as CogVideoX's does), and a new adversarial run starts from the exported folder with a
    fresh discriminator."""
    ds = write_world_dataset(tmp_path / "ds", num_samples=2, per_shard=2)
    adv = ["--set", "model.adversarial_weight=0.1", "--set", "model.discriminator_width=8"]
    run = tmp_path / "adv"
    common = ["train", "vae", "--preset", "tiny", "--shards", str(ds), *ARGS, *adv]
    assert main([*common, "--out", str(run), "--steps", "2"]) == 0
    rows = [json.loads(line) for line in open(run / "metrics.jsonl")]
    assert all("d_loss" in r and "g_loss" in r for r in rows)
    assert any(k.startswith("discriminator.") for k in load_file(str(run / "final" / "model.safetensors")))
    exported = run / "final" / "vae" / "diffusion_pytorch_model.safetensors"
    assert not any(k.startswith("discriminator.") for k in load_file(str(exported)))
    VideoVAE(run / "final" / "vae", device="cpu")
    again = tmp_path / "again"
    assert main([*common, "--out", str(again), "--steps", "1", "--set", f"model.init_weights={exported}"]) == 0


def test_decoder_only_fine_tune_keeps_the_encoder_and_its_scaling_factor(tmp_path):
    """``model.trainable=decoder``: only the decoder's weights move, and the exported folder keeps the init folder's
    scaling factor, so the latents a world model was trained on stay exactly what they were."""
    ds = write_world_dataset(tmp_path / "ds", num_samples=2, per_shard=2)
    common = ["train", "vae", "--preset", "tiny", "--shards", str(ds), *ARGS]
    assert main([*common, "--out", str(tmp_path / "base"), "--steps", "2"]) == 0
    init = tmp_path / "base" / "final" / "vae"
    dec = tmp_path / "dec"
    assert main([*common, "--out", str(dec), "--steps", "3", "--set", "optim.lr=0.01",
                 "--set", f"model.init_weights={init / 'diffusion_pytorch_model.safetensors'}",
                 "--set", "model.trainable=decoder"]) == 0
    before = load_file(str(init / "diffusion_pytorch_model.safetensors"))
    after = load_file(str(dec / "final" / "vae" / "diffusion_pytorch_model.safetensors"))
    assert before.keys() == after.keys()
    moved = {k.split(".")[0] for k in before if not torch.equal(before[k], after[k])}
    assert moved == {"decoder"}
    scale = [json.loads((d / "config.json").read_text())["scaling_factor"] for d in (init, dec / "final" / "vae")]
    assert scale[0] == scale[1]
    with pytest.raises(ConfigError, match="trainable=decoder needs model.init_weights"):
        build_vae({"block_out_channels": [8, 8, 8, 8], "norm_num_groups": 2,
                   "trainable": "decoder"})
    run_weights = tmp_path / "base" / "final" / "model.safetensors"    # no VAE folder: no scaling factor to keep
    with pytest.raises(ConfigError, match="no .*config.json to read their scaling_factor"):
        build_vae({"block_out_channels": [8, 8, 8, 8], "norm_num_groups": 2, "trainable": "decoder",
                   "init_weights": str(run_weights)})
