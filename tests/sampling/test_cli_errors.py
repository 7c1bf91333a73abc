"""User mistakes in `resim sample` / `resim plan`: a one-line error `resim <sub>: ...` naming the item and the
reason, exit 2, never a traceback; command-line mistakes are found before any model is loaded."""
import json
import shutil
import tarfile

import numpy as np
import pytest
import torch
import yaml

from resim.cli import main
from tests.planting import plant_nan_latents


@pytest.fixture(scope="module")
def env(tmp_path_factory):
    """A tiny world-model run, a reward run, shards with a 10 Hz clip (9 history frames) and a 2 Hz NAVSIM-like
    clip (1 history frame), and a 10 Hz video."""
    torch.set_num_threads(1)
    from safetensors.torch import save_file

    from resim.shards.schema import ClipSpec
    from tests.support.shards import add_dummy_prompts, dummy_frames, make_dummy_sample, write_data_encode
    from resim.shards.video import encode_mp4
    from resim.shards.writer import ShardWriter
    from resim.models.world.config import preset
    from resim.models.world.dit import WorldModel
    from resim.models.reward.checkpoint import save_checkpoint
    from resim.train.tasks.reward.config import RewardTrainConfig
    from resim.models.reward.model import Video2Reward

    root = tmp_path_factory.mktemp("sampling_errors")
    data = root / "shards"
    add_dummy_prompts(data, seq_len=16, dim=64)
    s10 = make_dummy_sample(item_id="ep0", seed=0, latent_channels=16, latent_hw=(4, 6), frames_hw=(32, 48))
    s2 = make_dummy_sample(item_id="nav0", seed=1, latent_channels=16, latent_hw=(4, 6), frames_hw=(32, 48),
                           spec=ClipSpec(fps_hz=2.0, num_history_frames=1, num_future_frames=8))
    with ShardWriter(data, "d", max_samples_per_shard=4, config_hash="dummy") as w:
        w.write(s10)
        w.write(s2)
    torch.manual_seed(0)
    ck = root / "run" / "final"
    ck.mkdir(parents=True)
    (ck / "config.yaml").write_text(yaml.safe_dump({"model_name": "world", "model": {"preset": "tiny"}}))
    write_data_encode(ck)
    save_file({k: v.contiguous() for k, v in WorldModel(preset("tiny")).state_dict().items()},
              str(ck / "model.safetensors"))
    tc = RewardTrainConfig()
    save_checkpoint(Video2Reward(tc.model), root / "reward", tc)
    video = root / "clip.mp4"
    video.write_bytes(encode_mp4(dummy_frames(12, 48, 64), 10.0))
    return {"root": root, "data": data, "key": s10["__key__"], "nav": s2["__key__"], "run": root / "run",
            "reward": root / "reward", "video": video}


@pytest.fixture
def no_model_load(monkeypatch):
    """Fail loudly if a command gets as far as loading the world model."""
    from resim.sample import load

    def boom(*a, **k):
        raise AssertionError("the world model was loaded before the command line was checked")
    monkeypatch.setattr(load, "load_world_model", boom)


def _base(env, sub="sample", *extra, out=None):
    argv = [sub, "--checkpoint", str(env["run"]), "--shards", str(env["data"]), "--history", env["key"],
            "--out", str(out or env["root"] / "out"), "--steps", "1", "--device", "cpu", *extra]
    if sub == "plan" and "--reward" not in extra:
        argv += ["--reward", str(env["reward"])]
    return argv


def _usage_error(capsys, argv, needle):
    with pytest.raises(SystemExit) as e:
        main(argv)
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert needle in err and "Traceback" not in err, err


def _one_line_error(capsys, argv, needle, sub="sample"):
    """Exit 2 with one error line; progress lines ("[resim sample] loading ...") may come before it."""
    assert main(argv) == 2
    lines = [ln for ln in capsys.readouterr().err.strip().splitlines() if not ln.startswith(f"[resim {sub}] ")]
    err = "\n".join(lines)
    assert err.startswith(f"resim {sub}: ") and needle in err and len(lines) == 1, err


