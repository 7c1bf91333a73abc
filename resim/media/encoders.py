"""The two frozen encoders of the pipeline: CogVideoX's VAE (video → latents) and T5 (prompt → embedding).

Both load from a local folder, never from the network. A real run points at the released weights
(``--vae /models/CogVideoX-2b`` or ``.../CogVideoX-2b/vae``; ``--text-encoder /models/CogVideoX-2b``
or a folder with the T5 encoder + tokenizer). The default folders under ``configs/models/placeholder-*``
hold only configs (and the tokenizer): when a folder has no weights, the model is built from its config
with weights drawn from ``placeholder_seed`` — deterministic, tiny, and flagged ``placeholder=True`` in
everything it produces so nobody mistakes them for trained weights. Same class, same calls either way.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

# torch, diffusers and transformers (and resim.media.device, which imports torch) are imported where a model is built or
# run, not here: the pipeline's driver imports this module with the encode and prompt stages and stays torch-free;
# the models load in the stages' actors.

WEIGHT_FILES = ("diffusion_pytorch_model.safetensors", "diffusion_pytorch_model.bin", "model.safetensors",
                "pytorch_model.bin", "diffusion_pytorch_model.safetensors.index.json",
                "model.safetensors.index.json", "pytorch_model.bin.index.json")

DTYPES = {"float32": "float32", "float16": "float16", "bfloat16": "bfloat16"}


def _has_weights(folder: Path) -> bool:
    return any((folder / f).is_file() for f in WEIGHT_FILES)


def _resolve(folder: Path, sub: str) -> Path:
    """A diffusers pipeline folder (``X/vae``, ``X/text_encoder``) or the component folder itself."""
    folder = Path(folder)
    return folder / sub if (folder / sub / "config.json").is_file() else folder


class MissingWeightsError(FileNotFoundError):
    """A model folder with a config but no weights, that is not a shipped seeded placeholder."""


def is_placeholder(folder: Path) -> bool:
    """The shipped tiny stand-ins (``configs/models/placeholder-*``): a config only, weights drawn from a seed. Any
    other folder without weights is a missing download, not a placeholder."""
    return Path(folder).name.startswith("placeholder-")


def _seeded_init(build, seed: int):
    """Build a model with parameters drawn from ``seed`` without touching the caller's global RNG."""
    import torch

    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        return build()


# ----------------------------------------------------------------------------------------------- VAE
@dataclass
class VaeInfo:
    vae_id: str
    placeholder: bool
    scaling_factor: float
    temporal_compression: int
    spatial_compression: int
    latent_channels: int


class VideoVAE:
    """CogVideoX VAE encoder with slicing/tiling; ``encode`` returns one posterior sample x scaling factor.

    Input frames: ``(B, T, H, W, 3)`` uint8 RGB (our video layout is (B, T, C, H, W); this takes the
    decoded HWC frames straight from the readers and permutes once). Output: ``(B, T_lat, C, h, w)``
    float32 with ``T_lat = 1 + (T - 1) / 4``, ``h = H / 8``, ``w = W / 8``.
    """

    def __init__(self, folder: str | Path, *, placeholder_seed: int = 0, dtype: str = "float32",
                 device: str | None = None, slicing: bool = True, tiling: bool = True):
        import torch
        from diffusers import AutoencoderKLCogVideoX

        from resim.media.device import resolve_device   # imports torch: lazy, see the note at the top

        folder = _resolve(Path(folder), "vae")
        self.device = device or resolve_device()
        self.dtype = getattr(torch, DTYPES[dtype])
        if _has_weights(folder):
            model = AutoencoderKLCogVideoX.from_pretrained(folder, torch_dtype=self.dtype)
            placeholder = False
        elif not is_placeholder(folder):
            raise MissingWeightsError(f"VAE folder {folder}: config.json but no weights ({WEIGHT_FILES[0]}); a "
                                      "decoder without its weights draws noise (only the shipped placeholder-* "
                                      "folders are built from a seed)")
        else:
            config = AutoencoderKLCogVideoX.load_config(folder)
            model = _seeded_init(lambda: AutoencoderKLCogVideoX.from_config(config), placeholder_seed)
            if self.dtype != torch.float32:   # (to(float32) on a fresh float32 model only warns)
                model = model.to(self.dtype)
            placeholder = True
        model.requires_grad_(False).eval().to(self.device)
        if slicing:
            model.enable_slicing()
        if tiling:
            model.enable_tiling()
        self.model = model
        cfg = model.config
        self.info = VaeInfo(
            vae_id=(folder.parent.name + "/vae") if folder.name == "vae" else folder.name,
            placeholder=placeholder,
            scaling_factor=float(cfg.scaling_factor),
            temporal_compression=int(cfg.temporal_compression_ratio),
            spatial_compression=2 ** (len(cfg.block_out_channels) - 1),
            latent_channels=int(cfg.latent_channels),
        )

    def encode(self, frames_bthwc: np.ndarray, seeds: list[int]) -> np.ndarray:
        """uint8 ``(B, T, H, W, 3)`` → float32 ``(B, T_lat, C, h, w)`` = sample x scaling_factor.

        ``seeds`` (one per clip) fix the posterior sample, so reruns write the same latents.
        """
        import torch

        if frames_bthwc.dtype != np.uint8 or frames_bthwc.ndim != 5 or frames_bthwc.shape[-1] != 3:
            raise ValueError(f"expected uint8 (B, T, H, W, 3), got {frames_bthwc.dtype} {frames_bthwc.shape}")
        if len(seeds) != frames_bthwc.shape[0]:
            raise ValueError(f"{len(seeds)} seeds for {frames_bthwc.shape[0]} clips")
        x = torch.from_numpy(np.ascontiguousarray(frames_bthwc)).to(self.device)
        x = x.permute(0, 4, 1, 2, 3).to(self.dtype) / 127.5 - 1.0      # (B, C, T, H, W) in [-1, 1]
        out = []
        with torch.inference_mode():
            dist = self.model.encode(x).latent_dist                      # slicing splits the batch
            for i, seed in enumerate(seeds):
                g = torch.Generator(device=self.device).manual_seed(int(seed))
                noise = torch.randn(dist.mean[i].shape, generator=g, device=self.device, dtype=dist.mean.dtype)
                z = dist.mean[i] + dist.std[i] * noise                   # = latent_dist.sample() with our noise
                out.append((z * self.info.scaling_factor).permute(1, 0, 2, 3).float().cpu().numpy())
        return np.stack(out)                                             # (B, T_lat, C, h, w)


