"""CogVideoX's causal 3D VAE as a trainable unit (registry name ``vae``): ``resim train vae``.

The model *is* diffusers' ``AutoencoderKLCogVideoX`` (a subclass adding ``loss``), so its state dict, its
``final/model.safetensors`` and the exported folder are exactly what ``AutoencoderKLCogVideoX.from_pretrained``
reads: the pipeline's ``VideoVAE`` loads a trained synthetic-world VAE with the same code as CogVideoX-2B's.

Objective: reconstruction MSE in [-1, 1] pixels + ``kl_weight`` x the posterior's KL to N(0, I) per latent
value. CogVideoX trained its VAE with L1 + LPIPS + KL + a GAN loss (Yang et al. 2024, Sec. 2.1); by default we
keep MSE + KL: our target is reconstruction PSNR, which MSE optimises directly. Optional terms: L1, L1 on the
spatial gradients, a motion term (the error must move with the original's optical flow, resim/train/tasks/vae_motion.py),
and an adversarial term against a spatio-temporal patch discriminator trained from scratch with the VAE
(``adversarial_weight``, resim/train/tasks/vae_gan.py); LPIPS needs downloaded weights and is left out. The small KL
weight keeps the latent close to a unit Gaussian scale without limiting detail (as Stable Diffusion's 1e-6). The
discriminator lives in the trained model (``discriminator.*`` in the run's weights) and is dropped from the
exported folder.

Each step crops ``clip_frames`` (1 + 8k) consecutive frames of every clip: 17 frames run the encoder's first
9-frame chunk and one cached 8-frame chunk, i.e. the same causal-cache path as a 49-frame clip at inference.

After training, :func:`export_vae` writes ``final/vae/`` (``save_pretrained``: config.json +
diffusion_pytorch_model.safetensors) with ``scaling_factor`` = 1 / std of the training latents, the
convention of Stable Diffusion and CogVideoX: the world model then sees latents of unit variance. A decoder-only
run (``model.trainable: decoder``) keeps its init folder's scaling factor instead: its latents are the init's.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Literal, Optional

import torch
import torch.nn.functional as F
import yaml
from diffusers import AutoencoderKLCogVideoX
from safetensors.torch import load_file

from resim.config import ConfigError, from_dict, safe_yaml
from resim.models.exported import ExportError, read_weights
from resim.train.tasks.vae_gan import PatchDiscriminator3D, adversarial_losses
from resim.train.tasks.vae_motion import backward_flow, motion_l1

DISCRIMINATOR_PREFIX = "discriminator."   # its weights in a run's state dict; never in an exported VAE


@dataclass
class VaeTrainConfig:
    """The ``model:`` section of ``resim train vae``: the VAE's widths and the objective."""

    block_out_channels: tuple[int, ...] = (32, 64, 64, 64)  # 4 levels: 8x spatial compression
    layers_per_block: int = 1
    latent_channels: int = 16
    norm_num_groups: int = 8
    temporal_compression_ratio: int = 4
    clip_frames: int = 17                 # frames per training crop (1 + 8k)
    # random spatial crop [height, width] px per step (None: whole frames). CogVideoX trains its VAE on crops of
    # its videos: the network is convolutional, so a crop costs its share of the pixels and teaches the same
    # weights; it is what lets a wider first level (the width the encoder averages frame pairs at) train on a CPU
    crop_hw: Optional[tuple[int, int]] = None
    kl_weight: float = 1e-6
    # detail terms (0 = off): L1 on the pixels (CogVideoX trains its VAE with L1, sharper than MSE's mean) and L1 on
    # the spatial gradients (the edges and texture the optical-flow labeler tracks; MSE alone averages them away)
    l1_weight: float = 0.0
    gradient_weight: float = 0.0
    # motion term (0 = off): L1 of the reconstruction error's change along the original's optical flow, i.e. the
    # error must move with the scene (resim/train/tasks/vae_motion.py): texture that stays put while the camera turns is what
    # the flow labeler cannot read through the VAE
    motion_weight: float = 0.0
    # adversarial term (0 = off): weight of the generator's hinge loss against a 3D patch discriminator
    # (resim/train/tasks/vae_gan.py) that is trained in the same step; discriminator_width: its first layer's channels
    adversarial_weight: float = 0.0
    discriminator_width: int = 32
    # the discriminator's hinge loss enters the summed loss x this. AdamW's update of a parameter does not change
    # when its loss is scaled by a constant, so the discriminator learns as it would unscaled; but the trainer
    # clips the one global gradient norm over both players. Unscaled, that norm went from ~1.5 (the VAE alone)
    # to 20-40 and the clipping shrank and jittered the VAE's steps with it: from synth-vae's stage 1, training
    # PSNR fell 28.9 -> 23.6 dB in 230 steps (docs/lab/2026-11-26-synth-vae-4x.md, 2026-11-27)
    discriminator_loss_scale: float = 0.02
    init_weights: Optional[Path] = None   # a run's final/model.safetensors to start from
    # which weights train (as the world model's model.trainable). "decoder" needs init_weights from a VAE folder:
    # the encoder and so the latents stay exactly those a world model was trained on, so a better decoder can
    # replace the shipped one without re-encoding the world model's data or retraining it; the export keeps the
    # folder's scaling_factor for the same reason
    trainable: Literal["all", "decoder"] = "all"

    def __post_init__(self):
        # 4 levels: 8x spatial compression, as CogVideoX. 3 (4x) or 2 (2x) for the synthetic world's 64x96 clips:
        # at 8x its 8x12 latent grid could not keep the texture the optical flow reads
        # (docs/lab/2026-11-26-synth-vae-4x.md, 2026-11-26).
        # Each level below the top halves time too until the temporal ratio is reached, so 4x time needs 3 levels
        if len(self.block_out_channels) not in (2, 3, 4):
            raise ConfigError("model.block_out_channels needs 4 widths (8x spatial compression, as CogVideoX), "
                              "3 (4x) or 2 (2x)")
        if 2 ** (len(self.block_out_channels) - 1) < self.temporal_compression_ratio:
            raise ConfigError(f"model.temporal_compression_ratio={self.temporal_compression_ratio} needs at least "
                              f"{self.temporal_compression_ratio.bit_length()} widths in model.block_out_channels")
        if any(c % self.norm_num_groups for c in self.block_out_channels):
            raise ConfigError(f"model.block_out_channels {self.block_out_channels} must be multiples of "
                              f"norm_num_groups={self.norm_num_groups}")
        if self.clip_frames < 9 or (self.clip_frames - 1) % 8:
            raise ConfigError(f"model.clip_frames must be 1 + 8k with k >= 1 (the encoder's frame chunks), "
                              f"got {self.clip_frames}")
        f = 2 ** (len(self.block_out_channels) - 1)    # the loader has checked two integers
        if self.crop_hw is not None and any(v < f or v % f for v in self.crop_hw):
            raise ConfigError(f"model.crop_hw must be [height, width] in multiples of the spatial compression "
                              f"{f}, got {list(self.crop_hw)}")
        if self.kl_weight < 0 or self.latent_channels < 1 or self.layers_per_block < 1:
            raise ConfigError("model.kl_weight must be >= 0, latent_channels and layers_per_block >= 1")
        if not (self.l1_weight >= 0 and self.gradient_weight >= 0 and self.adversarial_weight >= 0
                and self.motion_weight >= 0):
            raise ConfigError("model.l1_weight, model.gradient_weight, model.motion_weight and "
                              "model.adversarial_weight must be >= 0")
        if not self.discriminator_loss_scale > 0:
            raise ConfigError(f"model.discriminator_loss_scale must be > 0, got {self.discriminator_loss_scale}")
        if self.trainable == "decoder" and self.init_weights is None:
            raise ConfigError("model.trainable=decoder needs model.init_weights: a trained VAE whose encoder to keep")
        if self.discriminator_width < 8 or self.discriminator_width % 8:
            raise ConfigError(f"model.discriminator_width must be a multiple of 8, got {self.discriminator_width}")


