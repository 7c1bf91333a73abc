"""Imports of our own packages go at the top of the file (the style rule: an import hidden in a function hides a
dependency, and a cycle with it). The test parses the source, as tests/test_architecture.py does (nothing is
imported), and counts, per file, the import statements inside functions that import one of our packages
(``from resim... import``, ``import resim...``, relative imports). A file may hold at most the number
``ALLOWED`` gives it, with the reason; any other file none. A file below its number fails too, so the number is
lowered as the imports move and the count only shrinks. Third-party imports are not counted: heavy optional
ones (matplotlib, Ray, diffusers, ...) belong inside the function that needs them, with a comment saying why."""
import ast
from collections import Counter
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
OURS = ("resim", "bench", "scripts")

# Every `resim` call imports the CLI modules to register their subcommands (resim/cli.py COMMANDS), so their
# handlers import what they need (numpy, torch, the models) when they run: `resim --help` stays fast.
CLI = "CLI module: the handlers import their command's modules lazily, so `resim --help` stays fast"
TORCH_LATE = ("resolve_config and the run-folder checks answer `resim train` (--print-config, a bad config) "
              "before torch loads; run_training imports the trainer")
ENCODERS_TORCH_LATE = ("resim.media.device imports torch, which loads only where an encoder is built: the pipeline's driver "
                       "imports this module with the encode and prompt stages and stays torch-free")

# file -> (most function-level imports of our packages, reason)
ALLOWED = {
    "resim/shards/cli.py": (18, CLI),
    "resim/pipeline/cli.py": (12, CLI),
    "resim/pipeline/sources/cli.py": (2, CLI),
    "resim/labeling/cli.py": (4, CLI),
    "resim/train/cli.py": (5, CLI),
    "resim/train/launch.py": (3, CLI),
    "resim/eval/cli.py": (31, CLI),
    "resim/sample/cli.py": (19, CLI),
    "resim/train/tasks/reward/cli.py": (21, CLI),
    "resim/train/tasks/policy_cli.py": (2, CLI),
    "resim/eval/simulate_cli.py": (1, CLI),
    "resim/demo/run.py": (1, CLI),
    "resim/train/run.py": (3, TORCH_LATE),
    "resim/media/encoders.py": (2, ENCODERS_TORCH_LATE),
}


def function_imports(path: Path) -> list[tuple[int, str]]:
    """(line, module as written) of every import of our packages inside a function (at any depth) of ``path``."""
    out = []

    def visit(node, in_function: bool) -> None:
        for child in ast.iter_child_nodes(node):
            if in_function and isinstance(child, ast.Import):
                out.extend((child.lineno, a.name) for a in child.names if a.name.split(".")[0] in OURS)
            elif in_function and isinstance(child, ast.ImportFrom):
                module = "." * child.level + (child.module or "")
                if child.level or module.split(".")[0] in OURS:
                    out.append((child.lineno, module))
            visit(child, in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)))

    visit(ast.parse(path.read_text(), filename=str(path)), False)
    return out


def counts(root: Path) -> dict[str, list[tuple[int, str]]]:
    found = {}
    for pkg in OURS:
        for f in sorted((root / pkg).rglob("*.py")):
            hits = function_imports(f)
            if hits:
                found[f.relative_to(root).as_posix()] = hits
    return found


def problems(found: dict[str, list[tuple[int, str]]], allowed: dict[str, tuple[int, str]]) -> list[str]:
    out = []
    for f, hits in sorted(found.items()):
        most = allowed.get(f, (0, ""))[0]
        if len(hits) > most:
            out.append(f"{f}: {len(hits)} imports of our packages inside functions (allowed {most}); move them to "
                       "the top: " + ", ".join(f"line {n} {m}" for n, m in hits))
    for f, (most, _) in sorted(allowed.items()):
        if len(found.get(f, ())) < most:
            out.append(f"{f}: {len(found.get(f, ()))} imports inside functions now, fewer than {most}: "
                       "lower its number in ALLOWED")
    return out


def test_imports_of_our_packages_are_at_the_top():
    bad = problems(counts(REPO), ALLOWED)
    assert not bad, "function-level imports (see tests/test_imports_at_top.py):\n  " + "\n  ".join(bad)


def test_every_allowance_says_why():
    assert all(isinstance(n, int) and n > 0 and reason.strip() for n, reason in ALLOWED.values())


def test_a_planted_function_import_is_caught(tmp_path):
    (tmp_path / "resim" / "shards").mkdir(parents=True)
    (tmp_path / "resim" / "shards" / "a.py").write_text(
        "import json\nfrom resim.shards import schema\n\n\n"           # top level: fine
        "def f():\n    import numpy\n    return numpy\n\n\n"      # third-party: not counted
        "class C:\n    def m(self):\n        from resim.shards.reader import iter_samples\n        return iter_samples\n\n\n"
        "def g():\n    def h():\n        from . import layout\n        return layout\n    return h\n")
    found = counts(tmp_path)
    assert found == {"resim/shards/a.py": [(12, "resim.shards.reader"), (18, ".")]}
    assert len(problems(found, {})) == 1
    assert problems(found, {"resim/shards/a.py": (2, "reason")}) == []
    assert "lower its number" in problems(found, {"resim/shards/a.py": (3, "reason")})[0]