@pytest.mark.parametrize("sub", ["sample", "plan"])
@pytest.mark.parametrize("extra,needle", [
    (["--seconds", "-1"], "--seconds: must be > 0"),                 # was ValueError traceback
    (["--seconds", "nan"], "--seconds: expected a finite number"),
    (["--steps", "0"], "--steps: must be >= 1"),                     # was ConfigError traceback
    (["--steps", "-3"], "--steps: must be >= 1"),
    (["--device", "cudaa"], "--device: expected cpu, cuda"),         # was torch RuntimeError traceback
    (["--vae", "/nope"], "--vae: /nope: no such folder"),            # was an attempt to reach huggingface.co
])
def test_bad_values_are_usage_errors(env, capsys, no_model_load, sub, extra, needle):
    _usage_error(capsys, _base(env, sub, *extra), needle)


@pytest.mark.parametrize("sub", ["sample", "plan"])
@pytest.mark.parametrize("setting,needle", [
    ("rollout.chunk_frames=0", "need 1 <= chunk_frames (0)"),
    ("rollout.chunk_frames=11", "need 1 <= chunk_frames (11) <= frames_per_round (10)"),
    ("rollout.history_frames=0", "history_frames must be >= 1"),
    ("rollout.history_noise_level=-1", "history_noise_level=-1 must be >= 0"),
    ("rollout.guidance.scale_start=-3", "guidance.scale_start must be a finite number >= 0"),   # was accepted
    ("rollout.guidance.schedule=steep", "rollout.guidance.schedule: 'steep' is not one of"),
    ("rollout.num_step=3", "unknown config key rollout.num_step"),
    ("rolout.num_steps=3", "unknown settings section 'rolout'"),
    ("runtime.text_encoder=/nope", "text_encoder=/nope: no such local folder"),
    ("runtime.size_hw=64", "runtime.size_hw: expected a list"),       # was ValueError traceback
    ("runtime.max_text_tokens=0", "max_text_tokens must be a finite number > 0"),
    ("runtime.dtype=float8", "runtime.dtype: 'float8' is not one of"),
    ("runtime", "--set 'runtime': expected key=value"),
])
def test_bad_settings_are_one_line_errors(env, capsys, no_model_load, sub, setting, needle):
    _one_line_error(capsys, _base(env, sub, "--set", setting), needle, sub)


