#!/usr/bin/env bash
# Set up resim in a virtual environment (.venv by default).
#   bash scripts/setup.sh          # the product (pipeline + training)
#   bash scripts/setup.sh --dev    # plus the test tools
# Torch: if the venv has no torch yet and no NVIDIA GPU is visible, the CPU-only
# torch==2.13.0+cpu is installed first: from pip's configured sources where they have it
# (a local wheel on our dev/CI machines, seconds), else from PyTorch's CPU index (PyPI's
# own Linux torch is the multi-GB CUDA build). With a GPU visible, pip's default (CUDA)
# torch is used. An existing torch is kept.
set -euo pipefail
cd "$(dirname "$0")/.."
extras="all"
[ "${1:-}" = "--dev" ] && extras="dev"
venv="${RESIM_VENV:-.venv}"
py="${PYTHON:-}"
if [ -z "$py" ]; then
  for c in python3.11 python3 python; do command -v "$c" >/dev/null 2>&1 && { py="$c"; break; }; done
fi
[ -x "$venv/bin/python" ] || "$py" -m venv "$venv"
# This machine's pip config names local index folders that may be absent; drop those warnings only.
pip_() { "$venv/bin/python" -m pip "$@" 2> >(grep -v "is neither a file nor a directory" >&2); }
if ! "$venv/bin/python" -c "import torch" >/dev/null 2>&1; then
  if command -v nvidia-smi >/dev/null 2>&1 && nvidia-smi -L >/dev/null 2>&1; then
    echo "[setup] GPU visible: installing torch (CUDA build)"
    pip_ install -q "torch>=2.2"
  else
    echo "[setup] no GPU visible: installing CPU torch==2.13.0+cpu"
    pip_ install -q "torch==2.13.0+cpu" 2>/dev/null || \
      pip_ install -q "torch==2.13.0" --index-url https://download.pytorch.org/whl/cpu \
        --extra-index-url https://pypi.org/simple
  fi
fi
echo "[setup] installing resim[$extras] (editable)"
pip_ install -q -e ".[$extras]"
echo "[setup] done: $venv/bin/resim --help"
