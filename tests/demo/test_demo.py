"""The README's main command, scaled down: every step runs for real (Ray pipeline, training,
rollouts, planning, evaluation) with the smoke preset, and the report links only files that exist."""
import json
import math
import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


@pytest.mark.slow   # the whole smoke demo, twice
def test_smoke_demo_writes_report_and_reuses_steps(tmp_path):
    out = tmp_path / "demo"
    cmd = [sys.executable, "-m", "resim", "demo", "--preset", "smoke", "--out", str(out)]
    env = {"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin", "HOME": str(tmp_path),
           "RAY_USAGE_STATS_ENABLED": "0", "HF_HUB_OFFLINE": "1"}
    first = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
    assert first.returncode == 0, first.stdout[-3000:] + first.stderr[-3000:]
    # its embedded Ray used a token made for the run, not one left in the user's home
    assert not (tmp_path / ".ray" / "auth_token").exists()
    report = out / "report.html"
    assert f"report: {report}" in first.stdout
    page = report.read_text()
    links = re.findall(r'src="([^"]+)"', page)
    assert len(links) >= 5, page[:2000]
    for rel in links:
        assert (out / rel).is_file(), rel
    assert "missing:" not in page
    # tidy: the pipeline's stats as a table, the config folded away (no raw JSON dumps on the page)
    assert "<th>origin</th>" in page and '"units"' not in page and "<details><summary>" in page
    ranking = list(out.glob("plan/*.json"))
    assert ranking, "planning wrote no ranking"
    _check_evaluation(out, page)
    # a second run reuses every finished step
    second = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert second.returncode == 0, second.stderr[-3000:]
    assert second.stdout.count("reusing") >= 13


def _finite(v) -> bool:
    return isinstance(v, (int, float)) and math.isfinite(v)


def _check_evaluation(out: Path, page: str) -> None:
    """Issue 10's done-when on the demo's trained world model: the IDM, `resim eval control` and `resim eval
    quality` wrote JSON + PNG with real numbers, on clips of the episodes the IDM held out (the shards' split)."""
    ev = out / "eval"
    for png in ("idm/idm_report.png", "control/control.png", "quality/quality.png"):
        assert (ev / png).stat().st_size > 1000, png
        assert f'src="eval/{png}"' in page, png
    idm = json.loads((ev / "idm/idm_report.json").read_text())
    held = set(idm["protocol"]["heldout_items"])
    assert idm["protocol"]["episodes_heldout"] >= 2 and idm["protocol"]["episodes_train"] >= 1
    assert held and not held & set(idm["protocol"]["train_items"])
    for k in ("idm", "constant_velocity"):
        assert _finite(idm["heldout"][k]["ade_m"]) and _finite(idm["heldout"][k]["fde_m"])
        assert idm["heldout"][k]["n"] == idm["protocol"]["clips_heldout"] >= 2

    ctl = json.loads((ev / "control/control.json").read_text())
    assert ctl["protocol"]["clips"] == 2 and ctl["protocol"]["episodes"] == 2
    assert ctl["protocol"]["split"]["side"] == "heldout"          # the episodes the IDM held out: one split
    assert ctl["protocol"]["split"]["heldout_sha256_16"] == idm["protocol"]["split"]["heldout_sha256_16"]
    for k in ("expert", "non_expert", "idm_on_recorded_video", "idm_on_recorded_through_vae", "expert_vs_not_given",
              "recorded_video_vs_not_given"):
        assert _finite(ctl[k]["trajectory_difference_m"]) and _finite(ctl[k]["trajectory_difference_final_m"])
        assert ctl[k]["n"] == 2
    assert _finite(ctl["non_expert_vs_recorded_trajectory_m"]) and ctl["non_expert_vs_recorded_trajectory_m"] > 0
    assert all(p["clip"] != p["non_expert_from"] for p in ctl["pairs"])
    assert "Bounds: expert / IDM floor" in page and "expert_vs_not_given" in page
    ca = ctl["command_accuracy"]
    assert isinstance(ca, str) or all(v["n"] == 2 and 0 <= v["accuracy"] <= 1 for v in ca.values())
    wm = ctl["protocol"]["world_model"]
    # the rollouts and evaluations use the shipped synthetic-world model, decoded by the shipped VAE
    assert wm["checkpoint"].startswith(str(REPO / "configs" / "models" / "synth-world"))
    assert wm["rollout"]["num_steps"] == 2 and wm["vae_placeholder"] is False

    q = json.loads((ev / "quality/quality.json").read_text())
    assert q["protocol"]["clips"] == 1 and q["protocol"]["conditioning_frames_excluded"] == 9
    assert q["protocol"]["world_model"]["vae_placeholder"] is False
    assert [r["horizon_s"] for r in q["per_horizon"]] == [1.0, 2.0, 4.0]
    for r in q["per_horizon"]:
        assert _finite(r["psnr"]) and 0 < r["psnr"] < 100 and _finite(r["ssim"]) and -1 <= r["ssim"] <= 1
    assert set(q["overall"]) >= {"psnr", "ssim"} and "fid" not in q["overall"]
    assert "Trajectory Difference" in page and "PSNR" in page

    cm = json.loads((ev / "commands/commands.json").read_text())
    fl = cm["flow_labeler"]
    assert cm["protocol"]["clips"] == 1 and fl["commanded"]["n"] == 3 and fl["null_prompt"]["n"] == 3
    assert sum(map(sum, fl["commanded"]["matrix"])) == 3
    for png in ("commands.png", "commands_strip.png", "commands.gif"):
        assert f'src="eval/commands/{png}"' in page, png
    assert "Does the world model follow the command?" in page

    # closed loop: the shipped policy (and constant velocity) in the true world and inside the shipped world model
    cl = json.loads((ev / "closed_loop/closed_loop.json").read_text())
    assert cl["policies"] == ["policy", "constant velocity"] and len(cl["rows"]) == 2 * 2
    assert {"world_model_vs_true", "world_model_reward_vs_true", "reward_vs_true_on_true_frames"} <= set(cl)
    assert cl["protocol"]["policy"]["checkpoint"].startswith(str(REPO / "configs" / "models" / "synth-policy"))
    for row in cl["rows"]:
        assert 0 <= row["true"]["score"] <= 100 and 0 <= row["world_model_idm_proxy"]["score"] <= 100
        assert 0 < row["world_model_reward"] < 100
    for png in ("closed_loop_strip.png", "closed_loop.png"):
        assert f'src="eval/closed_loop/{png}"' in page, png
    assert "A policy driving inside the world model" in page
