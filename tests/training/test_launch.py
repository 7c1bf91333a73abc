"""`resim train launch`: dry run at CogVideoX-2B size for the stage presets, SLURM script, config errors."""
import re

import pytest

from resim.cli import main


@pytest.mark.parametrize("stage,gbs,trainable_frac", [("stage1", 80, (0.99, 1.0)), ("stage2", 160, (0.005, 0.05)),
                                                      ("stage3", 80, (0.999, 1.0))])
def test_dry_run_stage_presets(stage, gbs, trainable_frac, capsys, tmp_path):
    rc = main(["train", "launch", "--nnodes", "5", "--nproc-per-node", "8", "--dry-run", "--",
               "world", "--preset", stage, "--shards", str(tmp_path), "--out", str(tmp_path / "run")])
    out = capsys.readouterr().out
    assert rc == 0, out
    m = re.search(r"parameters: ([\d,]+) total \(([\d.]+) B\), ([\d,]+) trainable", out)
    total, trainable = int(m[1].replace(",", "")), int(m[3].replace(",", ""))
    assert 1.6e9 < total < 1.8e9  # CogVideoX-2B's DiT (1.69 B) + trajectory/action encoders (+ LoRA)
    assert trainable_frac[0] <= trainable / total <= trainable_frac[1]
    assert f"global batch: {gbs} = " in out and "40 ranks" in out and "FSDP" in out
    gib = {k.strip(): float(v) for k, v in re.findall(r"^\s{4}(\S.*?)\s+([\d.]+) GiB", out, re.M)}
    assert gib["total"] > 0 and any(k.startswith("activations") for k in gib)
    assert gib["optimizer (AdamW m, v fp32)"] == pytest.approx(8 * trainable / 40 / 2**30, abs=0.01)


def test_dry_run_one_gpu_needs_accumulation(capsys, tmp_path):
    assert main(["train", "launch", "--nproc-per-node", "8", "--dry-run", "--", "world", "--preset", "stage1",
                 "--out", str(tmp_path)]) == 0
    assert "global batch: 80 = 2/gpu x 8 ranks x 5 accumulation" in capsys.readouterr().out


def test_slurm_script(capsys, tmp_path):
    assert main(["train", "launch", "--nnodes", "5", "--nproc-per-node", "8", "--slurm", "--",
                 "world", "--preset", "stage2", "--shards", "/data/x", "--out", "runs/s2"]) == 0
    s = capsys.readouterr().out
    assert "#SBATCH --nodes=5" in s and "#SBATCH --gpus-per-node=8" in s
    assert "--rdzv-backend c10d" in s and "-m resim train world --preset stage2 --shards /data/x" in s


def test_bad_override_is_a_clear_config_error(capsys, tmp_path):
    rc = main(["train", "world", "--preset", "tiny", "--out", str(tmp_path), "--set", "optim.lrr=1"])
    assert rc == 2 and "unknown config key optim.lrr" in capsys.readouterr().err
    rc = main(["train", "world", "--preset", "tiny", "--out", str(tmp_path), "--set", "optim.lr=1e-4",
               "--print-config"])
    assert rc == 0 and "lr: 0.0001" in capsys.readouterr().out


def test_dry_run_accepts_reward(capsys, tmp_path):
    """`launch -- reward ...` runs without --dry-run, so the dry run accepts it: the config is resolved and
    checked, the launch command printed; there is no memory estimate for Video2Reward (said so)."""
    rc = main(["train", "launch", "--dry-run", "--", "reward", "--preset", "tiny", "--shards", str(tmp_path),
               "--out", str(tmp_path / "r")])
    cap = capsys.readouterr()
    assert rc == 0, cap.err
    assert "dry run: resim train reward --preset tiny" in cap.out and "Video2Reward" in cap.out
    assert "no estimate for reward" in cap.out
    assert "-m torch.distributed.run --nnodes 1 --nproc-per-node 1 --standalone -m resim train reward" in cap.out
    rc = main(["train", "launch", "--nproc-per-node", "2", "--dry-run", "--", "reward", "--shards", str(tmp_path),
               "--out", str(tmp_path / "r")])
    assert rc == 0 and "each of the 2 ranks would train the whole model" in capsys.readouterr().out
    rc = main(["train", "launch", "--dry-run", "--", "reward", "--shards", str(tmp_path), "--out", str(tmp_path),
               "--set", "lr=-1"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1 and "config error" in err and "lr" in err


def test_reward_launch_with_more_than_one_rank_is_refused(capsys, tmp_path):
    """Video2Reward trains on one process: torchrun with N ranks (or a SLURM script for them) would start N whole
    trainings writing the same --out; refused before anything starts, with the way out."""
    for extra in ([], ["--slurm"]):
        rc = main(["train", "launch", "--nproc-per-node", "2", *extra, "--", "reward", "--preset", "tiny",
                   "--shards", str(tmp_path), "--out", str(tmp_path / "r")])
        cap = capsys.readouterr()
        assert rc == 2 and "--nproc-per-node 1" in cap.err and "#SBATCH" not in cap.out, cap
    assert not (tmp_path / "r").exists()


def test_dry_run_largest_batch_per_gpu(capsys, tmp_path):
    """--gpu-memory-gib: the largest batch per GPU from the same estimate, per activation-checkpointing setting;
    checkpointing more lets more samples fit, and a GPU too small for one sample says 0."""
    def largest(gib):
        assert main(["train", "launch", "--nproc-per-node", "8", "--dry-run", "--gpu-memory-gib", str(gib), "--",
                     "world", "--preset", "stage1", "--out", str(tmp_path)]) == 0
        out = capsys.readouterr().out
        rows = dict(re.findall(r"^\s{4}(no AC|selective AC, every 2 blocks|AC on every block)\s+(\d+)", out, re.M))
        assert "(this config)" in out.split("AC on every block")[-1]          # stage1 checkpoints every block
        return {k: int(v) for k, v in rows.items()}
    h200 = largest(141)
    assert len(h200) == 3 and h200["no AC"] <= h200["selective AC, every 2 blocks"] < h200["AC on every block"]
    assert h200["AC on every block"] >= 2            # the preset's own 2 per GPU fits
    assert largest(20)["AC on every block"] < h200["AC on every block"]
    assert set(largest(2).values()) == {0}
    with pytest.raises(SystemExit, match="--gpu-memory-gib .* without --dry-run"):
        main(["train", "launch", "--gpu-memory-gib", "80", "--", "world", "--preset", "tiny", "--out", str(tmp_path)])
