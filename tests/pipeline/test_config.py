"""Config validation: every error names its key, before any work starts."""
import json
from pathlib import Path

import pytest

from resim.config import ConfigError, from_dict
from resim.pipeline.config import PipelineConfig, config_from_dict, to_dict
from resim.pipeline.load import load_config

from .conftest import REPO


def _load(*overrides, out="/tmp/unused-out", base="configs/pipeline/synthetic.yaml"):
    return load_config(REPO / base, list(overrides), out=out)


def test_shipped_configs_load(tmp_path):
    cfg = _load()
    assert cfg.clip.num_frames == 49 and cfg.balance.turn_factor == 5
    assert cfg.sources.synthetic.clip["navsim"].fps_hz == 2.0
    for name in ("opendv", "navsim", "carla"):
        c = _load(f"sources.{name}.root={tmp_path}", base=f"configs/pipeline/{name}.yaml")
        assert getattr(c.sources, name).root == tmp_path
    c = _load(f"sources.opendv.root={tmp_path}", base="configs/pipeline/opendv.yaml")
    assert (c.sources.opendv.start_discard_s, c.sources.opendv.end_discard_s,
            c.sources.opendv.min_height_px) == (90.0, 60.0, 720)
    assert (c.encode.height_px, c.encode.width_px) == (256, 448)


@pytest.mark.parametrize("override, key", [
    ("clip.strid=3", "clip.strid"),                                   # unknown key
    ("sources.synthetic.episods=3", "sources.synthetic.episods"),
    ("clip.stride_frames=many", "clip.stride_frames"),                # wrong type
    ("ray.stages.encode.num_gpus=x", "ray.stages.encode.num_gpus"),
    ("encode.height_px=60", "height_px"),                             # not a multiple of 8
    ("clip.stride_frames=12", "balance.turn_factor"),                 # 12 % 5 != 0
    ("clip.num_future_frames=42", "num_history_frames + num_future_frames"),   # 50 frames after the first: not 4k
    ("labels.labeler.command.window_s=3.0", "labels.labeler.command.window_s"),
    ("labels.labeler.flow.flow_preset=slow", "labels.labeler.flow.flow_preset"),
    ("sources.synthetic.clip.nuscenes={fps_hz: 2}", "layouts"),
    ("encode.vae=/no/such/vae", "encode.vae"),                        # missing path
    ("sources.carla.root=/no/such/dir", "sources.carla.root"),
    ("shards.max_samples_per_shard=0", "max_samples_per_shard must be >= 1"),   # was: fails in the writer
    ("shards.max_bytes_per_shard=-5", "max_bytes_per_shard must be >= 1"),
    ("clip.fps_hz=.nan", "fps_hz must be a finite number > 0"),                 # NaN passed `< 0` checks
    ("clip.fps_hz=.inf", "fps_hz must be a finite number > 0"),
    ("clip.waypoint_dt_s=.nan", "waypoint_dt_s"),
    ("sources.opendv.start_discard_s=.nan", "start_discard_s"),
    ("ray.stages.encode.num_gpus=.nan", "num_gpus"),
    ("sources.carla.max_items=-1", "max_items must be >= 0"),                   # was: items[:-1]
    ("sources.synthetic.layouts=[opendv,opendv]", "listed more than once"),     # was: a crash at enumerate
    ("sources.synthetic.layouts=[]", "layouts: empty"),
    ("sources.synthetic.preset=huge", "sources.synthetic.preset"),
    ("ray.num_cpus=0", "num_cpus must be >= 1"),
])
def test_errors_name_the_key(override, key):
    with pytest.raises(ConfigError) as e:
        _load(override)
    assert key in str(e.value), str(e.value)


def test_missing_out_and_no_source(tmp_path):
    with pytest.raises(ConfigError, match="out"):
        load_config(REPO / "configs/pipeline/opendv.yaml", [f"sources.opendv.root={tmp_path}"], out=None)
    with pytest.raises(ConfigError, match="sources"):
        from_dict(PipelineConfig, {"out": "x"})


def test_cli_check_reports_config_error(capsys):
    from resim.cli import main

    rc = main(["pipeline", "check", str(REPO / "configs/pipeline/synthetic.yaml"), "--out", "/tmp/x",
               "--set", "balance.turn_factr=2"])
    assert rc == 2
    assert "balance.turn_factr" in capsys.readouterr().err


