"""The rerun of a finished pipeline run reports in seconds: it lists the sources, reads the markers and the
prompt table, and does not start Ray. Anything left to do (a unit without its marker, a prompt missing, another
config) takes the normal path."""
import pytest

from .conftest import make_config


def test_a_finished_dataset_is_rerun_without_ray(tmp_path, synth_world, monkeypatch, capsys):
    from resim.pipeline import runner

    over = [f"sources.synthetic.root={synth_world}", "sources.synthetic.layouts=[opendv,carla]"]
    first = runner.run(make_config(tmp_path / "out", [*over, "ray.executor=local"]))
    cfg = make_config(tmp_path / "out", over)                   # the default executor: Ray
    assert cfg.ray.executor == "ray" and runner.finished_listing(cfg) is not None

    def no_ray(cfg):
        raise AssertionError("Ray was started for a finished dataset")

    monkeypatch.setattr(runner, "init_ray", no_ray)
    again = runner.run(cfg)
    assert again.ran == 0 and again.skipped == first.ran == 4
    assert again.stats["clips"] == first.stats["clips"] and again.stats["units"] == first.stats["units"]

    from resim.pipeline.report import format_summary
    assert "nothing to run" in format_summary(again.stats, again.out, again.report_png)

    # anything left to do is not "finished"
    marker = sorted((tmp_path / "out" / "commits").glob("*.json"))[0]
    saved = marker.read_bytes()
    marker.unlink()
    assert runner.finished_listing(cfg) is None
    marker.write_bytes(saved)
    (tmp_path / "out" / "prompts" / "prompts.json").unlink()      # the prompt table was never written
    assert runner.finished_listing(cfg) is None
    assert runner.finished_listing(make_config(tmp_path / "out", [*over, "clip.stride_frames=20"])) is None