def diffusers_config(cfg: VaeTrainConfig) -> dict[str, Any]:
    n = len(cfg.block_out_channels)
    return dict(in_channels=3, out_channels=3, block_out_channels=tuple(cfg.block_out_channels),
                layers_per_block=cfg.layers_per_block, latent_channels=cfg.latent_channels,
                norm_num_groups=cfg.norm_num_groups, temporal_compression_ratio=cfg.temporal_compression_ratio,
                down_block_types=("CogVideoXDownBlock3D",) * n, up_block_types=("CogVideoXUpBlock3D",) * n,
                use_quant_conv=False, use_post_quant_conv=False, scaling_factor=1.0)


def frames_to_input(frames: torch.Tensor) -> torch.Tensor:
    """uint8 ``(B, T, 3, H, W)`` 0..255 → float ``(B, 3, T, H, W)`` in [-1, 1] (diffusers' VAE layout)."""
    return frames.permute(0, 2, 1, 3, 4).float() / 127.5 - 1.0


def gradient_l1(rec: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """Mean |∇rec − ∇x| over horizontal and vertical neighbour differences of ``(B, C, T, H, W)`` video."""
    dx = (rec[..., :, 1:] - rec[..., :, :-1]) - (x[..., :, 1:] - x[..., :, :-1])
    dy = (rec[..., 1:, :] - rec[..., :-1, :]) - (x[..., 1:, :] - x[..., :-1, :])
    return 0.5 * (dx.abs().mean() + dy.abs().mean())


def psnr_db(mse: torch.Tensor) -> torch.Tensor:
    """PSNR of images in [0, 1] from an MSE measured in [-1, 1] (the range is twice as wide: 4 / mse)."""
    return 10.0 * torch.log10(4.0 / mse.clamp_min(1e-12))


class TrainableVAE(AutoencoderKLCogVideoX):
    """``AutoencoderKLCogVideoX`` + ``loss(batch)``; same parameters and names as the diffusers class."""

    train_cfg: VaeTrainConfig

    def loss(self, batch) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """``batch.frames`` uint8 ``(B, T, 3, H, W)`` (``data.load_frames``) → (MSE + kl_weight * KL [+ l1_weight *
        L1 + gradient_weight * gradient L1 + motion_weight * motion L1 + adversarial_weight * generator hinge +
        discriminator_loss_scale * discriminator hinge], logs).
        The two hinge terms reach only their own player's weights (resim/train/tasks/vae_gan.py)."""
        frames = batch.frames if not isinstance(batch, dict) else batch["frames"]
        if frames is None:
            raise ConfigError("resim train vae needs the clips' frames: set data.load_frames=true")
        n = self.train_cfg.clip_frames
        t = frames.shape[1]
        if t < n:
            raise ConfigError(f"clips have {t} frames, fewer than model.clip_frames={n}")
        start = int(torch.randint(0, t - n + 1, ()).item())          # global RNG: checkpointed, exact resume
        clip = frames[:, start:start + n]
        if self.train_cfg.crop_hw is not None:
            (ch, cw), (h, w) = self.train_cfg.crop_hw, clip.shape[-2:]
            if ch > h or cw > w:
                raise ConfigError(f"model.crop_hw={list(self.train_cfg.crop_hw)} is larger than the clips' {h}x{w}")
            top = int(torch.randint(0, h - ch + 1, ()).item())
            left = int(torch.randint(0, w - cw + 1, ()).item())
            clip = clip[..., top:top + ch, left:left + cw]
        x = frames_to_input(clip)
        with torch.set_grad_enabled(torch.is_grad_enabled() and self.train_cfg.trainable == "all"):
            post = self.encode(x).latent_dist
        z = post.mean + post.std * torch.randn_like(post.mean)
        rec = self.decode(z).sample
        mse = F.mse_loss(rec, x)
        kl = 0.5 * (post.mean.pow(2) + post.var - 1.0 - post.logvar).mean()
        c = self.train_cfg
        loss = mse + c.kl_weight * kl
        logs = {"mse": mse.detach(), "psnr_db": psnr_db(mse.detach()), "kl": kl.detach(),
                "latent_std": post.mean.detach().std()}
        if c.l1_weight:
            l1 = (rec - x).abs().mean()
            loss = loss + c.l1_weight * l1
            logs["l1"] = l1.detach()
        if c.gradient_weight:
            g = gradient_l1(rec, x)
            loss = loss + c.gradient_weight * g
            logs["gradient_l1"] = g.detach()
        if c.motion_weight:
            m = motion_l1(rec, x, backward_flow(clip).to(x.device))
            loss = loss + c.motion_weight * m
            logs["motion_l1"] = m.detach()
        if self.discriminator is not None:   # build_vae sets it: a module, or None (no adversarial term)
            g_loss, d_loss = adversarial_losses(self.discriminator, x, rec)
            loss = loss + c.adversarial_weight * g_loss + c.discriminator_loss_scale * d_loss
            logs["g_loss"], logs["d_loss"] = g_loss.detach(), d_loss.detach()
        return loss, logs

    def export_run(self, run_dir: str | Path, data: Iterable) -> Path:
        """After training (rank 0): the diffusers folder ``RUN/final/vae`` (:func:`export_vae`)."""
        return export_vae(run_dir, data)

    def fsdp_units(self):
        return [*self.encoder.down_blocks, *self.decoder.up_blocks]

    def set_activation_checkpointing(self, on: bool = True, every_blocks: int = 1) -> None:
        if on and every_blocks != 1:
            raise ConfigError("trainer.activation_checkpointing_every_blocks: the VAE checkpoints all of its "
                              "blocks or none (diffusers' gradient checkpointing); leave it at 1")
        if on:
            self.enable_gradient_checkpointing()
        else:
            self.disable_gradient_checkpointing()


def build_vae(model_cfg: dict, *, device: str | torch.device = "cpu") -> TrainableVAE:
    cfg = from_dict(VaeTrainConfig, model_cfg, prefix="model")
    with torch.device(device):
        model = TrainableVAE.from_config(diffusers_config(cfg))
        model.discriminator = PatchDiscriminator3D(cfg.discriminator_width) if cfg.adversarial_weight > 0 else None
    model.train_cfg = cfg
    if cfg.init_weights is not None:
        if not Path(cfg.init_weights).is_file():
            raise ConfigError(f"model.init_weights={cfg.init_weights} does not exist")
        # a VAE folder's or a run's weights; a discriminator missing from them starts fresh, one in them that
        # this model does not have is left out: the VAE's own weights must all be there
        try:   # a pickle or torch file: never unpickled, one line
            state = read_weights(cfg.init_weights)
        except ExportError as e:
            raise ConfigError(f"model.init_weights={e}") from None
        if model.discriminator is None:
            state = vae_weights(state)
        missing, unexpected = model.load_state_dict(state, strict=False)
        missing = [k for k in missing if not k.startswith(DISCRIMINATOR_PREFIX)]
        if missing or unexpected:
            raise ConfigError(f"model.init_weights={cfg.init_weights} does not fit this VAE: "
                              f"{len(missing)} missing weights (e.g. {missing[:2]}), "
                              f"{len(unexpected)} unexpected (e.g. {unexpected[:2]})")
    if cfg.trainable == "decoder":
        init_scaling_factor(cfg.init_weights)    # the export needs it: fail now, not after training
        model.encoder.requires_grad_(False)
    return model


def vae_weights(state: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """A run's state dict without the discriminator's weights: what ``AutoencoderKLCogVideoX`` loads."""
    return {k: v for k, v in state.items() if not k.startswith(DISCRIMINATOR_PREFIX)}


@torch.inference_mode()
def latent_std(vae: AutoencoderKLCogVideoX, batches: Iterable, max_batches: int = 8) -> float:
    """Std of posterior samples over a few batches (the scaling factor is its inverse)."""
    vals = []
    for i, b in enumerate(batches):
        if i >= max_batches:
            break
        post = vae.encode(frames_to_input(b.frames)).latent_dist
        vals.append((post.mean + post.std * torch.randn_like(post.mean)).flatten())
    if not vals:
        raise ConfigError("no batches to measure the latent scale on")
    return float(torch.cat(vals).std())


def init_scaling_factor(init_weights: str | Path) -> float:
    """The ``scaling_factor`` of the VAE folder that ``init_weights`` lies in (its ``config.json``)."""
    config = Path(init_weights).parent / "config.json"
    if not config.is_file():
        raise ConfigError(f"model.trainable=decoder keeps the latents of model.init_weights={init_weights}, but "
                          f"there is no {config} to read their scaling_factor from: start from a VAE folder's weights")
    return float(json.loads(config.read_text())["scaling_factor"])


def export_vae(run_dir: str | Path, batches: Iterable, out: str | Path | None = None) -> Path:
    """``RUN/final/model.safetensors`` → a diffusers folder (default ``RUN/final/vae``) with the measured
    ``scaling_factor``; loads with ``AutoencoderKLCogVideoX.from_pretrained`` / ``resim.media.encoders.VideoVAE``."""
    run_dir = Path(run_dir)
    out = Path(out) if out is not None else run_dir / "final" / "vae"

    cfg = from_dict(VaeTrainConfig, safe_yaml((run_dir / "config.yaml").read_text())["model"], prefix="model")
    vae = AutoencoderKLCogVideoX.from_config(diffusers_config(cfg))
    weights = run_dir / "final" / ("ema.safetensors" if (run_dir / "final" / "ema.safetensors").is_file()
                                   else "model.safetensors")
    vae.load_state_dict(vae_weights(load_file(str(weights))))
    vae.eval()
    if cfg.trainable == "decoder":
        # the latents are the init's: keep the scaling factor the world model's latents were scaled by
        std, scale = None, init_scaling_factor(cfg.init_weights)
    else:
        std = latent_std(vae, batches)
        scale = round(1.0 / std, 6)
    vae.register_to_config(scaling_factor=scale)
    vae.save_pretrained(out, safe_serialization=True)
    meta = {"weights": str(weights.name), "scaling_factor": scale,
            **({"latent_std": std} if std is not None else {"scaling_factor_of": str(cfg.init_weights)})}
    (out / "export.json").write_text(json.dumps(meta, indent=2) + "\n")
    return out
