#!/usr/bin/env bash
# The real-time and MFU measurements at CogVideoX-2B size, for one leased GPU call (H100/H200; random weights,
# bf16). Each part is a bench/ script that prints its configurations beside a baseline run in the same process;
# each is bounded by `timeout` so one slow part cannot eat the others' time. Nothing needs diffusers or data.
#
#   teacher   50 guided DDIM steps, 4-s 512x896 rollout (3 + 10 latent frames, KV cache), flex attention, blocks
#             compiled as `resim sample` compiles them on CUDA; target <= 20 s per clip
#   graphs    the same with --compile-mode reduce-overhead (CUDA graphs)
#   student   4 steps without CFG (a distilled student's sampler); target <= 4 s per 4-s clip (real time)
#   stream    frame by frame (chunk 1), 4 steps without CFG, 256x448; target >= 10 generated frames/s
#             (40 px frames per rollout / seconds)
#   mfu       training step at 512x896, FSDP2 on one GPU, full vs selective (every 2nd block) activation
#             checkpointing, eager vs compiled blocks, fused AdamW; target MFU >= 40 %
#   blocks    one 2B-size block's forward + backward at 256x448 under bf16 autocast: the block as it was against
#             the block without its gate and cast copies (bytes written outside matmul, seconds, same process)
#
# Usage (from the repository root): PARTS="teacher student stream mfu" bash scripts/gpu_realtime.sh OUT_DIR
# Not yet run (written without a GPU; each bench was smoke-run on a CPU with --smoke-cpu / --device cpu). The
# eager 50-step rollouts alone took ~50 s each on an H100, so all five parts may need more than one 10-minute
# call: run "teacher student stream" in one and "graphs mfu blocks" in the next. Logs in OUT_DIR/<part>.log.
set -uo pipefail
OUT=${1:?usage: PARTS="teacher student stream mfu" bash scripts/gpu_realtime.sh OUT_DIR}
PARTS=${PARTS:-teacher graphs student stream mfu blocks}
PYTHON=${PYTHON:-python3}
mkdir -p "$OUT"
export PYTHONPATH=.${PYTHONPATH:+:$PYTHONPATH} PYTHONUNBUFFERED=1
# --eager-baseline: each part times the eager model first, in the same process, so the compile's own speed-up
# is printed beside the target
roll=("$PYTHON" bench/rollout_gpu_cogvideox2b.py --attention flex --modes on --compile --eager-baseline)
for part in $PARTS; do
  echo "== $part ($(date -u +%H:%M:%S))"
  case $part in
    teacher) timeout 300 "${roll[@]}" --repeats 1 --steps 50 ;;
    graphs)  timeout 300 "${roll[@]}" --repeats 1 --steps 50 --compile-mode reduce-overhead ;;
    student) timeout 180 "${roll[@]}" --repeats 2 --steps 4 --no-guidance ;;
    stream)  timeout 180 "${roll[@]}" --repeats 2 --steps 4 --no-guidance --chunk 1 --height-px 256 --width-px 448 ;;
    mfu)     timeout 300 "$PYTHON" bench/train_mfu.py --sizes 64x112 --ac on,2 --compile off,on --attention flex \
               --adamw fused --steps 4 ;;
    blocks)  timeout 120 "$PYTHON" bench/block_elementwise.py --dim 1920 --heads 30 --frames 13 --hw 16x28 --text 226 \
               --batch 2 --device cuda --precision bf16 --repeats 10 ;;
    *) echo "unknown part $part (teacher graphs student stream mfu blocks)" >&2; continue ;;
  esac 2>&1 | tee "$OUT/$part.log"
  echo "== $part: exit ${PIPESTATUS[0]}"
done