def test_a_root_that_is_a_file_is_named_a_file_not_a_missing_folder(tmp_path, capsys):
    from resim.cli import main

    f = tmp_path / "opendv.mp4"
    f.write_bytes(b"")
    with pytest.raises(ConfigError) as e:      # was "sources.opendv.root: folder ... does not exist"
        _load(f"sources.opendv.root={f}", base="configs/pipeline/opendv.yaml")
    assert str(e.value) == f"sources.opendv.root: {f} is a file, not a folder"
    with pytest.raises(ConfigError) as e:
        _load(f"encode.vae={f}")
    assert str(e.value) == f"encode.vae: {f} is a file, not a folder (a model folder is expected)"
    with pytest.raises(ConfigError) as e:
        _load(f"sources.carla.root={tmp_path / 'nope'}")
    assert str(e.value) == f"sources.carla.root: {tmp_path / 'nope'} does not exist"
    rc = main(["pipeline", "check", str(REPO / "configs/pipeline/opendv.yaml"), "--out", str(tmp_path / "o"),
               "--set", f"sources.opendv.root={f}"])
    assert rc == 2
    assert capsys.readouterr().err.strip() == f"config error: sources.opendv.root: {f} is a file, not a folder"


def test_a_reader_whose_root_became_a_file_says_so(tmp_path):
    from resim.pipeline.sources.episode import SourceError
    from resim.pipeline.sources.opendv import OpenDVConfig, OpenDVReader

    f = tmp_path / "videos"
    f.write_bytes(b"")
    with pytest.raises(SourceError, match=f"^{f}: OpenDV root is a file, not a folder$"):
        OpenDVReader(OpenDVConfig(root=f)).list_items()


def test_vae_and_text_encoder_flags_override(tmp_path, capsys):
    from resim.cli import main

    vae = REPO / "configs/models/placeholder-cogvideox-vae-tiny"
    rc = main(["pipeline", "check", str(REPO / "configs/pipeline/synthetic.yaml"), "--out", str(tmp_path),
               "--vae", str(vae)])
    assert rc == 0 and f"vae: {vae}" in capsys.readouterr().out


def test_reader_options_are_checked_at_load(tmp_path, capsys):
    # a value only the reader validates used to pass load (and `pipeline check`) and fail at enumerate
    with pytest.raises(ConfigError, match="sources.navsim: split must be a plain folder name"):
        _load(f"sources.navsim.root={tmp_path}", "sources.navsim.split=synth/x")
    from resim.cli import main

    rc = main(["pipeline", "check", str(REPO / "configs/pipeline/synthetic.yaml"), "--out", str(tmp_path),
               "--set", "shards.max_samples_per_shard=0"])
    assert rc == 2 and "max_samples_per_shard" in capsys.readouterr().err


def test_reused_synthetic_world_must_match_the_config(synth_world, tmp_path):
    from resim.pipeline import runner

    root = f"sources.synthetic.root={synth_world}"                    # made with episodes 6, seed 0, tiny
    assert _load(root).sources.synthetic.episodes == 6
    for override, words in (("sources.synthetic.episodes=5", "episodes: 6 on disk, 5 by the config"),
                            ("sources.synthetic.seed=3", "seed: 0 on disk, 3 by the config"),
                            ("sources.synthetic.preset=demo", "height_px: 64 on disk, 128 by the config"),
                            ("sources.synthetic.fork_fraction=0.5", "fork_fraction: 0.0 on disk, 0.5 by the config")):
        with pytest.raises(ConfigError, match=words):                 # was: the world reused as is
            _load(root, override)
    # a world written before a SynthConfig field existed had that field's default: still the config's world
    older = tmp_path / "older"
    older.mkdir()
    (older / "ground_truth.json").write_text("{}")
    made = json.loads((Path(synth_world) / "synth_config.json").read_text())
    del made["fork_fraction"]
    (older / "synth_config.json").write_text(json.dumps(made))
    assert _load(f"sources.synthetic.root={older}").sources.synthetic.fork_fraction == 0.0
    with pytest.raises(ConfigError, match="fork_fraction: 0.0 on disk, 0.5 by the config"):
        _load(f"sources.synthetic.root={older}", "sources.synthetic.fork_fraction=0.5")
    # a config that skipped load_config (built from a dict) is checked where the world is reused
    d = to_dict(_load(root))
    d["sources"]["synthetic"]["episodes"] = 5
    with pytest.raises(ConfigError, match="episodes: 6 on disk, 5 by the config"):
        runner.ensure_synthetic(config_from_dict(d))
    bare = tmp_path / "world"
    bare.mkdir()
    (bare / "ground_truth.json").write_text("{}")
    with pytest.raises(ConfigError, match="without synth_config.json"):
        _load(f"sources.synthetic.root={bare}")


