"""The README's main command, scaled down: every step runs for real (Ray pipeline, training,
rollouts, planning) with the smoke preset, and the report links only files that exist."""
import re
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def test_smoke_demo_writes_report_and_reuses_steps(tmp_path):
    out = tmp_path / "demo"
    cmd = [sys.executable, "-m", "resim", "demo", "--preset", "smoke", "--out", str(out)]
    env = {"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin", "HOME": str(tmp_path),
           "RAY_AUTH_MODE": "disabled", "RAY_USAGE_STATS_ENABLED": "0", "HF_HUB_OFFLINE": "1"}
    first = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
    assert first.returncode == 0, first.stdout[-3000:] + first.stderr[-3000:]
    report = out / "report.html"
    assert f"report: {report}" in first.stdout
    page = report.read_text()
    links = re.findall(r'src="([^"]+)"', page)
    assert len(links) >= 5, page[:2000]
    for rel in links:
        assert (out / rel).is_file(), rel
    assert "missing:" not in page
    ranking = list(out.glob("plan/*.json"))
    assert ranking, "planning wrote no ranking"
    # a second run reuses every finished step
    second = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert second.returncode == 0, second.stderr[-3000:]
    assert second.stdout.count("reusing") >= 6
