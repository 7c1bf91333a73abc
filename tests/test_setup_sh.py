"""scripts/setup.sh: which torch it installs, what it says, and the Python check (no network, no install).

The venv is a fake: its ``bin/python`` logs ``-m pip`` calls and "installs" a stub torch package (version and
``torch.version.cuda`` as each test scripts it); anything else runs the real interpreter with ``-S`` and the
stub on PYTHONPATH, so setup.sh's own probes read the stub as they would read torch.
"""
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SETUP = REPO / "scripts" / "setup.sh"
CPU_INDEX = "https://download.pytorch.org/whl/cpu"

FAKE_PYTHON = r"""#!/bin/bash
# fake venv python; FAKE_LOCAL / FAKE_CPU_INDEX / FAKE_DEFAULT: what pip's configured sources, PyTorch's CPU
# index and a plain `pip install torch...` give: "fail" or "VERSION CUDA" (CUDA "None" for a CPU build)
if [ "$1" = "-c" ] && [ -n "${FAKE_PY_VERSION:-}" ] && [[ "$2" == *version_info* ]]; then
  echo "$FAKE_PY_VERSION"; exit 0
fi
if [ "$1" = "-m" ] && [ "$2" = "pip" ]; then
  shift 2; echo "$*" >> "$FAKE_DIR/pip.log"
  case " $* " in
    *" -e "*) got=${FAKE_EDITABLE_TORCH:-}; [ -n "$got" ] || exit 0 ;;   # resim's deps may pull another torch
    *"--index-url __CPU_INDEX__"*) got=$FAKE_CPU_INDEX ;;
    *"+cpu"*) got=$FAKE_LOCAL ;;
    *) got=$FAKE_DEFAULT ;;
  esac
  if [ "$got" = fail ]; then
    echo "WARNING: Location '/opt/gone' is neither a file nor a directory. It will be ignored." >&2
    echo "ERROR: No matching distribution found for torch (fake)" >&2; exit 1
  fi
  read -r ver cuda <<< "$got"
  mkdir -p "$FAKE_DIR/site/torch"
  printf '__version__ = "%s"\nfrom . import version\n' "$ver" > "$FAKE_DIR/site/torch/__init__.py"
  [ "$cuda" = None ] && cuda=None || cuda="\"$cuda\""
  printf 'cuda = %s\nhip = None\n' "$cuda" > "$FAKE_DIR/site/torch/version.py"
  exit 0
fi
PYTHONPATH="$FAKE_DIR/site" exec "$REAL_PYTHON" -S "$@"
""".replace("__CPU_INDEX__", CPU_INDEX)


@pytest.fixture
def fake(tmp_path):
    """A fake venv (RESIM_VENV) and a bin folder first on PATH; returns a runner of setup.sh."""
    venv, fakebin = tmp_path / "venv", tmp_path / "bin"
    (venv / "bin").mkdir(parents=True)
    fakebin.mkdir()
    py = venv / "bin" / "python"
    py.write_text(FAKE_PYTHON)
    py.chmod(0o755)

    def run(*args, gpu=False, torch_before=None, **outcomes):
        # a fake nvidia-smi either way: a GPU machine's real one (in /usr/bin) must not decide these tests
        smi = fakebin / "nvidia-smi"
        smi.write_text("#!/bin/sh\necho 'GPU 0: NVIDIA H100'\n" if gpu else "#!/bin/sh\nexit 9\n")
        smi.chmod(0o755)
        if torch_before:   # a venv that already has torch: install it through the fake pip
            subprocess.run([str(py), "-m", "pip", "install", "torch"], check=True,
                           env={**env, "FAKE_DEFAULT": torch_before})
            (tmp_path / "pip.log").unlink()
        p = subprocess.run(["bash", str(SETUP), *args], capture_output=True, text=True, timeout=60,
                           env={**env, **{k.upper(): v for k, v in outcomes.items()}})
        log = tmp_path / "pip.log"
        p.pip = log.read_text().splitlines() if log.exists() else []
        return p

    env = {"PATH": f"{fakebin}:/usr/bin:/bin", "HOME": str(tmp_path), "RESIM_VENV": str(venv),
           "FAKE_DIR": str(tmp_path), "REAL_PYTHON": sys.executable,
           "FAKE_LOCAL": "fail", "FAKE_CPU_INDEX": "fail", "FAKE_DEFAULT": "fail"}
    run.venv = venv
    run.env = env
    return run


@pytest.mark.parametrize("version", ["2.13.0+cpu", "2.13.0"])
def test_cpu_torch_from_pip_sources_is_reported_from_torch_itself(fake, version):
    """This machine: PIP_FIND_LINKS=/opt/wheels has the CPU wheel (torch 2.13.0+cpu, torch.version.cuda None).
    The build is read from torch.version.cuda, so a CPU build without "+cpu" in its version counts too."""
    p = fake(fake_local=f"{version} None")
    assert p.returncode == 0, p.stderr
    assert p.pip == ["install torch==2.13.0+cpu", "install -q -e .[all]"]
    assert f"[setup] torch {version} (CPU build)" in p.stdout.splitlines()
    assert "error" not in p.stderr


