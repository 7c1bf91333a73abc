"""`resim synth` user mistakes: one line `resim synth: error: ...` on stderr, exit 2 for usage/config errors and
1 for I/O, no traceback; the help says the default preset."""
import pytest

from resim.cli import build_parser, main


def _one_line(capsys, *needles):
    err = capsys.readouterr().err.strip()
    assert "Traceback" not in err, err
    last = err.splitlines()[-1]
    assert last.startswith("resim synth: error: "), err
    for n in needles:
        assert n in last, err


@pytest.mark.parametrize("extra,needle", [
    (["--episodes", "-3"], "--episodes: must be >= 1"),
    (["--episodes", "0"], "--episodes: must be >= 1"),
    (["--workers", "-2"], "--workers: must be >= 1"),
    (["--workers", "0"], "--workers: must be >= 1"),
    (["--preset", "nope"], "unknown preset 'nope'"),
    (["--set", "episod_s=10"], "unknown config key episod_s"),
    (["--set", "episode_s=abc"], "episode_s"),
    (["--set", "episode_s=-1"], "episode_s"),
    (["--config", "/nope.yaml"], "/nope.yaml"),
])
def test_usage_and_config_mistakes_exit_2_in_one_line(tmp_path, capsys, extra, needle):
    out = tmp_path / "w"
    try:
        rc = main(["synth", "--out", str(out), "--episodes", "1", "--quiet", *extra])
    except SystemExit as e:           # argparse type errors exit from parse_args
        rc = e.code
    assert rc == 2
    _one_line(capsys, needle)
    assert not out.exists()


def test_a_non_empty_out_is_refused_without_overwrite(tmp_path, capsys):
    (tmp_path / "notes.txt").write_text("keep me")
    assert main(["synth", "--out", str(tmp_path), "--episodes", "1", "--quiet"]) == 2
    _one_line(capsys, str(tmp_path), "not empty", "--overwrite")
    assert (tmp_path / "notes.txt").read_text() == "keep me"
    f = tmp_path / "file"
    f.write_text("x")
    assert main(["synth", "--out", str(f), "--episodes", "1", "--quiet"]) == 2
    _one_line(capsys, "not a folder")


def test_an_out_that_cannot_be_created_is_an_io_error(tmp_path, capsys):
    (tmp_path / "file").write_text("x")
    assert main(["synth", "--out", str(tmp_path / "file" / "x"), "--episodes", "1", "--quiet"]) == 1
    _one_line(capsys, "cannot write there")


def test_help_names_the_default_preset_and_has_an_example(capsys):
    with pytest.raises(SystemExit):
        build_parser().parse_args(["synth", "--help"])
    out = capsys.readouterr().out
    assert "default preset demo: 128x224 frames, 16-s episodes" in out
    assert "examples:\n  resim synth --out" in out
