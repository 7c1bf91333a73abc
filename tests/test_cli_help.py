"""The shape of `resim`'s command line, against the checked-in tests/support/cli_snapshot.json: the top-level
commands in `resim --help` order, and for every command path (`resim train world`, `resim shards features`, ...)
the options of its usage line (every spelling: `-q`, `--quiet`). A command or option renamed, removed or added fails here, so that the README,
docs/ and every caller move with it (tests/test_readme_commands.py checks the README's table). After an intended
change, regenerate the snapshot from the repository root and review its diff:

    python -m tests.test_cli_help --update

The old names in resim.cli.RETIRED answer with one line on stderr naming what to use now, and exit 2."""
import argparse
import json
import re
import sys
from pathlib import Path

import pytest

from resim.cli import RETIRED, RETIRED_FLAGS, SETTINGS_COMMANDS, build_parser, main, retired_flag

REPO = Path(__file__).resolve().parents[1]
SNAPSHOT = REPO / "tests" / "support" / "cli_snapshot.json"
UPDATE = "python -m tests.test_cli_help --update"


def _subcommands(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    """name -> parser of the subcommands of ``parser``, in --help order (empty for a leaf command)."""
    return {name: sub for a in parser._actions if isinstance(a, argparse._SubParsersAction)
            for name, sub in a.choices.items()}


def command_paths(parser: argparse.ArgumentParser,
                  prefix: tuple[str, ...] = ()) -> dict[tuple[str, ...], argparse.ArgumentParser]:
    """Every command path below ``parser`` (the root's is ``()``) -> its parser."""
    out = {prefix: parser}
    for name, sub in _subcommands(parser).items():
        out.update(command_paths(sub, prefix + (name,)))
    return out


def usage_options(parser: argparse.ArgumentParser) -> list[str]:
    """The option names its usage line stands for: every spelling of every option it shows (hidden ones, with
    help=SUPPRESS, are not shown; -h/--help, which every command has, is left out)."""
    return sorted(s for a in parser._actions if a.help is not argparse.SUPPRESS
                  and not isinstance(a, argparse._HelpAction) for s in a.option_strings)


def snapshot(parser: argparse.ArgumentParser | None = None) -> dict:
    """{"commands": top-level commands in --help order, "options": {"resim PATH": its usage_options}}."""
    parser = parser or build_parser()
    return {"commands": list(_subcommands(parser)),
            "options": {" ".join(("resim", *path)): usage_options(p) for path, p in command_paths(parser).items()}}


def snapshot_diff(want: dict, got: dict) -> list[str]:
    """What differs, one line each ("+" in the parser now, "-" only in the snapshot)."""
    lines = []
    if want["commands"] != got["commands"]:
        lines.append(f"top-level commands: snapshot {want['commands']}, parser {got['commands']}")
    for cmd in sorted(set(want["options"]) | set(got["options"])):
        if cmd not in got["options"]:
            lines.append(f"- {cmd} (no longer a command)")
        elif cmd not in want["options"]:
            lines.append(f"+ {cmd} (a new command) {' '.join(got['options'][cmd])}")
        else:
            gone = sorted(set(want["options"][cmd]) - set(got["options"][cmd]))
            new = sorted(set(got["options"][cmd]) - set(want["options"][cmd]))
            if gone or new:
                lines.append(f"  {cmd}: " + " ".join([*(f"-{o}" for o in gone), *(f"+{o}" for o in new)]))
    return lines


def test_the_command_line_matches_the_snapshot():
    assert SNAPSHOT.is_file(), f"{SNAPSHOT.relative_to(REPO)} is missing: write it with `{UPDATE}`"
    want, got = json.loads(SNAPSHOT.read_text()), snapshot()
    diff = snapshot_diff(want, got)
    assert not diff, ("the command line differs from tests/support/cli_snapshot.json:\n" + "\n".join(diff) +
                      f"\nIf the change is intended, update the README, docs/ and the callers (old names go to "
                      f"resim.cli.RETIRED), then regenerate the snapshot from the repository root with `{UPDATE}` "
                      "and review its diff.")


def test_the_snapshot_was_read():
    """The control: the snapshot covers the commands this test is about, with their options."""
    snap = json.loads(SNAPSHOT.read_text())
    assert {"shards", "train", "score", "eval"} <= set(snap["commands"])
    assert {"--out", "--threads", "--preset"} <= set(snap["options"]["resim shards features"])
    assert {"--checkpoint", "--shards", "--stride", "--json"} <= set(snap["options"]["resim score"])
    assert {"--shards", "--out", "--window", "--decoded-vae"} <= set(snap["options"]["resim train idm"])
    assert "--steps" in snap["options"]["resim train world"]


def test_a_changed_option_or_command_is_reported():
    want = {"commands": ["a", "b"], "options": {"resim a": ["--x", "--y"], "resim b": ["--z"]}}
    got = {"commands": ["a", "c"], "options": {"resim a": ["--x", "--w"], "resim c": ["--z"]}}
    assert snapshot_diff(want, got) == ["top-level commands: snapshot ['a', 'b'], parser ['a', 'c']",
                                        "  resim a: ---y +--w", "- resim b (no longer a command)",
                                        "+ resim c (a new command) --z"]
    assert snapshot_diff(want, want) == []


MAX_OPTIONS = 16   # past ~15 a usage line stops being read; the rest goes to --config / --set (resim.sample.settings)


def option_count(parser: argparse.ArgumentParser) -> int:
    """The options its usage line shows, each counted once whatever its spellings (-h/--help left out)."""
    return sum(1 for a in parser._actions if a.option_strings and a.help is not argparse.SUPPRESS
               and not isinstance(a, argparse._HelpAction))


def test_no_command_has_more_than_a_handful_of_options():
    crowded = {" ".join(("resim", *path)): option_count(p) for path, p in command_paths(build_parser()).items()
               if option_count(p) > MAX_OPTIONS}
    assert not crowded, f"commands with more than {MAX_OPTIONS} options (group the rest under --set): {crowded}"


def test_the_option_count_is_read_from_the_parser():
    """The control: a parser with 17 options is crowded, one with 16 is not; two spellings are one option."""
    for n, crowded in ((MAX_OPTIONS, False), (MAX_OPTIONS + 1, True)):
        p = argparse.ArgumentParser()
        for i in range(n):
            p.add_argument(f"--o{i}")
        assert (option_count(p) > MAX_OPTIONS) is crowded
    p = argparse.ArgumentParser()
    p.add_argument("-q", "--quiet", action="store_true")
    assert option_count(p) == 1


def test_a_flag_that_became_a_setting_answers_with_the_setting(capsys):
    """Every flag the sampling commands gave up: not an option of them any more, and an old script's use of it
    gets one line naming the --set that replaced it, which the command accepts."""
    paths = command_paths(build_parser())
    for cmd in SETTINGS_COMMANDS:
        assert not set(RETIRED_FLAGS) & set(usage_options(paths[cmd])) - {"--speed-mps"}, cmd
    assert "--speed-mps" in usage_options(paths[("plan",)])   # plan's own: no answer shadows it
    assert retired_flag(["plan", "--speed-mps", "3"]) is None
    cases = [(["sample", "--guidance-scale", "3"], "--set rollout.guidance.scale_start=S"),
             (["eval", "closed-loop", "--states", "2"], "--set closed_loop.states=N"),
             (["simulate", "--state-seed", "5"], "--set simulate.state_seed=S"),
             (["eval", "commands", "--horizons", "1"], "--set commands.horizons_s="),
             (["eval", "quality", "--fid-weights=w.pth"], "--set quality.fid_weights=FILE")]
    for argv, needle in cases:
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"resim {argv[0]}") and needle in err and len(err.splitlines()) == 1, err
    # not retired where the command never had it, nor on commands that keep it (eval vae --group-ends)
    assert retired_flag(["sample", "--horizons", "1"]) is None
    assert retired_flag(["eval", "vae", "--group-ends"]) is None
    assert retired_flag(["eval", "command-loss", "--batch-size", "4"]) is None


