#!/usr/bin/env bash
# One leased GPU call for the synthetic world: runs side by side on one card, each stopped by its wall-clock budget
# (trainer.max_wall_s) and packed as soon as it ends into flat files of <= 15 MB for a leased machine's return
# path (at most 8 files). synth-vae's stage 1b is its run V (docs/models/synth-vae.md, "Reproduce").
#
#   V    the VAE: `--preset synth-adv` (the "A2" recipe of the first GPU sweep, which kept the motion best there:
#        MSE + L1 + 2 x gradient L1 + 0.1 x adversarial, a discriminator 32 wide, lr 2e-4, EMA 0.998, batch 16;
#        the small VAE is launch-bound on a GPU, so a larger batch costs little) from the shipped weights, one run
#        for the whole lease
#   V2   the same at batch 32, lr 3e-4
#   W    the world model: the shipped weights + `--preset synth-control` with the pooled text path (ReSim's full-range
#        history noise, trajectory dropped half the time) on WORLD_DATA (latents of the shipped VAE), batch 32
#   WC   the same with `--preset synth-fork` (the command the only condition)
#
# Every run keeps a constant learning rate after warm-up: a wall-clock stop would cut a cosine part-way.
# WALL_S bounds the training loops; each process adds ~30-90 s of start-up, export and packing, so give the
# command WALL_S + 120 s. A leased call carries at most 64 MiB: the repository (~41 MB) and the VAE data (~21 MB)
# leave no room for world-model data beside them, so the default is the two VAE runs, and a world run builds its
# data on the leased machine:
#
#   FORKS=N   WORLD_DATA is built there first: a fork world of N episodes (FORK_SEED, default 84, a seed no run
#             has used), rendered by `resim synth --workers` on the machine's cores and turned into shards by
#             `resim pipeline run` with the local executor (Ray is not installed there; the VAE encodes on the
#             GPU, the flow labeler runs in sequence on one core), as FORKS81-83 were built on the CPU
#             (docs/lab/2026-11-26-synth-world-stage-chain.md). Give the command this step's time as well.
#   EVAL=1    each world run is then read by `resim eval commands --set commands.group_ends=true` on the 36 fork
#             clips of seed 3005, the clips of the command ladder in docs/lab/2026-11-26-synth-world-stage-chain.md
#             (built there beside the training data); its commands.json and pictures go into RUN.logs.tgz
#             (`gpu_unpack.py` puts them in DEST/logs/eval).
#
# Usage: RUNS="V V2" bash scripts/gpu_synth_round.sh OUT_DIR [WALL_S]
#        RUNS=WC FORKS=216 EVAL=1 DEADLINE_S=570 bash scripts/gpu_synth_round.sh OUT_DIR   # the command at scale
#        (env: RUNS, RESIM (may be several words, e.g. "python3 -m resim"), PYTHON, VAE_DATA, WORLD_DATA, WORK,
#        FORKS, FORK_SEED, EVAL, WORKERS; DEADLINE_S: the whole script's seconds, so the training loops get what
#        the data build leaves of them instead of WALL_S, which on a leased machine is not known ahead; SMOKE=1 shrinks the evaluation to one fork (3 clips), 2 DDIM steps and a 6-episode world for a CPU try)
# Output: OUT_DIR/<run>.part<i>.safetensors (float32: a VAE run's exported EMA VAE with its discriminator, a world
# run's EMA weights) and OUT_DIR/<run>.logs.tgz (log, config.yaml, metrics.jsonl, final/ configs). Back on the
# workstation: `python scripts/gpu_unpack.py OUT_DIR RUN DEST`.
set -uo pipefail
OUT=${1:?usage: RUNS="V V2" bash scripts/gpu_synth_round.sh OUT_DIR [WALL_S]}
WALL=${2:-400}
RUNS=${RUNS:-V V2}
read -r -a RESIM <<< "${RESIM:-resim}"
PYTHON=${PYTHON:-python3}
VAE_DATA=${VAE_DATA:-runs/synth/vae_data}
WORK=${WORK:-/tmp/gpu_round}
FORKS=${FORKS:-}
FORK_SEED=${FORK_SEED:-84}
EVAL=${EVAL:-0}
WORKERS=${WORKERS:-14}
WORLD_DATA=${WORLD_DATA:-$([ -n "$FORKS" ] && echo "$WORK/forks$FORK_SEED" || echo runs/fork/data_forks72)}
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
  [W]="--preset synth-control --set model.overrides.text_pool.enabled=true"   # the pooled text path
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
    for f in sorted((work / f"{run}.eval").glob("*")) + [work / f"{run}.eval.log"]:   # EVAL=1
        if f.is_file():
            tar.add(f, arcname=f"{run}/eval/{f.name}")
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

