"""The pipeline's driver stays torch-free: it imports every stage module (resim.pipeline.runner), and the stages import
resim.media.encoders at their top, so torch, diffusers and transformers must load only where a stage builds its model
(in ``__init__``, on the actor). This is why resim/media/encoders.py keeps its torch imports inside functions
(tests/test_imports_at_top.py)."""
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def test_driver_imports_no_model_library():
    code = ("import sys, resim.pipeline.runner, resim.pipeline.stages, resim.media.encoders; "
            "print([m for m in ('torch', 'diffusers', 'transformers') if m in sys.modules])")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, check=True,
                       env={"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin"})
    assert r.stdout.strip() == "[]"
