#!/usr/bin/env bash
# Set up resim in a virtual environment (.venv by default; RESIM_VENV=path picks another, PYTHON=... the interpreter).
#   bash scripts/setup.sh                     # the product (pipeline + training)
#   bash scripts/setup.sh --dev               # plus the test tools
#   bash scripts/setup.sh --allow-cuda-torch  # no GPU, CPU torch unavailable: accept PyPI's CUDA torch (~6 GB)
# Python: the interpreter must satisfy pyproject.toml's requires-python (checked before the venv is made).
# Torch: if the venv has no torch yet and no NVIDIA GPU is visible, the CPU-only torch==2.13.0+cpu is installed:
# from pip's configured sources where they have it (a local wheel on our dev/CI machines, seconds), else from
# PyTorch's CPU index. Where neither has it, setup stops and says how to go on: PyPI's own Linux torch is the
# multi-GB CUDA build, never taken unasked. With a GPU visible, pip's default (CUDA) torch is used. An existing
# torch is kept. Setup ends by saying which torch the venv has: version and build (CPU / CUDA x.y).
set -euo pipefail
cd "$(dirname "$0")/.."

TORCH_VERSION="2.13.0"
TORCH_CPU_INDEX="https://download.pytorch.org/whl/cpu"
# this machine's pip config names local index folders that may be absent: those warnings only are dropped
PIP_NOISE="is neither a file nor a directory"

extras="all"
allow_cuda=0
args=""   # the options given, for the rerun commands of the error messages
for arg in "$@"; do
  case "$arg" in
    --dev) extras="dev"; args+=" --dev" ;;
    --allow-cuda-torch) allow_cuda=1 ;;
    -h|--help) sed -n '2,11p' "$0" | sed 's/^# \{0,1\}//'; exit 0 ;;
    *) echo "[setup] error: unknown option $arg (known: --dev, --allow-cuda-torch, --help)" >&2; exit 2 ;;
  esac
done
venv="${RESIM_VENV:-.venv}"

# ---------------------------------------------------------------------------------------------- Python
requires=$(sed -n 's/^requires-python *= *"\([^"]*\)".*/\1/p' pyproject.toml)

# version_cmp A B: a number < 0, 0 or > 0 as A is below, equal to or above B (numeric fields, missing ones are 0)
version_cmp() {
  local IFS=. i
  local -a a=($1) b=($2)
  for i in 0 1 2; do
    if (( ${a[i]:-0} != ${b[i]:-0} )); then echo $(( ${a[i]:-0} - ${b[i]:-0} )); return; fi
  done
  echo 0
}

# version_in VERSION SPEC: SPEC is comma-separated clauses with >=, >, <=, <, ==, != (requires-python's forms)
version_in() {
  local IFS=, clause op c ops='^(>=|>|<=|<|==|!=)$' num='^[0-9]+(\.[0-9]+)*$'
  for clause in $2; do
    clause=${clause// /}
    op=${clause%%[0-9]*}
    if [[ ! "$op" =~ $ops || ! "${clause#"$op"}" =~ $num ]]; then
      echo "[setup] error: pyproject.toml requires-python: cannot read the clause '$clause'" >&2; exit 2
    fi
    c=$(version_cmp "$1" "${clause#"$op"}")
    case "$op" in
      ">=") (( c >= 0 )) ;; ">") (( c > 0 )) ;; "<=") (( c <= 0 )) ;; "<") (( c < 0 )) ;;
      "==") (( c == 0 )) ;; "!=") (( c != 0 )) ;;
    esac || return 1
  done
}

# check_python INTERPRETER HINT: one-line error and exit 2 unless it runs and satisfies requires-python
check_python() {
  local v
  v=$("$1" -c 'import sys; print("%d.%d.%d" % sys.version_info[:3])' 2>/dev/null) \
    || { echo "[setup] error: $1 does not run as Python; $2" >&2; exit 2; }
  version_in "$v" "$requires" \
    || { echo "[setup] error: $1 is Python $v, resim needs Python $requires (pyproject.toml requires-python); $2" >&2
         exit 2; }
}

if [ -x "$venv/bin/python" ]; then
  check_python "$venv/bin/python" "remove $venv or set RESIM_VENV=another/folder, and PYTHON=/path/to/python3.x"
