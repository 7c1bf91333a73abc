#!/usr/bin/env bash
# Reproduce the synthetic world's models from a fresh clone on a CPU, with the commands a user runs:
#   1. the per-frame VAE (`resim train vae --preset synth-frame`; its candidate so far: lab/runs/synth-vae-frame);
#   2. the world model's data: `resim pipeline run configs/pipeline/synth-world.yaml` through that VAE;
#   3. the world model (`resim train world --preset synth-world`), one run, in budgeted segments that resume.
# Records: docs/lab/2026-12-07-representation.md, docs/lab/2026-12-07-world-recipe.md; cards: docs/models/.
#
#   bash scripts/setup.sh && bash scripts/train_synth_world.sh [WORK_DIR]        (default WORK_DIR: runs/synth-world)
#
# Each step is skipped when its output exists; training resumes from its last checkpoint. Environment:
#   SEGMENT_S   wall seconds of world-model training per call (default 3600); call again to go on
#   TOTAL_STEPS stop the world model at this many steps (default: the preset's 100,000, i.e. the budget decides)
#   THREADS     torch threads for training (default 2: the whole 2-core machine)
#   VAE=PATH    skip step 1 and encode with this VAE folder (e.g. lab/runs/synth-vae-frame)
# Time on the shared 2-core x86-64 CPU: step 1 ~45 min, step 2 ~20 min, step 3 as budgeted.
set -euo pipefail
cd "$(dirname "$0")/.."
W=${1:-runs/synth-world}
R=".venv/bin/resim"
THREADS=${THREADS:-2}
export OMP_NUM_THREADS=$THREADS MKL_NUM_THREADS=$THREADS
mkdir -p "$W"
step() { echo "[train_synth_world] $(date +%H:%M:%S) $*"; }
world=(configs/pipeline/synth-world.yaml --set sources.synthetic.root="$W/world")

# 1. the VAE: per-frame, 2x spatial (2 levels, 4 channels), on the 5-Hz clips of the world model's own world (frames only)
if [ -z "${VAE:-}" ]; then
  if [ ! -f "$W/vae_data/stats.json" ]; then
    step "pipeline: the VAE's clips (frames; the latents of the 4x placeholder are not used)"
    mkdir -p "$W/placeholder-vae-frame"
    .venv/bin/python - "$W/placeholder-vae-frame" <<'EOF'
import json, sys
c = json.load(open("configs/models/placeholder-cogvideox-vae-tiny/config.json"))
c["temporal_compression_ratio"] = 1      # the clips are 3 + 20 frames: a per-frame encoder takes any length
json.dump(c, open(sys.argv[1] + "/config.json", "w"))
EOF
    $R pipeline run "${world[@]}" --out "$W/vae_data" --set encode.vae="$W/placeholder-vae-frame"
  fi
  if [ ! -f "$W/vae/final/vae/config.json" ]; then
    step "train vae (per-frame, 2x spatial)"
    $R train vae --preset synth-frame --shards "$W/vae_data" --out "$W/vae" --set trainer.progress_bar=false \
       $( [ -d "$W/vae/checkpoints" ] && echo --resume )
  fi
  VAE="$W/vae/final/vae"
fi

# 2. the world model's data, encoded by that VAE
if [ ! -f "$W/data/stats.json" ]; then
  step "pipeline: the world model's clips through $VAE"
  $R pipeline run "${world[@]}" --out "$W/data" --set encode.vae="$VAE"
fi

# 3. the world model: one run, SEGMENT_S of wall clock per call, resumed exactly from its checkpoint
step "train world (segment of ${SEGMENT_S:-3600} s at $THREADS threads)"
$R train world --preset synth-world --shards "$W/data" --out "$W/world_run" \
   --set trainer.max_wall_s="${SEGMENT_S:-3600}" --set trainer.progress_bar=false \
   $( [ -n "${TOTAL_STEPS:-}" ] && echo --steps "$TOTAL_STEPS" ) \
   $( [ -d "$W/world_run/checkpoints" ] && echo --resume )
step "done: $W/world_run (python lab/milestone.py save $W/world_run --name synth-world --threads $THREADS)"
