"""Every command line a document quotes still runs: the ``lc-*`` lines of the fenced code blocks of README.md,
every ``.md`` under docs/, zoo/ and experiments/ (the notes), and the examples of each command's own ``--help``,
read against today's argparse parsers (built in-process, nothing run). A command no longer installed, a flag
no longer accepted, an older spelling hidden from ``--help`` (a flag kept only so that old command lines keep
working; a document writes today's), a value outside a flag's choices, a subcommand that is gone, and a
``python tools/...`` or ``python -m experiments...`` script that no longer exists all fail, naming the document
and line. The Python scripts kept beside the notes (docs/) and in experiments/ may import, read or patch only
names the packages still have.

The rule for history: a note whose title is followed (within its first five lines) by the banner

    > **Archived** study: its runs were made at commit `C`; commands below are as they were then ...
    > Current command: `...`.

records how past results were made, with the commands and flags of commit C (which must exist in the
repository's history). It keeps its text, and its code blocks are not read here; the banner's own commands
(today's way to the same result) are. Archive a note only when it records history; a live document is updated.

Tolerated in a command line: shell variables (``$P``), placeholders (``...``, ``<run>``, ``{a,b}``, ``RUN``),
comments, continuation lines (joined), environment assignments and ``time``/``nohup`` before the command, and
several commands joined by ``;``, ``&&``, ``|`` or a ``for`` loop.
"""

from __future__ import annotations

import argparse
import re
import shlex
import subprocess
import tomllib
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from lccli import (
    bench,
    calibrate,
    dagger,
    evaluate,
    experiment,
    importer,
    policy,
    predictor,
    record,
    tune,
    view,
)

ROOT = Path(__file__).resolve().parent.parent
ARCHIVED = re.compile(r"^> \*\*Archived\*\* study: its runs were made at commit `(?P<commit>[0-9a-f]{7,40})`;"
                      r".*Current command: (?P<now>.*)$", re.M)  # fmt: skip
"""The banner of an archived note: the commit its runs were made at, and today's command."""
BANNER_LINES = 5
"""The banner stands in the note's first lines, under its title."""

PARSERS: dict[str, Callable[[], argparse.ArgumentParser]] = {
    "lc-record": record.build_parser,
    "lc-train-predictor": predictor.train_predictor_parser,
    "lc-train-policy": policy.train_policy_parser,
    "lc-eval": evaluate.eval_parser,
    "lc-experiment": experiment.experiment_parser,
    "lc-view": view.build_parser,
    "lc-dagger": dagger.dagger_parser,
    "lc-tune": tune.tune_parser,
    "lc-import": importer.build_parser,
    "lc-calibrate": calibrate.build_parser,
    "lc-bench": bench.bench_parser,
}
"""Each console script's parser builder."""

SKIP_LANGUAGES = {"python", "py", "toml", "json", "jsonl", "yaml", "yml", "csv", "diff", "ini"}
"""Fenced blocks in these languages hold no command lines."""
PREFIX_WORDS = {"time", "nohup", "do", "then", "else", "exec", "env", "command", "!"}
SEPARATORS = {";", "&&", "||", "|", "&", "(", ")", "((", "))", ";;", "|&"}
PLACEHOLDER = re.compile(r"[$<>{}*?\[\]]|\.\.\.|…|^[A-Z][A-Z0-9_]+(?![a-z])")
"""A word a person fills in: a variable, ``<run>``, ``{a,b}``, a glob, ``...``, ``RUN``."""


