"""Config validation: every error names its key, before any work starts."""
import pytest

from pipelines.config import PipelineConfig, load_config
from resim.config import ConfigError, from_dict

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
    ("clip.num_future_frames=39", "num_history_frames + num_future_frames"),
    ("labels.labeler.command.window_s=3.0", "labels.labeler.command.window_s"),
    ("labels.labeler.flow.flow_preset=slow", "labels.labeler.flow.flow_preset"),
    ("sources.synthetic.clip.nuscenes={fps_hz: 2}", "layouts"),
    ("encode.vae=/no/such/vae", "encode.vae"),                        # missing path
    ("sources.carla.root=/no/such/dir", "sources.carla.root"),
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


def test_vae_and_text_encoder_flags_override(tmp_path, capsys):
    from resim.cli import main

    vae = REPO / "configs/models/placeholder-cogvideox-vae-tiny"
    rc = main(["pipeline", "check", str(REPO / "configs/pipeline/synthetic.yaml"), "--out", str(tmp_path),
               "--vae", str(vae)])
    assert rc == 0 and f"vae: {vae}" in capsys.readouterr().out
