"""lab/calibrate_labeler.py end to end on a tiny synthetic world: it makes the world, labels it, calibrates the
threshold on the even episodes, reports the odd ones, and writes its numbers, the resolved config and the plot."""
import json
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


def test_calibration_bench_reports_held_out_windows_and_plots(tmp_path):
    pytest.importorskip("matplotlib")
    out, png = tmp_path / "cal.json", tmp_path / "held_out.png"
    r = subprocess.run([sys.executable, "lab/calibrate_labeler.py", "--episodes", "4", "--seed", "3", "--preset",
                        "fast", "--json-out", str(out), "--plot", str(png)],
                       cwd=REPO, capture_output=True, text=True, env={"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin"})
    assert r.returncode == 0, r.stderr[-2000:]
    doc = json.loads(out.read_text())
    n = doc["windows"]["held_out"]
    assert n > 0 and doc["windows"]["calibration"] > 0
    assert sum(map(sum, doc["confusion_held_out"])) == n
    assert doc["held_out_accuracy"] == pytest.approx(sum(doc["confusion_held_out"][i][i] for i in range(3)) / n)
    assert doc["labeler_config"]["flow"]["work_width_px"] == 160      # the resolved `fast` preset is saved with it
    assert 0 <= doc["yaw_err_deg_held_out"]["median"] <= doc["yaw_err_deg_held_out"]["p90"]
    assert "held-out accuracy" in r.stdout and "confusion" in r.stdout
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 20_000