RENAMED = {("reward",): ("score",), ("reward-features",): ("shards", "features"), ("eval", "idm"): ("train", "idm")}


@pytest.mark.parametrize("old", sorted(RETIRED), ids=" ".join)
def test_an_old_name_answers_in_one_line_naming_the_new_one(old, capsys):
    paths = command_paths(build_parser())
    assert old not in paths   # no longer offered
    assert not [p for p in paths if p[:len(old)] == old]   # and the match on the leading words hides no command
    for argv in ([*old], [*old, "--help"], [*old, "some/arg", "--out", "x"]):
        assert main(argv) == 2, argv
        out, err = capsys.readouterr()
        assert out == "" and err.endswith("\n") and len(err.splitlines()) == 1, (argv, err)
        assert err.startswith(f"resim {' '.join(old)}: "), err
    now = re.search(r"use `resim ([^`]+)`", err)
    if old in RENAMED:
        assert now and tuple(now.group(1).split()) == RENAMED[old], err
    if now:   # the new name is a command
        assert tuple(now.group(1).split()) in paths, err


def test_the_renames_of_the_cli_grouped_by_noun_are_retired():
    assert set(RENAMED) <= set(RETIRED)


@pytest.mark.parametrize("argv", [["train", "reward"], ["score"], ["shards", "features"], ["train", "idm"],
                                  ["eval", "quality"]], ids=" ".join)
def test_the_new_names_and_their_neighbours_answer_help(argv, capsys):
    """`resim train reward` is not `resim reward`: the retired names match the leading words only."""
    with pytest.raises(SystemExit) as e:
        main([*argv, "--help"])
    assert e.value.code == 0
    assert capsys.readouterr().out.startswith(f"usage: resim {' '.join(argv)} ")


def test_the_demo_runs_only_existing_commands(tmp_path):
    from resim.demo.run import DemoConfig, build_steps, eval_steps, rollout_steps

    cfg, parser = DemoConfig(), build_parser()
    steps = [*build_steps(cfg, tmp_path), *rollout_steps(cfg, tmp_path, "some_key"), *eval_steps(cfg, tmp_path)]
    assert len(steps) > 8
    for step in steps:
        parser.parse_args(step.argv)   # an unknown command or option exits 2


if __name__ == "__main__":
    if sys.argv[1:] != ["--update"]:
        sys.exit(f"usage: {UPDATE}   (rewrites {SNAPSHOT.relative_to(REPO)} from resim.cli.build_parser)")
    SNAPSHOT.write_text(json.dumps(snapshot(), indent=2) + "\n")
    print(f"wrote {SNAPSHOT.relative_to(REPO)}: review its diff (git diff {SNAPSHOT.relative_to(REPO)})")