def scripts() -> set[str]:
    """The console scripts the package installs."""
    return set(tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"])


def documents() -> list[Path]:
    """README.md and every note under docs/, zoo/ and experiments/."""
    found = [ROOT / "README.md"]
    for folder in ("docs", "zoo", "experiments"):
        found += sorted((ROOT / folder).rglob("*.md"))
    return [p for p in found if p.is_file()]


def banner(text: str) -> re.Match[str] | None:
    """The archived banner of a note's text, or None for a live document."""
    return ARCHIVED.search("\n".join(text.splitlines()[:BANNER_LINES]))


def _commit_known(commit: str) -> bool | None:
    """Whether ``commit`` is in the repository's history (None: no git here to ask)."""
    try:
        done = subprocess.run(["git", "-C", str(ROOT), "cat-file", "-e", f"{commit}^{{commit}}"],
                              capture_output=True, timeout=30)  # fmt: skip
    except (OSError, subprocess.SubprocessError):
        return None
    if done.returncode != 0 and b"not a git repository" in done.stderr:
        return None
    return done.returncode == 0


@dataclass(frozen=True)
class Quoted:
    where: str
    """``document:line``"""
    text: str
    """The command line, continuation lines joined, comments kept."""


def code_lines(text: str, where: str) -> Iterator[Quoted]:
    """The logical lines of ``text``'s fenced code blocks (continuation lines joined), by first line."""
    fence: str | None = None
    skip = False
    pending: list[str] = []
    start = 0
    for i, line in enumerate(text.splitlines(), 1):
        stripped = line.strip()
        opening = re.match(r"(`{3,}|~{3,})\s*([\w+-]*)", stripped)
        if fence is None:
            if opening:
                fence, skip = opening.group(1), opening.group(2).lower() in SKIP_LANGUAGES
            continue
        if stripped.startswith(fence) and stripped.strip(fence[0]) == "":
            fence = None
            continue
        if skip:
            continue
        if not pending:
            start = i
        if stripped.endswith("\\") and not stripped.lstrip().startswith("#"):
            pending.append(stripped[:-1])
            continue
        pending.append(stripped)
        yield Quoted(f"{where}:{start}", " ".join(pending))
        pending = []
    if pending:
        yield Quoted(f"{where}:{start}", " ".join(pending))


def help_lines(parser: argparse.ArgumentParser) -> Iterator[Quoted]:
    """The command lines a command's own ``--help`` quotes (lines of its description and epilog that start
    with a command), its subcommands' too."""
    parsers = [parser, *(p for a in parser._actions if isinstance(a, argparse._SubParsersAction)
                         for p in a.choices.values())]  # fmt: skip
    for p in parsers:
        for n, line in enumerate(f"{p.description or ''}\n{p.epilog or ''}".splitlines(), 1):
            if re.match(r"\s*(\$ )?lc-[a-z]", line):
                yield Quoted(f"{p.prog} --help:{n}", line.strip().removeprefix("$ "))


def words(line: str) -> list[str]:
    """``line`` as shell words and operators, comments dropped (a line shlex cannot read: cut at `` #``, then
    split on blanks)."""
    lexer = shlex.shlex(line, posix=True, punctuation_chars=";&|()")
    lexer.whitespace_split = True
    lexer.commenters = "#"
    try:
        return list(lexer)
    except ValueError:  # an unbalanced quote: a prose apostrophe
        return re.split(r"\s+", re.split(r"\s#", line, maxsplit=1)[0].strip())


def commands(line: str) -> Iterator[list[str]]:
    """Each simple command of ``line`` as its words, from the command's name on."""
    current: list[str] = []
    for w in [*words(line), ";"]:
        if w not in SEPARATORS:
            current.append(w)
            continue
        while current and (current[0] in PREFIX_WORDS or re.fullmatch(r"[A-Za-z_]\w*=\S*", current[0])):
            current.pop(0)
        if current and current[0] == "for":  # for NAME in WORDS; do ...: the words are no command
            current = []
        if current:
            yield current
        current = []


def _visible(parser: argparse.ArgumentParser, action: argparse.Action) -> list[str]:
    """The flags ``--help`` shows that do what the hidden ``action`` does."""
    return [o for a in parser._actions if a.dest == action.dest and a.help != argparse.SUPPRESS
            for o in a.option_strings]  # fmt: skip


def _takes(action: argparse.Action) -> int | str:
    """How many values an option takes: a count, or ``?``/``*``/``+``."""
    if action.nargs is None:
        return 0 if isinstance(action, (argparse._StoreConstAction, argparse._HelpAction,
                                        argparse._VersionAction, argparse._CountAction)) else 1  # fmt: skip
    return action.nargs if isinstance(action.nargs, (int, str)) else 1


def problems(argv: list[str], parser: argparse.ArgumentParser) -> list[str]:
    """What in ``argv`` (the words after the command's name) today's ``parser`` no longer takes: a flag it
    does not know, one that left (it answers with an error), an older spelling hidden from ``--help``, a value
    outside a flag's choices, a subcommand it does not have."""
    found = []
    i = 0
    while i < len(argv):
        word = argv[i]
        i += 1
        if word == "--":
            break
        if not word.startswith("-") or word == "-" or re.fullmatch(r"-\d[\d.e+-]*", word):
            subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
            if subs:
                if PLACEHOLDER.search(word):  # which subcommand is not said: nothing more to check
                    break
                if word not in subs[0].choices:
                    found.append(f"{word}: no such subcommand (today: {', '.join(subs[0].choices)})")
                    break
                parser = subs[0].choices[word]
            continue
        if PLACEHOLDER.search(word):
            continue
        flag, eq, value = word.partition("=") if word.startswith("--") else (word, "", "")
        action = parser._option_string_actions.get(flag)
        if action is None:
            found.append(f"{flag}: not a flag of {parser.prog} any more")
            continue
        if type(action).__name__ == "_Gone":
            found.append(f"{flag}: removed ({action.where})")  # type: ignore[attr-defined]
        elif action.help == argparse.SUPPRESS:
            key = getattr(action, "key", None)
            today = f"--set {key}={'true' if action.nargs == 0 else 'VALUE'}" if key else " or ".join(_visible(parser, action)) or "nothing"
            found.append(f"{flag}: an older spelling kept for old command lines; write {today}")
        n = _takes(action)
        values: list[str] = [value] if eq else []
        if not eq and n != 0:
            while i < len(argv) and not (argv[i].startswith("-") and not re.fullmatch(r"-\d[\d.e+-]*", argv[i])):
                values.append(argv[i])
                i += 1
                if (isinstance(n, int) and len(values) == n) or n == "?":
                    break
        if action.choices is not None and not isinstance(action, argparse._SubParsersAction):
            allowed = {str(c) for c in action.choices}
            found += [f"{flag} {v}: not one of {', '.join(sorted(allowed))}" for v in values
                      if v not in allowed and not PLACEHOLDER.search(v)]  # fmt: skip
    return found


def script_problem(argv: list[str], doc: Path | None) -> str | None:
    """A ``python`` command's script or module that no longer exists (only the repository's own: ``tools/``,
    ``experiments/``, the packages, a path beside ``doc``)."""
    if not argv:
        return None
    if argv[0] == "-m" and len(argv) > 1:
        module = argv[1]
        top = module.split(".")[0]
        if top not in ("tools", "experiments", "lckit", "lcsim", "lcdata", "lcmodels", "lccli"):
            return None
        base = ROOT / Path(*module.split("."))
        if base.with_suffix(".py").is_file() or (base / "__init__.py").is_file() or (base / "__main__.py").is_file():
            return None
        return f"python -m {module}: no such module"
    script = argv[0]
    if not script.endswith(".py") or PLACEHOLDER.search(script) or Path(script).is_absolute():
        return None
    if (ROOT / script).is_file() or (doc is not None and (doc.parent / script).is_file()):
        return None
    return f"python {script}: no such script"


def rot(quoted: Quoted, doc: Path | None = None) -> list[str]:
    """What is wrong with one quoted line today: every command in it checked."""
    found = []
    for cmd in commands(quoted.text):
        name = cmd[0]
        if name in ("python", "python3") or name.endswith("/python"):
            problem = script_problem(cmd[1:], doc)
            found += [problem] if problem else []
        elif re.fullmatch(r"lc-[a-z][a-z-]*", name):
            if name not in PARSERS:
                found.append(f"{name}: no such command (today: {', '.join(sorted(scripts()))})")
                continue
            found += [f"{name} {p}" for p in problems(cmd[1:], PARSERS[name]())]
    return [f"{quoted.where}: {p}" for p in found]


def test_every_installed_command_has_its_parser_here():
    assert set(PARSERS) == scripts(), "a console script was added or removed: update PARSERS"


@pytest.mark.parametrize("doc", documents(), ids=lambda p: str(p.relative_to(ROOT)))
def test_the_commands_a_document_quotes_still_parse(doc: Path):
    text = doc.read_text(encoding="utf-8")
    where = str(doc.relative_to(ROOT))
    archive = banner(text)
    if archive is not None:
        assert _commit_known(archive["commit"]) is not False, f"{where}: no commit {archive['commit']} in history"
        line = text[: archive.start()].count("\n") + 1
        quoted = [Quoted(f"{where}:{line}", span) for span in re.findall(r"`([^`]+)`", archive["now"])]
        assert quoted, f"{where}: the archived banner names no current command"
    else:
        assert "**Archived**" not in "\n".join(text.splitlines()[:BANNER_LINES]), (
            f"{where}: a malformed archived banner (see this test's docstring)")  # fmt: skip
        quoted = list(code_lines(text, where))
    found = [p for q in quoted for p in rot(q, doc)]
    assert found == [], "quoted command lines today's commands refuse (update them, or archive a note that " \
        "records history):\n" + "\n".join(found)


@pytest.mark.parametrize("name", sorted(PARSERS))
def test_the_examples_of_a_command_s_help_still_parse(name: str):
    found = [p for q in help_lines(PARSERS[name]()) for p in rot(q)]
    assert found == [], "\n".join(found)


def test_a_removed_flag_command_or_script_is_caught():
    def check(line: str) -> list[str]:
        return rot(Quoted("x:1", line))

    assert check("lc-eval zoo:pure-ppo --episodes 200 --seed 0 --json-out e.json") == []
    assert check("LC_THREADS=1 time lc-eval rule --episodes $N \\ --no-record   # the rule's") == []
    assert check("for e in local ray; do lc-experiment --preset quick --out runs/q-$e --executor $e; done") == []
    assert check("lc-import highd 07_tracks.csv --out runs/x --frame-rate 20") == []
    assert check("lc-eval zoo:pure-ppo --no-such-flag 3") == ["x:1: lc-eval --no-such-flag: not a flag of lc-eval "
                                                              "any more"]  # fmt: skip
    assert check("lc-evaluate zoo:pure-ppo")[0].startswith("x:1: lc-evaluate: no such command")
    assert check("lc-import sumo fcd.xml --out x") == ["x:1: lc-import sumo: no such subcommand (today: sumo-fcd, "
                                                       "highd)"]  # fmt: skip
    assert check("lc-experiment --preset huge --out x") == [
        "x:1: lc-experiment --preset huge: not one of " + ", ".join(sorted(experiment.experiment_parser()._option_string_actions["--preset"].choices))]  # fmt: skip
    hidden = check("lc-eval safety-layer:zoo:hybrid-ppo --lookahead-follow zoo:pure-ppo --lookahead-horizon 32")
    assert [h.split(": ", 2)[1] for h in hidden] == ["lc-eval --lookahead-follow", "lc-eval --lookahead-horizon"]
    assert "write --follow" in hidden[0] and "write --set safety.horizon_decisions=VALUE" in hidden[1]
    assert "removed" in check("lc-eval safety-layer:rule --lookahead-margin 1")[0]
    assert check("python tools/no_such_tool.py --x") == ["x:1: python tools/no_such_tool.py: no such script"]
    assert check("python -m experiments.no_such_study") == ["x:1: python -m experiments.no_such_study: no such module"]


def test_code_blocks_join_continuations_and_skip_other_languages():
    text = "x\n```\nlc-eval rule \\\n  --episodes 5\n# lc-nothing --x\n```\n```python\nlc-no = 1\n```\n"
    assert [(q.where, q.text) for q in code_lines(text, "d")] == [
        ("d:3", "lc-eval rule  --episodes 5"), ("d:5", "# lc-nothing --x")]  # fmt: skip
    assert [rot(q) for q in code_lines(text, "d")] == [[], []]


PACKAGES = ("lckit", "lcsim", "lcdata", "lcmodels", "lccli", "experiments", "tools")
"""The repository's own importable top-level names."""


def study_scripts() -> list[Path]:
    """The Python files kept beside the notes (docs/) and in experiments/."""
    return sorted(p for folder in ("docs", "experiments") for p in (ROOT / folder).rglob("*.py"))


def missing_names(path: Path) -> list[str]:
    """What ``path`` imports from the repository's packages, or reads or patches on a class or module it
    imported from them, that no longer exists (found by reading the file, nothing of it run)."""
    import ast
    import importlib
    import inspect

    tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
    known: dict[str, object] = {}
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.split(".")[0] in PACKAGES:
                    try:
                        module = importlib.import_module(alias.name)
                    except ImportError as exc:
                        found.append(f"{path.name}:{node.lineno}: import {alias.name}: {exc}")
                        continue
                    known[alias.asname or alias.name] = module if alias.asname else importlib.import_module(
                        alias.name.split(".")[0])  # fmt: skip
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and (node.module or "").split(".")[0] in PACKAGES:
            try:
                module = importlib.import_module(str(node.module))
            except ImportError as exc:
                found.append(f"{path.name}:{node.lineno}: from {node.module}: {exc}")
                continue
            for alias in node.names:
                if hasattr(module, alias.name):
                    known[alias.asname or alias.name] = getattr(module, alias.name)
                else:
                    try:
                        known[alias.asname or alias.name] = importlib.import_module(f"{node.module}.{alias.name}")
                    except ImportError:
                        found.append(f"{path.name}:{node.lineno}: {node.module} has no {alias.name}")
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id in known:
            owner = known[node.value.id]
            if (inspect.ismodule(owner) or inspect.isclass(owner)) and not hasattr(owner, node.attr):
                try:
                    importlib.import_module(f"{owner.__name__}.{node.attr}")
                except (ImportError, AttributeError):
                    found.append(f"{path.name}:{node.lineno}: {node.value.id}.{node.attr} does not exist")
    return found


@pytest.mark.parametrize("script", study_scripts(), ids=lambda p: str(p.relative_to(ROOT)))
def test_a_study_script_imports_and_patches_only_what_exists(script: Path):
    assert missing_names(script) == [], "fix the script, or remove it and say in its note what it did"


def test_a_script_patching_a_method_that_is_gone_is_caught(tmp_path: Path):
    script = tmp_path / "patch.py"
    script.write_text("from lcsim.sim import HighwaySim\nimport lcsim.planning as planning\n"
                      "full = HighwaySim.no_such_method\nplanning.no_such_function(1)\n"
                      "from experiments.no_such_study import x\n")  # fmt: skip
    assert [m.split(": ", 1)[1] for m in missing_names(script)] == [
        "from experiments.no_such_study: No module named 'experiments.no_such_study'",
        "HighwaySim.no_such_method does not exist", "planning.no_such_function does not exist"]  # fmt: skip
