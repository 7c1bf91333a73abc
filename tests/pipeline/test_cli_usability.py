"""`resim pipeline ...` from the command line: an unreachable or malformed cluster address is one line and a
non-zero exit, a non-empty OUT that is not a pipeline output is refused, every subcommand has a description."""
import subprocess
import sys
from pathlib import Path

import pytest

from resim.cli import build_parser, main

REPO = Path(__file__).resolve().parents[2]
CONFIG = str(REPO / "configs/pipeline/synthetic.yaml")
NOBODY = "http://127.0.0.1:9"           # the discard port: nothing answers


def _one_line(capsys, *needles):
    err = capsys.readouterr().err.strip()
    assert "Traceback" not in err and len(err.splitlines()) == 1, err
    for n in needles:
        assert n in err, err


@pytest.mark.parametrize("argv,cmd", [
    (["status", "raysubmit_x", "--address", NOBODY], "status"),
    (["logs", "raysubmit_x", "--address", NOBODY], "logs"),
    (["submit", CONFIG, "--address", NOBODY], "submit"),
    (["submit", CONFIG, "--address", "notaurl"], "submit"),
])
def test_an_unreachable_or_malformed_cluster_is_one_line(tmp_path, capsys, argv, cmd):
    if argv[0] == "submit":
        argv = [*argv, "--out", str(tmp_path / "o"), "--set", f"sources.synthetic.root={tmp_path / 'w'}"]
    assert main(["pipeline", *argv]) == 1
    _one_line(capsys, f"resim pipeline {cmd}: error: Ray dashboard at {argv[argv.index('--address') + 1]}")


def test_run_refuses_a_non_empty_out_that_is_not_a_pipeline_output(tmp_path, capsys):
    out = tmp_path / "mine"
    out.mkdir()
    (out / "notes.txt").write_text("keep me")
    assert main(["pipeline", "run", CONFIG, "--out", str(out),
                 "--set", f"sources.synthetic.root={tmp_path / 'w'}"]) == 2
    _one_line(capsys, "is not empty and is not a pipeline output", "notes.txt", "--force")
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]
    assert not (tmp_path / "w").exists()            # refused before the synthetic world is generated


def test_run_into_an_out_that_is_a_file_is_one_line(tmp_path, capsys):
    out = tmp_path / "afile"
    out.write_text("keep me")
    assert main(["pipeline", "run", CONFIG, "--out", str(out),
                 "--set", f"sources.synthetic.root={tmp_path / 'w'}"]) == 2
    _one_line(capsys, "is a file, not a folder")
    assert out.read_text() == "keep me"


def test_a_pipeline_output_or_an_empty_folder_is_not_foreign(tmp_path):
    """Rerunning into OUT resumes: an earlier run's OUT (even an unfinished one) is not refused."""
    from resim.pipeline.cli import foreign_out

    assert foreign_out(tmp_path / "absent") is None and foreign_out(tmp_path) is None
    (tmp_path / "shards").mkdir()
    (tmp_path / "config.yaml").write_text("out: x\n")
    assert foreign_out(tmp_path) is None                 # only what a run writes
    (tmp_path / "notes.txt").write_text("x")
    assert foreign_out(tmp_path) == "notes.txt"
    (tmp_path / "config_hash.txt").write_text("abc\n")  # stamped by `resim pipeline run` before anything else
    assert foreign_out(tmp_path) is None


@pytest.mark.parametrize("cmd", ["run", "check", "submit", "status", "logs"])
def test_every_pipeline_subcommand_has_a_description_and_an_example(cmd, capsys):
    with pytest.raises(SystemExit):
        build_parser().parse_args(["pipeline", cmd, "--help"])
    out = capsys.readouterr().out
    assert f"resim pipeline {cmd} " in out.split("options:")[-1], out
    head = out.split("positional arguments:")[0].split("\n\n")
    assert len(head) >= 2 and head[1].strip(), out


def test_status_of_an_unreachable_cluster_in_a_subprocess_has_no_traceback():
    r = subprocess.run([sys.executable, "-m", "resim", "pipeline", "status", "j", "--address", NOBODY],
                       capture_output=True, text=True, cwd=REPO, timeout=120)
    assert r.returncode == 1 and "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
