#!/usr/bin/env bash
# Synthetic-world VAE runs side by side on one GPU, each for a wall-clock budget (trainer.max_wall_s), packed
# into at most 8 flat files for a leased machine's return path (its one H100 call, 2026-11-27:
# docs/lab/2026-11-26-synth-vae-4x.md).
#
#   A   the shipped widths (16-32-64-64) from the shipped weights: MSE + L1 + 2 x gradient L1 + 0.05 x adversarial
#       (the CPU run `runs/vae_gan2`'s recipe, 4x its batch)
#   B1  wide (32-64-128-128, 10.3 M parameters) from scratch: MSE + L1 + 2 x gradient L1
#   B2  B1's EMA weights + 0.05 x adversarial (B1 -> B2 in sequence; together they take A's wall time)
#   A2  as A with a stronger adversary: a discriminator twice as wide (32) at twice the weight (0.1)
#
# The small VAE is launch-bound on a GPU (small 3D convolutions), so the runs share the card at little cost to
# each. Every run keeps a constant learning rate after warm-up: a wall-clock stop cuts a cosine part-way.
#
# WALL_S bounds the training loops; each process adds ~30-60 s of start-up and export, so give the command
# WALL_S + 120 s. Usage: bash scripts/gpu_vae_sweep.sh OUT_DIR [WALL_S]        (env: RESIM, PYTHON, DATA, BATCH, WORKERS, WORK)
# Output: OUT_DIR/{A,A2}.safetensors, OUT_DIR/{B1,B2}.part{0,1}.safetensors (the exported EMA VAEs in float16,
# split where one would pass 15 MB), OUT_DIR/logs.tgz (each run's config.yaml, metrics.jsonl, final/vae/config.json
# and export.json, and the discriminator's last weights). Reassemble with scripts/gpu_unpack.py.
set -uo pipefail
OUT=${1:?usage: bash scripts/gpu_vae_sweep.sh OUT_DIR [WALL_S]}
WALL=${2:-420}
RESIM=${RESIM:-resim}
DATA=${DATA:-runs/synth/vae_data}
BATCH=${BATCH:-8}
WORKERS=${WORKERS:-3}
WORK=${WORK:-/tmp/vae_sweep}
mkdir -p "$OUT" "$WORK"
export OMP_NUM_THREADS=${OMP_NUM_THREADS:-4} PYTHONUNBUFFERED=1

common=(--preset synth --shards "$DATA" --set data.batch_size_per_gpu="$BATCH" --set data.num_workers="$WORKERS"
        --set optim.schedule=constant --set trainer.steps=1000000 --set trainer.checkpoint_every_steps=2000
        --set trainer.progress_bar=false --set trainer.log_every_steps=250 --set model.l1_weight=1.0
        --set model.gradient_weight=2.0)
wide=(--set 'model.block_out_channels=[32,64,128,128]')
gan_tune=(--set model.adversarial_weight=0.05 --set optim.lr=2e-4 --set optim.warmup_steps=50
          --set trainer.ema_decay=0.998)
scratch=(--set optim.lr=5e-4 --set optim.warmup_steps=200 --set trainer.ema_decay=0.999)
b1_wall=$((WALL * 65 / 100))

t0=$(date +%s)
"$RESIM" train vae "${common[@]}" "${gan_tune[@]}" --out "$WORK/A" --set trainer.max_wall_s="$WALL" \
    --set model.init_weights=configs/models/synth-vae/diffusion_pytorch_model.safetensors \
    --set model.discriminator_width=16 >"$WORK/A.log" 2>&1 &
pa=$!
( "$RESIM" train vae "${common[@]}" "${wide[@]}" "${scratch[@]}" --out "$WORK/B1" \
      --set trainer.max_wall_s="$b1_wall" >"$WORK/B1.log" 2>&1 &&
  # B2 gets what is left of WALL: B1's start-up and export took 140 s on an H100 machine (the export measures
  # the latent scale on the CPU), and a fixed share overran the lease once
  b2_wall=$((WALL - ($(date +%s) - t0) - 40)) &&
  "$RESIM" train vae "${common[@]}" "${wide[@]}" "${gan_tune[@]}" --out "$WORK/B2" \
      --set model.init_weights="$WORK/B1/final/ema.safetensors" --set trainer.max_wall_s="$((b2_wall > 30 ? b2_wall : 30))" \
      >"$WORK/B2.log" 2>&1 ) &
pb=$!
"$RESIM" train vae "${common[@]}" "${gan_tune[@]}" --out "$WORK/A2" --set trainer.max_wall_s="$WALL" \
    --set model.init_weights=configs/models/synth-vae/diffusion_pytorch_model.safetensors \
    --set model.discriminator_width=32 --set model.adversarial_weight=0.1 >"$WORK/A2.log" 2>&1 &
pc=$!
wait $pa; ra=$?; wait $pb; rb=$?; wait $pc; rc=$?
echo "[sweep] exit codes A=$ra B1+B2=$rb A2=$rc after $(( $(date +%s) - t0 )) s"
for r in A A2 B1 B2; do echo "== $r"; tail -n 4 "$WORK/$r.log" 2>/dev/null; done

"${PYTHON:-python3}" - "$WORK" "$OUT" <<'EOF'
import json, sys, tarfile
from pathlib import Path
import torch
from safetensors.torch import load_file, save_file

work, out = Path(sys.argv[1]), Path(sys.argv[2])
limit = 15 * 2**20
with tarfile.open(out / "logs.tgz", "w:gz") as tar:
    for run in ("A", "A2", "B1", "B2"):
        d = work / run
        for f in (work / f"{run}.log", d / "config.yaml", d / "metrics.jsonl", d / "final/vae/config.json",
                  d / "final/vae/export.json"):
            if f.is_file():
                tar.add(f, arcname=f"{run}/{f.name}")
        vae = d / "final/vae/diffusion_pytorch_model.safetensors"
        if not vae.is_file():
            print(f"[sweep] {run}: no exported VAE")
            continue
        raw = load_file(str(d / "final/model.safetensors"))
        disc = {k: v for k, v in raw.items() if k.startswith("discriminator.")}
        if disc:
            save_file({k: v.half() for k, v in disc.items()}, str(work / f"{run}_discriminator.safetensors"))
            tar.add(work / f"{run}_discriminator.safetensors", arcname=f"{run}/discriminator.safetensors")
        sd = {k: v.half().contiguous() for k, v in load_file(str(vae)).items()}
        parts, cur, size = [], {}, 0
        for k, v in sd.items():
            if cur and size + v.numel() * 2 > limit:
                parts.append(cur); cur, size = {}, 0
            cur[k] = v; size += v.numel() * 2
        parts.append(cur)
        for i, p in enumerate(parts):
            name = f"{run}.safetensors" if len(parts) == 1 else f"{run}.part{i}.safetensors"
            save_file(p, str(out / name))
        steps = [json.loads(l)["step"] for l in open(d / "metrics.jsonl")]
        print(f"[sweep] {run}: {steps[-1]} steps, {len(parts)} file(s)")
EOF
ls -la "$OUT"
