"""The README's command table names only commands that exist: every `resim ...` in its first column (with its
`a|b` alternatives) is a command path of `resim --help`'s parser."""
import argparse
import re
from pathlib import Path

from resim.cli import build_parser

REPO = Path(__file__).resolve().parents[1]


def command_paths(parser: argparse.ArgumentParser, prefix: tuple[str, ...] = ()) -> set[tuple[str, ...]]:
    out = {prefix}
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                out |= command_paths(sub, prefix + (name,))
    return out


def readme_commands(text: str) -> set[tuple[str, ...]]:
    """Each `resim w1 a|b ...` of the table's first column -> its command paths (words before the first
    argument in capitals, option or placeholder)."""
    out = set()
    for line in text.splitlines():
        if not line.startswith("| `resim"):
            continue
        first = line.split(" | ")[0]
        for cmd in re.findall(r"`(resim [^`]+)`", first):
            words = []
            for w in cmd.replace("\\|", "|").split()[1:]:
                if w.startswith("-") or not re.fullmatch(r"[a-z][a-z0-9|-]*", w):
                    break
                words.append(w.split("|"))
            paths = [()]
            for alts in words:
                paths = [p + (a,) for p in paths for a in alts]
            out |= set(paths)
    return out


def test_the_readme_table_names_only_existing_commands():
    table = readme_commands((REPO / "README.md").read_text())
    assert len(table) > 20, table   # the control: the table was read
    missing = sorted(" ".join(p) for p in table - command_paths(build_parser()))
    assert not missing, f"README names commands that do not exist: {missing}"


def test_a_removed_command_in_the_table_is_caught():
    table = readme_commands("| `resim eval commands\\|synth` | x | y |\n| `resim demo` | x | y |\n")
    assert table == {("eval", "commands"), ("eval", "synth"), ("demo",)}
    assert table - command_paths(build_parser()) == {("eval", "synth")}
