"""`resim shards features SRC --out OUT`: a non-empty OUT that is not a shard dataset is refused (the copy would
mix into it); a new/empty OUT or an earlier output is accepted; the help has an example."""
import pytest

from resim.cli import build_parser, main

from .test_cli_errors import TINY_SETS, two_episodes  # noqa: F401  (fixture)


def test_features_refuses_a_non_empty_unrelated_out(two_episodes, tmp_path, capsys):  # noqa: F811
    out = tmp_path / "mine"
    out.mkdir()
    (out / "notes.txt").write_text("keep me")
    assert main(["shards", "features", str(two_episodes), "--out", str(out), *TINY_SETS]) == 1
    err = capsys.readouterr().err.strip()
    assert err.splitlines() == [f"resim shards features: error: output folder {out} is not empty and is not a shard "
                                "dataset (it holds notes.txt); give an empty or new folder"]
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]


def test_an_earlier_output_or_an_empty_folder_is_accepted(tmp_path):
    from resim.train.tasks.reward.cli import _check_features_out

    _check_features_out(tmp_path / "absent")
    _check_features_out(tmp_path)
    for d in ("shards", "index", "manifest", "prompts", "quarantine"):
        (tmp_path / d).mkdir()
    (tmp_path / "config.yaml").write_text("x: 1\n")
    _check_features_out(tmp_path)                     # a rerun redoes an earlier output
    (tmp_path / "f").write_text("x")
    with pytest.raises(ValueError, match="not a shard dataset"):
        _check_features_out(tmp_path)


def test_features_help_has_an_example(capsys):
    with pytest.raises(SystemExit):
        build_parser().parse_args(["shards", "features", "--help"])
    assert "example:\n  resim shards features " in capsys.readouterr().out
