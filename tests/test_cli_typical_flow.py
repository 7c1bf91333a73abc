"""The "typical flow" of `resim --help` runs as written, in order (run end to end by hand in an empty folder;
here: every line parses, and what each step needs from the earlier ones is there)."""
import shlex

import pytest

from resim.cli import EPILOG, build_parser, main


def flow_commands() -> list[list[str]]:
    text = EPILOG.split("typical flow", 1)[1].split("\n\n", 1)[0].replace("\\\n", " ")
    cmds = [shlex.split(line, comments=True) for line in text.splitlines()[1:]]
    return [c[1:] for c in cmds if c and c[0] == "resim"]


def _opt(argv: list[str], name: str, default=None):
    return argv[argv.index(name) + 1] if name in argv else default


def test_every_flow_line_parses():
    p = build_parser()
    for argv in flow_commands():
        p.parse_args([a.replace("KEY", "some_key") for a in argv])


def test_the_pipeline_reads_the_world_synth_wrote_and_has_enough_episodes(tmp_path):
    """synth's world must be the config's (else: config error "not made with this config's episodes/seed/preset"),
    and `train reward` needs >= 12 episodes to split hazardous and clean held-out episodes."""
    from resim.pipeline.load import load_config
    from resim.pipeline.sources.synth.generate import SYNTH_PRESETS

    cmds = flow_commands()
    synth = next(c for c in cmds if c[0] == "synth")
    run = next(c for c in cmds if c[:2] == ["pipeline", "run"])
    sets = [run[i + 1] for i, a in enumerate(run) if a == "--set"]
    cfg = load_config(run[2], [*sets, f"sources.synthetic.root={tmp_path / 'absent'}"], out=tmp_path / "o")
    syn = cfg.sources.synthetic
    assert _opt(synth, "--out") == "data/synth" and "root: data/synth" in open(run[2]).read()
    assert _opt(synth, "--preset", "demo") == syn.preset in SYNTH_PRESETS
    assert int(_opt(synth, "--episodes", 12)) == syn.episodes >= 12
    assert int(_opt(synth, "--seed", 0)) == syn.seed


def test_each_step_reads_what_an_earlier_step_wrote():
    cmds = flow_commands()
    written: set[str] = set()
    for argv in cmds:
        for flag in ("--shards", "--checkpoint", "--reward", "--heldout-from"):
            if flag in argv:
                assert _opt(argv, flag) in written, (argv, flag)
        if argv[:2] == ["eval", "quality"]:     # random-init metric networks need saying so, or weights
            assert "--allow-placeholder-networks" in argv or any("quality.fvd_weights" in a for a in argv)
        if "--out" in argv:
            written.add(_opt(argv, "--out"))
    assert any(c[:2] == ["shards", "ls"] and "--samples" in c for c in cmds)   # where KEY comes from


def test_top_level_help_shows_the_flow(capsys):
    with pytest.raises(SystemExit):
        main(["--help"])
    assert "resim shards ls out/shards --samples" in capsys.readouterr().out


def test_ctrl_c_is_one_line_and_exit_130(monkeypatch, capsys):
    """Ctrl-C anywhere in a command: no KeyboardInterrupt traceback, exit 130 (128 + SIGINT)."""
    import argparse

    import resim.cli as cli

    def interrupted(_args):
        raise KeyboardInterrupt

    def parser():
        p = argparse.ArgumentParser(prog="resim")
        sub = p.add_subparsers(dest="command")
        sub.add_parser("train").set_defaults(func=interrupted)
        return p

    monkeypatch.setattr(cli, "build_parser", parser)
    assert cli.main(["train"]) == 130
    err = capsys.readouterr().err.strip()
    assert err == "resim train: interrupted (Ctrl-C)"
