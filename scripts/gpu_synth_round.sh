#!/usr/bin/env bash
# One leased GPU call for the synthetic world: runs side by side on one card, each stopped by its wall-clock budget
# (trainer.max_wall_s) and packed as soon as it ends into flat files of <= 15 MB for a leased machine's return
# path (at most 8 files; docs/models/synth-vae.md and synth-world.md, "On a GPU").
#
#   V    the VAE: `--preset synth-adv` (the "A2" recipe of the first GPU sweep, which kept the motion best there:
#        MSE + L1 + 2 x gradient L1 + 0.1 x adversarial, a discriminator 32 wide, lr 2e-4, EMA 0.998, batch 16;
#        the small VAE is launch-bound on a GPU, so a larger batch costs little) from the shipped weights, one run
#        for the whole lease
#   V2   the same at batch 32, lr 3e-4
#   W    the world model: the shipped weights + `--preset synth-command` (pooled text path, ReSim's full-range
#        history noise, trajectory dropped half the time) on WORLD_DATA (latents of the shipped VAE), batch 32
#   WC   the same with `--preset synth-fork` (the command the only condition)
#
# Every run keeps a constant learning rate after warm-up: a wall-clock stop would cut a cosine part-way.
# WALL_S bounds the training loops; each process adds ~30-90 s of start-up, export and packing, so give the
# command WALL_S + 120 s. A leased call carries at most 64 MiB: the repository (~37 MB) and the VAE data (~21 MB)
# leave no room for world-model data beside them, so the default is the two VAE runs.
#
# Usage: RUNS="V V2" bash scripts/gpu_synth_round.sh OUT_DIR [WALL_S]
#        (env: RUNS, RESIM, PYTHON, VAE_DATA, WORLD_DATA, WORK)
# Output: OUT_DIR/<run>.part<i>.safetensors (float32: a VAE run's exported EMA VAE with its discriminator, a world
# run's EMA weights) and OUT_DIR/<run>.logs.tgz (log, config.yaml, metrics.jsonl, final/ configs). Back on the
# workstation: `python scripts/gpu_unpack.py OUT_DIR RUN DEST`.
set -uo pipefail
OUT=${1:?usage: RUNS="V V2" bash scripts/gpu_synth_round.sh OUT_DIR [WALL_S]}
WALL=${2:-400}
RUNS=${RUNS:-V V2}
RESIM=${RESIM:-resim}
PYTHON=${PYTHON:-python3}
VAE_DATA=${VAE_DATA:-runs/synth/vae_data}
WORLD_DATA=${WORLD_DATA:-runs/fork/data_forks72}
WORK=${WORK:-/tmp/gpu_round}
mkdir -p "$OUT" "$WORK"
OUT=$(cd "$OUT" && pwd)
export OMP_NUM_THREADS=${OMP_NUM_THREADS:-4} PYTHONUNBUFFERED=1
common=(--set trainer.progress_bar=false --set trainer.max_wall_s="$WALL" --set trainer.steps=1000000
        --set optim.schedule=constant --set trainer.checkpoint_every_steps=1000000 --set trainer.log_every_steps=100)
vae=(train vae --preset synth-adv --shards "$VAE_DATA" "${common[@]}" --set data.num_workers=4
     --set model.init_weights=configs/models/synth-vae/diffusion_pytorch_model.safetensors)
world=(train world --shards "$WORLD_DATA" "${common[@]}" --set data.batch_size_per_gpu=32 --set data.num_workers=3
       --set optim.warmup_steps=100 --set model.init_weights=configs/models/synth-world/model.safetensors)
declare -A args=(
  [V]=""
  [V2]="--set data.batch_size_per_gpu=32 --set optim.lr=3e-4"
  [W]="--preset synth-command"
  [WC]="--preset synth-fork"
)

pack() {   # RUN: its weights in parts of <= 15 MB, its logs in RUN.logs.tgz
  "$PYTHON" - "$WORK" "$OUT" "$1" <<'EOF'
import json, sys, tarfile
from pathlib import Path
from safetensors.torch import load_file, save_file

work, out, run = Path(sys.argv[1]), Path(sys.argv[2]), sys.argv[3]
d = work / run
with tarfile.open(out / f"{run}.logs.tgz", "w:gz") as tar:
    for f in [work / f"{run}.log", d / "config.yaml", d / "metrics.jsonl"] + sorted((d / "final").rglob("*")):
        if f.is_file() and f.suffix != ".safetensors":
            tar.add(f, arcname=f"{run}/{f.relative_to(d) if f.is_relative_to(d) else f.name}")
vae = d / "final/vae/diffusion_pytorch_model.safetensors"
main = vae if vae.is_file() else d / "final/ema.safetensors"
if not main.is_file():
    sys.exit(f"[round] {run}: no final weights")
state = load_file(str(main))
if vae.is_file():   # the discriminator too, to continue the adversarial run elsewhere
    state.update({k: v for k, v in load_file(str(d / "final/model.safetensors")).items()
                  if k.startswith("discriminator.")})
parts, cur, size = [], {}, 0
for k, v in state.items():
    n = v.numel() * v.element_size()
    if cur and size + n > 15 * 2**20:
        parts.append(cur); cur, size = {}, 0
    cur[k] = v.contiguous(); size += n
parts.append(cur)
for i, p in enumerate(parts):
    save_file(p, str(out / f"{run}.part{i}.safetensors"))
steps = [json.loads(l)["step"] for l in open(d / "metrics.jsonl")]
print(f"[round] {run}: {steps[-1]} steps, {len(parts)} file(s)")
EOF
}

t0=$(date +%s)
pids=()
for r in $RUNS; do
  case $r in V*) base=("${vae[@]}") ;; W*) base=("${world[@]}") ;; *) echo "unknown run $r" >&2; exit 2 ;; esac
  # shellcheck disable=SC2086  # the per-run options are words
  ( "$RESIM" "${base[@]}" --out "$WORK/$r" ${args[$r]} >"$WORK/$r.log" 2>&1
    echo "[round] $r exit $? after $(( $(date +%s) - t0 )) s"; tail -n 3 "$WORK/$r.log"; pack "$r" ) &
  pids+=($!)
done
for p in "${pids[@]}"; do wait "$p"; done
echo "[round] all done after $(( $(date +%s) - t0 )) s"
ls -la "$OUT"
