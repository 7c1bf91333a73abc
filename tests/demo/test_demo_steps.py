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


def test_a_step_s_output_goes_to_its_log_and_the_console_gets_one_line(tmp_path, capfd):
    (tmp_path / "shards").mkdir()
    r = StepRunner(tmp_path / "logs")
    assert r.go(Step("list it", tmp_path / "a", ["shards", "ls", str(tmp_path)]), 1, 2)
    out = capfd.readouterr()
    assert out.out.count("\n") == 1 and out.out.startswith("[demo 1/2] list it: done in "), out
    log = tmp_path / "logs" / "01-list-it.log"
    assert str(log) in out.out
    assert log.read_text().strip()          # what `resim shards ls` printed is in the log, not on the console
    # a failing step ends with the tail of its log, the command and where the whole output is
    with pytest.raises(SystemExit, match=r"(?s)demo step 'broken' failed \(exit \d+\).*02-broken\.log"):
        r.go(Step("broken", tmp_path / "b", ["shards", "ls", str(tmp_path / "nowhere")]), 2, 2)
    assert (tmp_path / "logs" / "02-broken.log").read_text().strip()