def test_fork_fraction_at_its_default_leaves_the_data_hash_as_it_was(tmp_path):
    """Datasets made before the field existed keep their hash (a rerun resumes them); forks change it."""
    from resim.pipeline.config import absolute_paths
    from resim.pipeline.stages.encode import _without_new_defaults, data_config_hash
    from resim.config import config_hash

    cfg = _load()
    d = to_dict(absolute_paths(cfg))
    del d["sources"]["synthetic"]["fork_fraction"]     # the config as it was before the field existed
    before = config_hash(_without_new_defaults(   # (the older max_held_frames at its default: left out as ever)
        {k: d[k] for k in ("sources", "clip", "labels", "balance", "quality", "encode", "shards")}))
    assert data_config_hash(cfg) == before
    assert data_config_hash(_load("sources.synthetic.fork_fraction=0.5")) != before
    del d["sources"]["synthetic"]["pace_fork_fraction"]   # nor pace forks
    assert data_config_hash(cfg) == config_hash(_without_new_defaults(
        {k: d[k] for k in ("sources", "clip", "labels", "balance", "quality", "encode", "shards")}))
    assert data_config_hash(_load("sources.synthetic.pace_fork_fraction=0.5")) != before
    with pytest.raises(ConfigError, match="pace_fork_fraction"):
        _load("sources.synthetic.fork_fraction=0.6", "sources.synthetic.pace_fork_fraction=0.6")


# ------------------------------------------------------------------------------- paths made absolute
def test_paths_are_saved_absolute_and_a_rerun_from_the_saved_config_resumes(tmp_path, monkeypatch):
    import yaml

    from resim.pipeline import runner
    from resim.pipeline.stages.encode import data_config_hash

    work = tmp_path / "work"
    (work / "routes").mkdir(parents=True)
    user_yaml = work / "my.yaml"
    user_yaml.write_text((REPO / "configs/pipeline/carla.yaml").read_text().replace("out: null", "out: ds", 1))
    before = user_yaml.read_bytes()
    monkeypatch.chdir(work)
    cfg = load_config("my.yaml", ["sources.carla.root=routes", "ray.address=null"])
    assert cfg.out == work / "ds" and cfg.sources.carla.root == work / "routes"   # was: ds, routes
    out = runner.prepare_out(cfg)
    saved = yaml.safe_load((out / "config.yaml").read_text())
    assert saved["out"] == str(work / "ds") and saved["sources"]["carla"]["root"] == str(work / "routes")
    assert user_yaml.read_bytes() == before                                     # the user's file untouched
    (out / "commits").mkdir()
    (out / "commits" / "unit.json").write_text("{}")                             # OUT now holds a committed unit

    elsewhere = tmp_path / "elsewhere"
    (elsewhere / "routes").mkdir(parents=True)
    monkeypatch.chdir(elsewhere)
    again = load_config(out / "config.yaml")                                    # rerun from the saved config
    assert data_config_hash(again) == data_config_hash(cfg) == (out / "config_hash.txt").read_text().strip()
    runner.prepare_out(again)                                                   # resumes: not "a different config"
    other = load_config(user_yaml, ["sources.carla.root=routes", "ray.address=null", f"out={out}"])
    assert other.sources.carla.root == elsewhere / "routes"                     # the same words, other data
    with pytest.raises(ConfigError, match="different config"):
        runner.prepare_out(other)


# ---------------------------------------------------------------------------------- sample keys
def test_two_sources_whose_samples_would_share_keys_are_refused_at_enumerate(synth_world, tmp_path):
    from resim.pipeline import runner
    from resim.pipeline.runner import EnumerateStage

    world = f"sources.synthetic.root={synth_world}"
    opendv = [f"sources.opendv.root={synth_world / 'opendv'}", "sources.opendv.min_height_px=32"]
    item = sorted(p.relative_to(synth_world / "opendv").as_posix() for p in (synth_world / "opendv").rglob("*.mp4"))[0]
    cfg = _load(world, "sources.synthetic.layouts=[opendv]", *opendv, out=tmp_path / "out")
    with pytest.raises(ConfigError) as e:                                       # was: duplicate __key__s in the shards
        EnumerateStage(cfg)()
    msg = str(e.value)
    assert f"sources.opendv item {item!r} under {synth_world / 'opendv'}" in msg, msg
    assert f"sources.synthetic (layout opendv) item {item!r} under {synth_world / 'opendv'}" in msg, msg
    assert "same keys" in msg and "(2 such pairs in all)" in msg
    with pytest.raises(ConfigError, match="same keys"):                          # the run stops before any unit
        runner.run(cfg, progress=False)
    assert not (tmp_path / "out" / "commits").exists()
    # a source of another kind beside the synthetic world is fine
    ok = _load(world, "sources.synthetic.layouts=[opendv]", f"sources.carla.root={synth_world / 'carla'}",
               out=tmp_path / "out2")
    states, bad = EnumerateStage(ok)()
    assert len(states) == 4 and bad == []