def test_a_settings_file_is_read_and_checked(env, capsys, no_model_load, tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("rollout: [1, 2]\n")
    _one_line_error(capsys, _base(env, "sample", "--config", str(bad)), "rollout: expected a mapping of keys")
    _one_line_error(capsys, _base(env, "sample", "--config", str(tmp_path / "nope.yaml")), "nope.yaml does not exist")
    bad.write_text("rollout: {chunk_frames: 0}\n")
    _one_line_error(capsys, _base(env, "sample", "--config", str(bad)), "need 1 <= chunk_frames (0)")
    # --set goes over the file
    _one_line_error(capsys, _base(env, "sample", "--config", str(bad), "--set", "rollout.chunk_frames=11"),
                    "chunk_frames (11)")


def test_plan_speed_must_be_positive(env, capsys, no_model_load):
    _usage_error(capsys, _base(env, "plan", "--speed-mps", "-5"), "--speed-mps: must be > 0")   # was accepted
    _usage_error(capsys, _base(env, "plan", "--speed-mps", "0"), "--speed-mps: must be > 0")


def test_mistakes_found_before_the_model_is_loaded(env, capsys, no_model_load, tmp_path):
    # was "not a candidate name ...: Expecting value"
    _one_line_error(capsys, _base(env, "sample", "--trajectory", str(tmp_path / "nope.npy")), "nope.npy: no such file")
    _one_line_error(capsys, _base(env, "sample", "--trajectory", "nope.json"), "nope.json: no such file")
    (tmp_path / "bad.npy").write_text("not numpy")
    _one_line_error(capsys, _base(env, "sample", "--trajectory", str(tmp_path / "bad.npy")), "not a readable .npy")
    # was found only after the model had been loaded and the rollout had started
    _one_line_error(capsys, _base(env, "sample", "--set", "runtime.actions_from_trajectory=true"), "add --trajectory")
    _one_line_error(capsys, _base(env, "sample", "--preset", "vid2world"),
                    "add --set runtime.actions_from_trajectory=true")
    if torch.cuda.is_available():
        _one_line_error(capsys, _base(env, "sample", "--device", "cuda:99"), "CUDA device(s) here")
    else:   # was AssertionError "Torch not compiled with CUDA enabled"
        why = "this torch build has no" if torch.version.cuda is None else "no CUDA GPU is visible"   # CPU / CUDA build
        _one_line_error(capsys, _base(env, "sample", "--device", "cuda"), f"--device cuda: {why}")
    _one_line_error(capsys, _base(env, "sample", "--shards", str(tmp_path / "nope")), "no such folder")
    assert not (env["root"] / "out").exists()


def test_plan_checks_the_reward_run_before_the_world_model(env, capsys, no_model_load, tmp_path):
    # was a CheckpointError traceback, after the world model had been loaded
    _one_line_error(capsys, _base(env, "plan", "--reward", str(tmp_path / "nope")),
                    "--reward: " + str(tmp_path / "nope") + ": no such checkpoint folder", "plan")
    for world_run in (env["run"], env["run"] / "final"):   # a world-model run, or its export
        _one_line_error(capsys, _base(env, "plan", "--reward", str(world_run)),
                        f"{env['run'] / 'final' / 'config.yaml'}: model_name is 'world', not a reward run", "plan")
    _one_line_error(capsys, _base(env, "plan", "--reward", str(tmp_path)),
                    f"{tmp_path} is not a reward checkpoint: no config.yaml + model.safetensors in it", "plan")


def test_shard_history_shorter_than_the_rollouts_says_what_to_do(env, capsys):
    """A NAVSIM-like key (1 latent history frame at 2 Hz): the error names the setting, which works."""
    _one_line_error(capsys, _base(env, "sample", "--history", env["nav"]), "pass --set rollout.history_frames=1")
    out = env["root"] / "nav"
    assert main(_base(env, "sample", "--history", env["nav"], "--set", "rollout.history_frames=1", "--seconds", "2",
                      out=out)) == 0
    assert np.load(out / "sample_latents.npy").shape[0] == 1 + 1        # 2 s at 2 Hz = 4 frames = 1 latent frame
    assert json.loads((out / "run.json").read_text())["rollout"]["history_frames"] == 1


def test_model_dependent_checks_are_one_line(env, capsys, tmp_path):
    # a video history at a size the VAE + patching cannot take: was "latent size (3, 5) not divisible" traceback
    _one_line_error(capsys, ["sample", "--checkpoint", str(env["run"]), "--history", str(env["video"]),
                             "--set", "runtime.size_hw=[30, 45]", "--steps", "1", "--device", "cpu",
                             "--out", str(tmp_path / "o")],
                    "runtime.size_hw=[30, 45]: both sides must be multiples of 16")
    # a trajectory the model's encoder cannot take: was ValueError traceback from inside the rollout
    _one_line_error(capsys, _base(env, "sample", "--trajectory", "[[1, 0, 0]]"), "the model takes 8 waypoints")
    _one_line_error(capsys, _base(env, "sample", "--steps", "5000"), "num_train_timesteps=1000")


def test_trajectory_json_file(env, tmp_path):
    from resim.sample.plan import make_candidate

    p = tmp_path / "traj.json"
    p.write_text(json.dumps(make_candidate("turn_left").trajectory.tolist()))
    out = tmp_path / "o"
    assert main(_base(env, "sample", "--trajectory", str(p), "--seconds", "0.4", out=out)) == 0
    assert json.loads((out / "sample_meta.json").read_text())["num_frames"] > 0


def test_help_says_what_works_and_what_is_written(capsys):
    with pytest.raises(SystemExit):
        main(["sample", "--help"])
    out = " ".join(capsys.readouterr().out.split())
    assert "NAVSIM's 2 Hz" not in out and "--set rollout.history_frames=1" in out
    assert "run.json" in out and "nothing is downloaded" in out
    assert "seed of the rollout's noise" in out and "runtime.dtype (float32|bfloat16|float16)" in out
    for key in ("rollout.chunk_frames", "rollout.kv_cache", "rollout.guidance.scale_start", "runtime.text_encoder",
                "runtime.size_hw", "runtime.compile", "runtime.actions_from_trajectory"):   # every setting is named
        assert key in out, key
    with pytest.raises(SystemExit):
        main(["plan", "--help"])
    out = " ".join(capsys.readouterr().out.split())
    assert "run.json" in out and "m/s > 0" in out


def test_hostile_shard_dataset_is_one_line(env, capsys, tmp_path):
    """A JSON bomb as the history's meta.json (was a RecursionError traceback) and a prompt entry naming /dev/zero
    (was read until MemoryError), each next to good samples and entries: one line, exit 2."""
    from tests.support.shards import insert_raw_sample

    data = tmp_path / "data"
    shutil.copytree(env["data"], data)
    shard = sorted((data / "shards").glob("*.tar"))[0].name
    bomb = insert_raw_sample(data, shard, "synthetic-bomb-000", {"meta.json": b"[" * 200_000})
    _one_line_error(capsys, _base(env, "sample", "--shards", str(data), "--history", bomb, out=tmp_path / "o"),
                    f"history {bomb!r}: shard {data / 'shards' / shard} sample {bomb!r}: member meta.json cannot be "
                    "decoded: JSON nested 200000 levels deep")
    path = data / "prompts" / "prompts.json"
    table = json.loads(path.read_text())
    pid = next(p for p, e in table["prompts"].items() if e["role"] == "null")
    table["prompts"][pid]["file"] = "/dev/zero"
    path.write_text(json.dumps(table))
    for sub in ("sample", "plan"):
        _one_line_error(capsys, _base(env, sub, "--shards", str(data), out=tmp_path / sub),
                        f"prompt {pid}: file '/dev/zero' is an absolute path", sub)


@pytest.mark.parametrize("ext,member,reason", [
    ("meta.json", "symlink", "member '{key}.meta.json' is a symbolic link to '/etc/passwd', not a regular file"),
    ("latent.npy", "hardlink", "member '{key}.latent.npy' is a hard link to '{first}.latent.npy', not a regular file"),
    ("latent.npy", None, "required member latent.npy missing"),
])
def test_history_sample_with_a_link_or_missing_member_is_one_line(env, capsys, tmp_path, ext, member, reason):
    """Each was a KeyError traceback (the reader dropped the member; history_from_shard indexed it)."""
    from tests.support.shards import NotRegular, insert_raw_sample

    data = tmp_path / "data"
    shutil.copytree(env["data"], data)
    shard = sorted((data / "shards").glob("*.tar"))[0].name
    first = env["key"]
    override = {"symlink": NotRegular(tarfile.SYMTYPE, "/etc/passwd"),
                "hardlink": NotRegular(tarfile.LNKTYPE, f"{first}.{ext}"), None: None}[member]
    key = insert_raw_sample(data, shard, "synthetic-link-000", {ext: override})
    _one_line_error(capsys, _base(env, "sample", "--shards", str(data), "--history", key, out=tmp_path / "o"),
                    f"history {key!r}: shard {data / 'shards' / shard} sample {key!r}: "
                    + reason.format(key=key, first=first))


def test_non_finite_inputs_are_refused_in_one_line(env, capsys, tmp_path):
    """NaN in a history's latents, a prompt embedding or the weights: refused by name, never a NaN rollout with
    exit 0."""
    from safetensors.torch import load_file, save_file

    from tests.support.shards import add_dummy_prompts, make_dummy_sample
    from resim.shards.writer import ShardWriter

    data = tmp_path / "shards"
    add_dummy_prompts(data, seq_len=16, dim=64)
    s = make_dummy_sample(item_id="nan0", seed=0, latent_channels=16, latent_hw=(4, 6), frames_hw=(32, 48))
    with ShardWriter(data, "d", max_samples_per_shard=4, config_hash="dummy") as w:
        w.write(s)
    plant_nan_latents(next(data.glob("shards/*.tar")), (1, 2))   # the writer refuses NaN: planted, same size
    argv = _base(env, "sample", out=tmp_path / "o1")
    argv[argv.index("--shards") + 1], argv[argv.index("--history") + 1] = str(data), s["__key__"]
    _one_line_error(capsys, argv, "latent.npy: 24 of")
    assert not (tmp_path / "o1").exists()

    run = tmp_path / "run"
    shutil.copytree(env["run"], run)
    w = load_file(str(run / "final" / "model.safetensors"))
    name = sorted(w)[3]
    w[name] = w[name].clone().fill_(float("inf"))
    save_file(w, str(run / "final" / "model.safetensors"))
    argv = _base(env, "sample", out=tmp_path / "o2")
    argv[argv.index("--checkpoint") + 1] = str(run)
    _one_line_error(capsys, argv, "1 weight tensors hold NaN or inf (first: ")

    prompts = tmp_path / "p"
    shutil.copytree(env["data"], prompts)
    for entry in json.loads((prompts / "prompts" / "prompts.json").read_text())["prompts"].values():
        f = prompts / "prompts" / entry["file"]
        raw = bytearray(f.read_bytes())
        raw[-64:] = b"\xff" * 64          # bfloat16 NaN bit patterns at the end of each embedding's payload
        f.write_bytes(bytes(raw))
    argv = _base(env, "sample", out=tmp_path / "o3")
    argv[argv.index("--shards") + 1] = str(prompts)
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "NaN or inf" in err and "Traceback" not in err, err


def test_an_out_that_is_a_file_or_inside_a_dataset_is_one_line(env, capsys, tmp_path):
    (tmp_path / "afile").write_text("x")
    _one_line_error(capsys, _base(env, "sample", out=tmp_path / "afile"), "is a file, not a folder")
    inside = env["data"] / "rollouts"
    _one_line_error(capsys, _base(env, "sample", out=inside), f"lies inside the dataset {env['data']}")
    assert not inside.exists()
    _one_line_error(capsys, _base(env, "plan", out=inside), "lies inside the dataset", sub="plan")


def test_a_rollout_that_overflows_is_said_and_not_written(env, capsys, tmp_path, monkeypatch):
    from resim.sample import rollout as ro

    real = ro.rollout

    def overflowing(*a, **k):
        res = real(*a, **k)
        res.latents[..., 0] = float("nan")
        return res
    monkeypatch.setattr(ro, "rollout", overflowing)
    out = tmp_path / "o"
    assert main(_base(env, "sample", out=out)) == 1
    err = capsys.readouterr().err.replace("\r", "\n")   # the progress bar's lines come before it
    lines = [ln for ln in err.strip().splitlines() if ln.startswith("resim sample:")]
    assert len(lines) == 1 and "NaN/inf values" in lines[0] and "nothing written" in lines[0], err[-2000:]
    assert "Traceback" not in err
    assert not list(out.glob("*.mp4")) and not list(out.glob("*.npy"))


def test_a_plan_whose_rollouts_overflow_is_said_and_not_written(env, capsys, tmp_path, monkeypatch):
    from resim.sample import plan as pl

    real = pl.plan

    def overflowing(*a, **k):
        res = real(*a, **k)
        res.rows[0].latents[..., 0] = float("nan")
        return res
    monkeypatch.setattr(pl, "plan", overflowing)
    out = tmp_path / "o"
    assert main(_base(env, "plan", "--candidates", "keep_lane", out=out)) == 1
    err = capsys.readouterr().err.replace("\r", "\n")
    lines = [ln for ln in err.strip().splitlines() if ln.startswith("resim plan:")]
    assert len(lines) == 1 and "NaN/inf values" in lines[0] and "nothing written" in lines[0], err[-2000:]
    assert not (out / "ranking.json").exists()


def test_an_out_on_a_read_only_mount_is_one_line(env, capsys, tmp_path, monkeypatch):
    import errno
    from pathlib import Path

    out = tmp_path / "ro" / "o"
    real = Path.mkdir

    def read_only(self, *a, **k):   # as a read-only mount answers (root ignores permission bits, so not chmod)
        if self == out:
            raise OSError(errno.EROFS, "Read-only file system", str(self))
        return real(self, *a, **k)
    monkeypatch.setattr(Path, "mkdir", read_only)
    _one_line_error(capsys, _base(env, "sample", out=out), f"--out {out}: cannot be created (Read-only file system)")