forks() {   # DATASET SEED EPISODES WORKERS: a fork world rendered in parallel, then the pipeline without Ray
  "${RESIM[@]}" synth --out "$1.world" --episodes "$3" --seed "$2" --preset demo --set fork_fraction=1.0 \
      --workers "$4" --quiet \
  && "${RESIM[@]}" pipeline run configs/pipeline/synthetic.yaml --out "$1" --set ray.executor=local \
      --set ray.progress_bars=false --set sources.synthetic.root="$1.world" --set sources.synthetic.seed="$2" \
      --set sources.synthetic.episodes="$3" --set sources.synthetic.fork_fraction=1.0 \
      --set sources.synthetic.preset=demo --set 'sources.synthetic.layouts=[opendv,carla]' \
      --set encode.vae=configs/models/synth-vae
}

t0=$(date +%s)
HELDOUT=$WORK/forks3005
rm -f "$WORK/forks3005.rc"
if [ "$EVAL" = 1 ]; then   # beside the training data: 27 episodes, the seed-3005 world of the ladder
  h_episodes=27
  [ "${SMOKE:-0}" = 1 ] && h_episodes=6
  ( forks "$HELDOUT" 3005 "$h_episodes" 2 >"$WORK/forks3005.log" 2>&1
    rc=$?; echo "$rc" >"$WORK/forks3005.rc"
    echo "[round] seed-3005 clips: exit $rc after $(( $(date +%s) - t0 )) s" ) &
fi
if [ -n "$FORKS" ]; then
  forks "$WORLD_DATA" "$FORK_SEED" "$FORKS" "$WORKERS" >"$WORK/forks$FORK_SEED.log" 2>&1
  rc=$?
  echo "[round] fork world: $FORKS episodes, seed $FORK_SEED, exit $rc after $(( $(date +%s) - t0 )) s"
  tail -n 12 "$WORK/forks$FORK_SEED.log"
  [ "$rc" -eq 0 ] || exit "$rc"
fi
evaluate() {   # RUN: the ladder's command reading (docs/lab/2026-11-26-synth-world-stage-chain.md)
  [ "$EVAL" = 1 ] || return 0
  while [ ! -f "$WORK/forks3005.rc" ]; do sleep 5; done   # built by a sibling process: no `wait` from here
  [ "$(cat "$WORK/forks3005.rc")" = 0 ] || { echo "[round] no seed-3005 clips to read $1 on: $WORK/forks3005.log"; return 1; }
  local n=36 steps=25
  [ "${SMOKE:-0}" = 1 ] && n=3 steps=2
  "${RESIM[@]}" eval commands --checkpoint "$WORK/$1" --shards "$HELDOUT" --all-clips --counterfactual-only \
      --limit "$n" --steps "$steps" --set commands.group_ends=true --out "$WORK/$1.eval" >"$WORK/$1.eval.log" 2>&1
  echo "[round] $1 eval exit $? after $(( $(date +%s) - t0 )) s"; tail -n 8 "$WORK/$1.eval.log"
}
wall=()
if [ -n "${DEADLINE_S:-}" ]; then   # the loops get what is left of the call once the data is built
  reserve=$([ "$EVAL" = 1 ] && echo 210 || echo 90)   # start-up, export, the evaluation and packing after the loop
  left=$(( DEADLINE_S - ($(date +%s) - t0) - reserve ))
  [ "$left" -ge 30 ] || { echo "[round] only ${left} s left for training of DEADLINE_S=$DEADLINE_S: not started" >&2; exit 1; }
  echo "[round] training for ${left} s (DEADLINE_S=$DEADLINE_S)"
  wall=(--set trainer.max_wall_s="$left")
fi
pids=()
for r in $RUNS; do
  case $r in V*) base=("${vae[@]}") ;; W*) base=("${world[@]}") ;; *) echo "unknown run $r" >&2; exit 2 ;; esac
  # shellcheck disable=SC2086  # the per-run options are words
  ( "${RESIM[@]}" "${base[@]}" "${wall[@]}" --out "$WORK/$r" ${args[$r]} >"$WORK/$r.log" 2>&1
    echo "[round] $r exit $? after $(( $(date +%s) - t0 )) s"; tail -n 3 "$WORK/$r.log"
    case $r in W*) evaluate "$r" ;; esac
    pack "$r" ) &
  pids+=($!)
done
for p in "${pids[@]}"; do wait "$p"; done
echo "[round] all done after $(( $(date +%s) - t0 )) s"
ls -la "$OUT"
