"""`resim eval ...` on bad input: argparse refuses malformed values (exit 2), and the commands check clips,
the dataset's split, weight files and the IDM's window before loading the world model or rolling anything out.
The world-model checkpoint given here does not exist: any test that got as far as loading it would fail."""
import shutil

import pytest
import torch
import yaml

from resim.cli import main
from resim.config import ConfigError, from_dict
from resim.shards.schema import ClipSpec


@pytest.fixture(scope="module")
def ds(tmp_path_factory, road_world):
    """2 episodes x one 21-frame clip (9 history + 12 future), and two IDM runs: one whose window fits the clips,
    one (the tiny preset: 21 frames every 2 after the history) that needs 49-frame clips."""
    from safetensors.torch import save_file

    from resim.config import to_dict
    from resim.models.idm import InverseDynamicsModel, idm_preset

    torch.set_num_threads(1)
    root = tmp_path_factory.mktemp("evalinputs")
    spec = ClipSpec(fps_hz=10.0, num_history_frames=9, num_future_frames=12, waypoint_dt_s=0.15)
    road_world.write_shards(root / "ds", 2, 21, seed=1, spec=spec)
    for name, cfg in (("idm-fits", idm_preset("tiny", future_frames=12, num_frames=7)), ("idm-49", idm_preset("tiny"))):
        d = root / name / "final"
        d.mkdir(parents=True)
        torch.manual_seed(0)
        m = InverseDynamicsModel(cfg)
        save_file({k: v.contiguous() for k, v in m.state_dict().items()}, str(d / "model.safetensors"))
        (d / "config.yaml").write_text(yaml.safe_dump({"model_name": "idm", "model": to_dict(cfg)}))
    return root


def _world(root, *extra):
    return ["--checkpoint", str(root / "no-world-model"), "--shards", str(root / "ds"), "--out", str(root / "out"),
            "--device", "cpu", *extra]


def _usage_error(capsys, argv, needle):
    with pytest.raises(SystemExit) as e:
        main(argv)
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert needle in err and "Traceback" not in err, err


def _error(capsys, needle):
    err = capsys.readouterr().err.strip()
    assert needle in err and "Traceback" not in err and len(err.splitlines()) == 1, err


def test_malformed_values_are_usage_errors(ds, capsys):
    # was IndexError
    assert main(["eval", "quality", *_world(ds, "--set", "quality.resolution_hw=64")]) == 2
    _error(capsys, "quality.resolution_hw: expected a list")
    assert main(["eval", "quality", *_world(ds, "--set", "quality.fps_hz=5")]) == 2   # the clips decide it
    _error(capsys, "quality.fps_hz: set by the clips or the flags")
    assert main(["eval", "commands", *_world(ds, "--set", "commands.horizons_s=[0]")]) == 2
    _error(capsys, "horizons_s=[0.0]: give one or more horizons > 0 s")
    _usage_error(capsys, ["eval", "quality", *_world(ds, "--steps", "0")], "--steps: must be >= 1")  # was: 50 steps
    _usage_error(capsys, ["eval", "quality", *_world(ds, "--limit", "0")], "--limit: must be >= 1")  # was: all clips
    _usage_error(capsys, ["eval", "control", *_world(ds, "--limit", "-1"), "--idm", "x"], "--limit: must be >= 1")
    assert not (ds / "out").exists()


def test_retired_heldout_flag_bad_split_file_and_weight_files(ds, tmp_path, capsys):
    assert main(["eval", "quality", *_world(ds, "--heldout-from", "runs/idm")]) == 2
    _error(capsys, "--heldout-from is gone: the held-out split is the dataset's own")
    bad = tmp_path / "bad"
    shutil.copytree(ds / "ds", bad / "ds")
    (bad / "ds" / "split.json").write_text("{not json")
    with pytest.raises(SystemExit, match="split.json: not a split file"):   # before the world model loads
        main(["eval", "quality", *_world(bad)])
    # was FileNotFoundError, after the world model had been loaded
    assert main(["eval", "quality", *_world(ds, "--metrics", "fid", "--set",
                                            f"quality.fid_weights={tmp_path / 'no.pth'}")]) == 2
    _error(capsys, "no.pth is not a file")


def test_control_and_planning_check_inputs_before_rollouts(ds, capsys):
    # one clip, one episode: no non-expert trajectory from another episode (was a ValueError traceback)
    assert main(["eval", "control", *_world(ds, "--all-clips", "--limit", "1"), "--idm", str(ds / "idm-fits")]) == 2
    _error(capsys, "all of episode")
    # the IDM's window does not fit the clips (used to fail only after all rollouts)
    assert main(["eval", "control", *_world(ds, "--all-clips"), "--idm", str(ds / "idm-49")]) == 2
    _error(capsys, "does not fit clip")
    assert main(["eval", "planning", *_world(ds, "--all-clips"), "--idm", str(ds / "idm-49")]) == 2
    _error(capsys, "does not fit clip")
    assert not (ds / "out").exists()
    # inputs fine: the next failure is the missing world model, reported in one line
    with pytest.raises(SystemExit, match="--checkpoint: .*no-world-model"):
        main(["eval", "control", *_world(ds, "--all-clips"), "--idm", str(ds / "idm-fits")])


