"""The built wheel holds one import name, ``resim``, and only the product: no test fixture, lab script or benchmark.

Built with pip, as a user's ``pip install .`` would (no build isolation: nothing is downloaded), from a copy of what
the build reads (pyproject.toml, README.md, resim/), so the build folder setuptools writes stays out of the checkout.
"""
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def wheel_names(tmp_path_factory) -> list[str]:
    pytest.importorskip("setuptools")
    src, out = tmp_path_factory.mktemp("src"), tmp_path_factory.mktemp("wheel")
    for f in ("pyproject.toml", "README.md"):
        shutil.copy(REPO / f, src / f)
    shutil.copytree(REPO / "resim", src / "resim", ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    r = subprocess.run([sys.executable, "-m", "pip", "wheel", str(src), "--no-deps", "--no-build-isolation",
                        "-q", "-w", str(out)], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    (whl,) = out.glob("resim-*.whl")
    with zipfile.ZipFile(whl) as z:
        return z.namelist()


def test_one_top_level_import_name(wheel_names):
    top = {n.split("/")[0] for n in wheel_names if not n.split("/")[0].endswith((".dist-info", ".data"))}
    assert top == {"resim"}, top


def test_only_the_product(wheel_names):
    modules = [n for n in wheel_names if n.endswith(".py")]
    assert "resim/cli.py" in modules and "resim/models/world/dit.py" in modules   # the control: the product is there
    outside = {f.stem for d in ("lab", "bench", "tests/support") for f in (REPO / d).glob("*.py")}
    lab = [n for n in modules if Path(n).stem in outside or any(w in Path(n).stem for w in ("toy", "testing",
                                                                                            "fixture"))]
    assert not lab, f"fixtures, lab scripts or benchmarks in the wheel: {lab}"