else
  py="${PYTHON:-}"
  if [ -z "$py" ]; then
    for c in python3.11 python3 python; do command -v "$c" >/dev/null 2>&1 && { py="$c"; break; }; done
  fi
  [ -n "$py" ] || { echo "[setup] error: no python3 on PATH; set PYTHON=/path/to/python3.x" >&2; exit 2; }
  check_python "$py" "set PYTHON=/path/to/python3.x"
  "$py" -m venv "$venv"
fi

# ----------------------------------------------------------------------------------------------- torch
pip_() { "$venv/bin/python" -m pip "$@" 2> >(grep -v "$PIP_NOISE" >&2); }
log=$(mktemp)
trap 'rm -f "$log"' EXIT

# try_pip ARGS...: a pip install with its output kept in $log, not -q: pip says why it failed only when not quiet
try_pip() { "$venv/bin/python" -m pip install "$@" >"$log" 2>&1; }
show_pip_tail() { grep -v -e "$PIP_NOISE" -e '^ *$' "$log" | tail -n 10 | sed 's/^/[setup]   pip: /' >&2; }

# the venv's torch as "VERSION (BUILD build)", BUILD = CPU / CUDA x.y / ROCm x.y, read from torch itself
torch_info() {
  "$venv/bin/python" -c 'import torch; v = torch.version
build = "CUDA " + v.cuda if v.cuda else "ROCm " + v.hip if getattr(v, "hip", None) else "CPU"
print(torch.__version__ + " (" + build + " build)")' 2>"$log"
}

install_cpu_torch() {
  local want="torch==$TORCH_VERSION+cpu"
  echo "[setup] no GPU visible: installing CPU $want from pip's configured sources"
  try_pip "$want" && return
  echo "[setup] pip's configured sources have no $want; pip said:" >&2
  show_pip_tail
  echo "[setup] trying PyTorch's CPU index $TORCH_CPU_INDEX"
  # +cpu stays pinned: PyPI (there for torch's dependencies) has no such build, so this cannot become the CUDA one
  try_pip "$want" --index-url "$TORCH_CPU_INDEX" --extra-index-url https://pypi.org/simple && return
  echo "[setup] PyTorch's CPU index did not give $want; pip said:" >&2
  show_pip_tail
  if (( allow_cuda )); then
    echo "[setup] --allow-cuda-torch: installing PyPI's torch==$TORCH_VERSION, the CUDA build (~6 GB venv, minutes)"
    want_cpu=0
    pip_ install -q "torch==$TORCH_VERSION"
    return
  fi
  {
    echo "[setup] error: CPU $want is not available: pip's configured sources lack it and PyTorch's CPU index failed"
    echo "[setup]   either make it reachable and rerun: PIP_EXTRA_INDEX_URL=$TORCH_CPU_INDEX bash scripts/setup.sh$args"
    echo "[setup]     (or a mirror of that index; pip's --extra-index-url; or PIP_FIND_LINKS=folder-with-the-wheel)"
    echo "[setup]   or accept PyPI's torch==$TORCH_VERSION, the CUDA build (~6 GB venv, ~10 min):" \
         "bash scripts/setup.sh$args --allow-cuda-torch"
  } >&2
  exit 1
}

want_cpu=0
if torch_now=$(torch_info); then
  echo "[setup] keeping the venv's torch $torch_now"
elif command -v nvidia-smi >/dev/null 2>&1 && nvidia-smi -L >/dev/null 2>&1; then
  echo "[setup] GPU visible: installing torch (CUDA build)"
  pip_ install -q "torch>=2.2"
else
  want_cpu=1
  install_cpu_torch
fi

echo "[setup] installing resim[$extras] (editable)"
pip_ install -q -e ".[$extras]"

if ! torch_now=$(torch_info); then
  echo "[setup] error: torch does not import in $venv after setup; python said:" >&2
  tail -n 5 "$log" | sed 's/^/[setup]   /' >&2
  exit 1
fi
if (( want_cpu )) && [[ "$torch_now" != *"(CPU build)" ]]; then
  echo "[setup] error: torch in $venv is $torch_now, not the CPU build asked for (did a dependency replace it?)" >&2
  exit 1
fi
echo "[setup] torch $torch_now"
echo "[setup] done: $venv/bin/resim --help"