def test_idm_training_says_why_no_clip_is_usable(ds, tmp_path, capsys):
    out = tmp_path / "idm"
    assert main(["train", "idm", "--shards", str(tmp_path / "nope"), "--out", str(out), "--preset", "tiny"]) == 1
    _error(capsys, "does not exist")                       # was "0 clips from 0 episode(s)"
    assert main(["train", "idm", "--shards", str(ds / "ds"), "--out", str(out), "--preset", "tiny"]) == 1
    _error(capsys, "the model's window fits none of the 2 clips")   # and the first clip's reason
    (tmp_path / "empty").mkdir()
    assert main(["train", "idm", "--shards", str(tmp_path / "empty"), "--out", str(out), "--preset", "tiny"]) == 1
    _error(capsys, "no samples")
    assert main(["train", "idm", "--shards", str(ds / "ds"), "--out", str(out), "--lr", "nan"]) == 2
    _error(capsys, "lr must be a finite number")
    assert main(["train", "idm", "--shards", str(ds / "ds"), "--out", str(out), "--set", "head_heads=0"]) == 2
    _error(capsys, "head_heads must be >= 1")           # was ZeroDivisionError
    assert not out.exists()


def test_idm_configs_validate_without_dividing_by_zero():
    from resim.models.idm import idm_preset
    from resim.train.tasks.idm import IDMTrainConfig

    with pytest.raises(ConfigError, match="head_heads must be >= 1"):
        idm_preset("tiny", head_heads=0)
    with pytest.raises(ConfigError, match="target_scale"):
        idm_preset("tiny", target_scale=(1.0, float("nan"), 1.0))
    for bad in (float("nan"), float("inf"), 0.0):
        with pytest.raises(ConfigError, match="optim.lr must be a finite number"):
            from_dict(IDMTrainConfig, {"optim": {"lr": bad}})


def test_device_and_model_folders_are_checked_first(ds, capsys):
    """--device typos / a CUDA device this build lacks, and missing --vae / runtime.text_encoder folders: one line,
    exit 2, before anything is loaded (were a torch RuntimeError / AssertionError traceback, and an attempt to
    download the folder name from huggingface.co)."""
    idm = ["--idm", str(ds / "idm-fits")]
    for sub, extra in (("quality", []), ("control", idm), ("planning", idm)):
        argv = _world(ds, "--all-clips", *extra)
        _usage_error(capsys, ["eval", sub, *argv, "--device", "cudaa"], "--device: expected cpu, cuda")
        _usage_error(capsys, ["eval", sub, *argv, "--vae", str(ds / "nope")], "--vae: ")
        assert main(["eval", sub, *argv, "--set", f"runtime.text_encoder={ds / 'nope'}"]) == 2
        _error(capsys, "no such local folder")
        # no GPU: a CPU build says it has no CUDA support, a CUDA build that no GPU is visible
        dev, needle = (("cuda:99", "CUDA device(s) here") if torch.cuda.is_available() else
                       ("cuda", "has no CUDA" if torch.version.cuda is None else "no CUDA GPU is visible"))
        assert main(["eval", sub, *argv, "--device", dev]) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith(f"resim eval {sub}: --device {dev}: ") and needle in err and "\n" not in err, err


def test_cuda_message_names_the_way_out(ds, capsys):
    if torch.cuda.is_available():
        pytest.skip("CUDA present: the CPU-build message cannot be shown")
    assert main(["eval", "control", *_world(ds, "--all-clips"), "--idm", str(ds / "idm-fits"), "--device", "cuda"]) == 2
    _error(capsys, ("this torch build has no CUDA support" if torch.version.cuda is None else "no CUDA GPU is visible")
           + "; use --device cpu")


def _help(capsys, argv):
    with pytest.raises(SystemExit) as e:
        main([*argv, "--help"])
    assert e.value.code == 0
    return " ".join(capsys.readouterr().out.split())


def test_help_describes_each_command(capsys):
    from resim.models.idm import IDM_PRESETS

    assert "issue 10" not in _help(capsys, ["eval"])
    for sub in ("quality", "control", "planning"):
        h = _help(capsys, ["eval", sub])
        assert f"resim eval {sub} --checkpoint" in h and f"OUT/{sub}.json" in h and f"OUT/{sub}.png" in h, h
    # the quality example runs without downloaded weights: placeholder networks and an IDM run made first
    q = _help(capsys, ["eval", "quality"])
    assert "--allow-placeholder-networks" in q and "resim train idm --shards DATA --out runs/idm" in q
    i = _help(capsys, ["train", "idm"])
    assert all(name in i for name in IDM_PRESETS), i                      # was: "tiny, small (default)"


def test_a_retired_command_answers_its_old_name_in_one_line(ds, capsys):
    assert main(["eval", "detail", *_world(ds), "--all-clips"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("resim eval detail: ") and "retired" in err and "\n" not in err, err
    assert "detail" not in _help(capsys, ["eval"])   # and it is no longer offered
