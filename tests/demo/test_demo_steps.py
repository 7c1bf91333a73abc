"""The demo's step reuse and its guards, without running the demo (steps are cheap `resim shards ls` calls)."""
import json

import pytest

from resim.cli import main
from resim.config import ConfigError
from resim.demo.run import Step, StepRunner, check_fresh


def _steps(tmp_path, first_target):
    return [Step("first", tmp_path / "a", ["shards", "ls", str(first_target)]),
            Step("second", tmp_path / "b", ["shards", "ls", str(tmp_path)]),
            Step("third", tmp_path / "c", ["shards", "ls", str(tmp_path)])]


def _run(steps):
    r = StepRunner()
    return [r.go(s, i, len(steps)) for i, s in enumerate(steps, 1)]


def test_a_redone_step_redoes_every_later_step(tmp_path, capsys):
    for d in (tmp_path / "x", tmp_path / "y", tmp_path):   # the steps run `resim shards ls` on these: datasets
        (d / "shards").mkdir(parents=True, exist_ok=True)
    assert _run(_steps(tmp_path, tmp_path / "x")) == [True, True, True]
    assert _run(_steps(tmp_path, tmp_path / "x")) == [False, False, False]   # nothing changed: all reused
    # the first step's arguments change: the later steps read its output, so they run again although their own
    # arguments did not change (they used to be reused on top of the new first step)
    assert _run(_steps(tmp_path, tmp_path / "y")) == [True, True, True]
    assert _run(_steps(tmp_path, tmp_path / "y")) == [False, False, False]
    # a later step changing does not redo the earlier ones
    steps = _steps(tmp_path, tmp_path / "y")
    steps[1].argv = ["shards", "ls", str(tmp_path / "x")]
    assert _run(steps) == [False, True, True]
    assert json.loads((tmp_path / "c" / ".done").read_text())["upstream"]


def test_fresh_refuses_to_delete_a_folder_the_demo_did_not_make(tmp_path, capsys):
    (tmp_path / "notes.txt").write_text("keep me")
    with pytest.raises(ConfigError, match="not a demo output folder"):
        check_fresh(tmp_path)
    assert main(["demo", "--out", str(tmp_path), "--fresh"]) == 2
    assert "not a demo output folder" in capsys.readouterr().err
    assert (tmp_path / "notes.txt").read_text() == "keep me"
    check_fresh(tmp_path / "new")            # absent or empty: fine
    (tmp_path / "demo").mkdir()
    (tmp_path / "demo" / "demo_config.yaml").write_text("episodes: 12\n")
    check_fresh(tmp_path / "demo")


def test_demo_bad_override_is_a_clear_error(capsys):
    assert main(["demo", "--set", "bogus=1"]) == 2
    assert "unknown config key bogus" in capsys.readouterr().err
    assert main(["demo", "--set", "workers=0"]) == 2
    assert "workers must be >= 1" in capsys.readouterr().err
    assert main(["demo", "--set", "closed_loop_variants=[policy,bogus]"]) == 2
    assert "closed_loop_variants" in capsys.readouterr().err
