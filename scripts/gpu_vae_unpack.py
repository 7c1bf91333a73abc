"""Reassemble a VAE of scripts/gpu_vae_sweep.sh into a diffusers folder (float32) that
``AutoencoderKLCogVideoX.from_pretrained`` and ``resim eval vae --vae`` load.

    python scripts/gpu_vae_unpack.py SWEEP_OUT RUN DEST     # e.g. OUT B2 runs/gpu_vae/B2

The sweep brings each exported VAE back in float16, split into parts of at most 15 MB (a leased machine returns
at most 8 files of 16 MB); logs.tgz holds each run's config.json, export.json, config.yaml and metrics.jsonl.
"""
from __future__ import annotations

import sys
import tarfile
from pathlib import Path

from safetensors.torch import load_file, save_file


def main(src: str, run: str, dest: str) -> None:
    src_dir, out = Path(src), Path(dest)
    parts = sorted(src_dir.glob(f"{run}.part*.safetensors")) or [src_dir / f"{run}.safetensors"]
    if not parts[0].is_file():
        raise SystemExit(f"{src_dir}: no weights of run {run!r}")
    state = {}
    for p in parts:
        state.update({k: v.float() for k, v in load_file(str(p)).items()})
    out.mkdir(parents=True, exist_ok=True)
    with tarfile.open(src_dir / "logs.tgz") as tar:
        for m in tar.getmembers():
            if m.name.startswith(f"{run}/") and m.isfile():
                (out / Path(m.name).name).write_bytes(tar.extractfile(m).read())
    vae = out / "vae"
    vae.mkdir(exist_ok=True)
    (out / "config.json").replace(vae / "config.json")
    save_file(state, str(vae / "diffusion_pytorch_model.safetensors"))
    print(f"{vae}: {sum(v.numel() for v in state.values()):,} parameters from {len(parts)} file(s)")


if __name__ == "__main__":
    if len(sys.argv) != 4:
        raise SystemExit(__doc__)
    main(*sys.argv[1:])