def test_cpu_index_is_tried_next_with_plus_cpu_pinned_and_pip_error_shown(fake):
    p = fake("--dev", fake_cpu_index="2.13.0+cpu None")
    assert p.returncode == 0, p.stderr
    assert p.pip == ["install torch==2.13.0+cpu",
                     f"install torch==2.13.0+cpu --index-url {CPU_INDEX} --extra-index-url https://pypi.org/simple",
                     "install -q -e .[dev]"]
    assert "pip: ERROR: No matching distribution found for" in p.stderr    # the first attempt's error, shown
    assert "neither a file nor a directory" not in p.stderr                # this machine's pip-config noise, not
    assert p.stdout.splitlines()[-2] == "[setup] torch 2.13.0+cpu (CPU build)"


def test_no_cpu_torch_stops_and_names_both_ways_out_without_cuda_download(fake):
    p = fake("--dev", fake_default="2.13.0 13.0")   # PyPI would give the CUDA build: it must not be asked
    assert p.returncode == 1
    assert all("+cpu" in c for c in p.pip) and len(p.pip) == 2, p.pip      # no unpinned torch, no resim install
    err = p.stderr
    assert "[setup] error: CPU torch==2.13.0+cpu is not available" in err
    assert f"PIP_EXTRA_INDEX_URL={CPU_INDEX} bash scripts/setup.sh --dev" in err
    assert "bash scripts/setup.sh --dev --allow-cuda-torch" in err and "CUDA build (~6 GB" in err
    assert err.count("pip: ERROR: No matching distribution") == 2           # both attempts' errors shown
    assert not (fake.venv.parent / "site" / "torch").exists()


def test_allow_cuda_torch_takes_pypi_torch_and_says_it_is_cuda(fake):
    p = fake("--allow-cuda-torch", fake_default="2.13.0 13.0")
    assert p.returncode == 0, p.stderr
    assert p.pip[2:] == ["install -q torch==2.13.0", "install -q -e .[all]"]
    assert "--allow-cuda-torch: installing PyPI's torch==2.13.0, the CUDA build" in p.stdout
    assert "[setup] torch 2.13.0 (CUDA 13.0 build)" in p.stdout


def test_gpu_visible_installs_pip_default_torch(fake):
    p = fake(gpu=True, fake_default="2.13.0+cu130 13.0")
    assert p.returncode == 0, p.stderr
    assert p.pip == ["install -q torch>=2.2", "install -q -e .[all]"]
    assert "[setup] torch 2.13.0+cu130 (CUDA 13.0 build)" in p.stdout


def test_existing_torch_is_kept_and_reported(fake):
    p = fake("--dev", torch_before="2.9.1+cu128 12.8")
    assert p.returncode == 0, p.stderr
    assert p.pip == ["install -q -e .[dev]"]
    assert "[setup] keeping the venv's torch 2.9.1+cu128 (CUDA 12.8 build)" in p.stdout


def test_cpu_torch_replaced_by_a_dependency_is_an_error(fake):
    """Asked for CPU, ended with CUDA (resim's editable install pulled another torch): said, not passed quietly."""
    p = fake(fake_local="2.13.0+cpu None", fake_editable_torch="2.14.0 13.0")
    assert p.returncode == 1
    assert p.stderr.splitlines()[-1] == (f"[setup] error: torch in {fake.venv} is 2.14.0 (CUDA 13.0 build), not the "
                                         "CPU build asked for (did a dependency replace it?)")


def test_python_outside_requires_python_is_a_one_line_error(fake, tmp_path):
    old = tmp_path / "python3.9"
    old.write_text(FAKE_PYTHON)
    old.chmod(0o755)
    env = {**fake.env, "RESIM_VENV": str(tmp_path / "new-venv"), "PYTHON": str(old), "FAKE_PY_VERSION": "3.9.18"}
    p = subprocess.run(["bash", str(SETUP)], capture_output=True, text=True, timeout=60, env=env)
    assert p.returncode == 2
    assert p.stderr.splitlines() == [f"[setup] error: {old} is Python 3.9.18, resim needs Python >=3.10 "
                                     "(pyproject.toml requires-python); set PYTHON=/path/to/python3.x"]
    assert not (tmp_path / "new-venv").exists()                  # no venv made with the wrong interpreter
    # an existing venv made with it: the same check, and the way out names the venv
    p = fake(fake_local="2.13.0+cpu None", fake_py_version="3.9.18")
    assert p.returncode == 2 and f"remove {fake.venv} or set RESIM_VENV" in p.stderr and p.pip == []


def test_unknown_option_is_an_error(fake):
    p = fake("--devv")
    assert p.returncode == 2 and p.stderr.strip() == ("[setup] error: unknown option --devv "
                                                      "(known: --dev, --allow-cuda-torch, --help)")
    assert p.pip == []