def to_storage(latent: np.ndarray, latent_dtype: str) -> np.ndarray:
    """float32 latent → stored array: float16, or bfloat16 as its uint16 bit pattern (npy has no bf16)."""
    if latent_dtype == "float16":
        return latent.astype(np.float16)
    if latent_dtype == "bfloat16":
        import torch

        return torch.from_numpy(np.ascontiguousarray(latent, dtype=np.float32)).to(torch.bfloat16) \
            .view(torch.int16).numpy().view(np.uint16)
    raise ValueError(f"unknown latent dtype {latent_dtype!r}")


# ------------------------------------------------------------------------------------------------ T5
@dataclass
class TextInfo:
    encoder_id: str
    placeholder: bool
    max_tokens: int
    dim: int


class TextEncoder:
    """T5 encoder (``transformers.T5EncoderModel``) + tokenizer, padded to ``max_tokens`` (226 for CogVideoX).

    ``encode(texts)`` → float32 ``(N, max_tokens, D)``, the last hidden state including the padded
    positions, exactly as CogVideoX's pipeline feeds its transformer.
    """

    def __init__(self, folder: str | Path, *, max_tokens: int = 226, placeholder_seed: int = 0,
                 device: str | None = None):
        import torch
        from transformers import AutoTokenizer, T5Config, T5EncoderModel

        from resim.media.device import resolve_device   # imports torch: lazy, see the note at the top

        folder = Path(folder)
        enc_dir = _resolve(folder, "text_encoder")
        tok_dir = folder / "tokenizer" if (folder / "tokenizer").is_dir() else enc_dir
        self.device = device or resolve_device()
        self.tokenizer = AutoTokenizer.from_pretrained(tok_dir)
        if _has_weights(enc_dir):
            model = T5EncoderModel.from_pretrained(enc_dir)
            placeholder = False
        else:
            config = T5Config.from_pretrained(enc_dir)
            model = _seeded_init(lambda: T5EncoderModel(config), placeholder_seed)
            placeholder = True
        self.model = model.requires_grad_(False).eval().to(self.device)
        self.torch = torch
        name = enc_dir.parent.name + "/text_encoder" if enc_dir.name == "text_encoder" else enc_dir.name
        self.info = TextInfo(encoder_id=name, placeholder=placeholder, max_tokens=max_tokens,
                             dim=int(model.config.d_model))

    def encode(self, texts: list[str]) -> np.ndarray:
        return self.encode_with_counts(texts)[0]

    def encode_with_counts(self, texts: list[str]) -> tuple[np.ndarray, list[int]]:
        """``encode`` plus each text's token count before padding (the tokenizer's attention-mask sum:
        the text's tokens and the end-of-sequence token, after truncation to ``max_tokens``)."""
        enc = self.tokenizer(list(texts), padding="max_length", max_length=self.info.max_tokens,
                             truncation=True, add_special_tokens=True, return_tensors="pt")
        with self.torch.inference_mode():
            h = self.model(enc.input_ids.to(self.device)).last_hidden_state
        counts = [int(n) for n in enc.attention_mask.sum(dim=1).tolist()]
        return h.float().cpu().numpy(), counts
