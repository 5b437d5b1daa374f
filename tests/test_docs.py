"""Every command and snippet in README.md and docs/*.md works as written.

Default suite: every ``marbler-jax`` command parses with the CLI's own parser and reads only what the repository
or an earlier command on its page provides; every other command is one the docs explain; every Python snippet that
needs no run folder runs. ``-m slow``: each page's commands and snippets run in order in a fresh workspace, with
cheap budgets (:func:`cheap`) in place of the hours a documented training takes.
"""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from marbler_jax.registry import canonical_name
from marbler_jax_rl.cli import build_parser
from tests.doc_commands import (NOT_CODE, ROOT, RUNNABLE, Command, Snippet, blocks, expand, inline_commands,
                                page_items, pages)

PAGES = [page.relative_to(ROOT).as_posix() for page in pages()]
NEEDS_RUNS = "runs/"             # a snippet that loads a run folder needs its page's commands first
EXTRAS = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"])


def test_every_fenced_block_is_code_a_reader_can_tell_apart():
    for page in pages():
        for block in blocks(page):
            assert block.lang in RUNNABLE | NOT_CODE, f"{block.where}: fence language {block.lang!r}"
            assert block.skip is None or block.lang in RUNNABLE, f"{block.where}: skip marker on {block.lang}"


def test_a_block_that_is_not_run_says_why():
    skipped = [b for page in pages() for b in blocks(page) if b.skip is not None]
    assert all(len(b.skip) > 10 for b in skipped), skipped
    assert len(skipped) <= 2, "the docs show code to run; an outline is the exception"


class Page:
    """What the commands of one page have made so far (paths relative to the repository root)."""

    def __init__(self):
        self.made: set[str] = set()
        self.variables: dict[str, str] = {}
        self.cwd = "."

    def path(self, text: str) -> str:
        return os.path.normpath(os.path.join(self.cwd, text))

    def make(self, *paths):
        self.made.update(self.path(p) for p in paths if p)

    def require(self, command: Command, text: str, what: str):
        path = self.path(text)
        made = any(path == p or path.startswith(p + "/") for p in self.made)
        assert made or (ROOT / path).exists(), f"{command.where}: {what} {text!r} is neither in the repository " \
                                               f"nor made by a command above it on the page"


def _check_marbler_jax(page: Page, command: Command):
    argv = [expand(a, page.variables) for a in command.argv[1:]]
    try:
        args = build_parser().parse_args(argv)
    except SystemExit:
        pytest.fail(f"{command.where}: `marbler-jax {' '.join(argv)}` does not parse")
    name = args.command
    if name in ("evaluate", "export"):
        page.require(command, args.run, "run folder")
    if name == "render" and "/" in args.target:
        page.require(command, args.target, "run folder")
    if name == "report":
        page.require(command, args.results, "results folder")
    if name == "import":
        page.require(command, args.model, "model")
        page.require(command, args.config, "config")
    if name == "train" and ".py:" in args.scenario:
        page.require(command, args.scenario.split(":")[0], "scenario file")
    if name == "train" and ":" in args.algo:
        roots = [page.path(p) for p in command.env.get("PYTHONPATH", "").split(":") if p]
        module = args.algo.split(":")[0].replace(".", "/") + ".py"
        assert any((ROOT / r / module).exists() for r in roots), f"{command.where}: {module} not on PYTHONPATH"
    if name == "benchmark":
        out = args.out or "results/marbler-table2"
        page.make(out, *(f"{out}/runs/{canonical_name(s)}/{a}" for s in args.scenarios for a in args.algos))
    elif name in ("train", "export", "import", "render", "quickstart"):
        page.make(getattr(args, "out", None), getattr(args, "bundle", None))


def _check_other(page: Page, command: Command):
    argv = list(command.argv)
    if argv[0] == "cd":
        page.require(command, argv[1], "folder")
        page.cwd = page.path(argv[1])
    elif argv[:3] == ["python", "-m", "venv"] or argv[:2] == [".", ".venv/bin/activate"]:
        pass                                         # the Quickstart's fresh environment
    elif argv[:3] == ["python", "-m", "pytest"]:
        pass                                         # this suite
    elif argv[0] == "pip" and argv[1] == "install":
        for target in (a for a in argv[2:] if not a.startswith("-")):
            folder, _, extras = target.partition("[")
            page.require(command, folder, "package")
            assert (ROOT / page.path(folder) / "pyproject.toml").exists(), f"{command.where}: {folder} is no package"
            assert set(filter(None, extras.rstrip("]").split(","))) <= EXTRAS, f"{command.where}: extras {extras}"
    elif argv == ["python", "main.py"]:
        page.require(command, "main.py", "bundle's main.py")
    else:
        pytest.fail(f"{command.where}: {' '.join(argv)!r} is not a command the docs test knows how to check")


@pytest.mark.parametrize("name", PAGES)
def test_documented_commands_parse_and_read_what_exists(name):
    page = Page()
    for item in page_items(ROOT / name):
        if isinstance(item, Snippet):
            continue
        page.variables.update(item.env if not item.argv else {})
        if not item.argv:
            continue
        if item.program == "marbler-jax":
            _check_marbler_jax(page, item)
        else:
            _check_other(page, item)
        if item.program == "marbler-jax" and item.argv[1:2] == ("quickstart",):
            page.make("runs/quickstart")


@pytest.mark.parametrize("name", PAGES)
def test_documented_python_snippets_run(name, monkeypatch):
    """The snippets of a page run in one namespace, in order, from the repository root."""
    monkeypatch.chdir(ROOT)
    scope: dict = {}
    snippets = [s for s in page_items(ROOT / name) if isinstance(s, Snippet) and NEEDS_RUNS not in s.code]
    for snippet in snippets:
        exec(compile(snippet.code, snippet.where, "exec"), scope)
    if name == "README.md":
        assert scope["obs"].shape == (4096, 4, 16) and scope["rewards"].shape == (4096, 4)


def _options(parser) -> dict[str, set[str]]:
    commands = next(a for a in parser._actions if a.dest == "command").choices
    return {name: {flag for action in sub._actions for flag in action.option_strings} for name, sub in commands.items()}


def test_commands_quoted_in_the_prose_name_real_commands_options_and_extras():
    """Inline synopses and fragments (`marbler-jax export RUN --out DIR [--bundle B]`) are not run, but every
    subcommand, option, extra and script they name exists."""
    options = _options(build_parser())
    seen = 0
    for page in pages():
        for where, text in inline_commands(page):
            seen += 1
            tokens = text.replace("[", " ").replace("]", " ").split()
            if tokens[0] == "marbler-jax":
                top = {flag for action in build_parser()._actions for flag in action.option_strings}
                while tokens[1].startswith("-"):               # options of marbler-jax itself (--debug)
                    assert tokens.pop(1) in top, f"{where}: `{text}`"
                if tokens[1] == "...":                          # any subcommand
                    continue
                assert tokens[1] in options, f"{where}: no subcommand {tokens[1]!r} in `{text}`"
                flags = {t.split("=")[0] for t in tokens[2:] if t.startswith("-")}
                assert flags <= options[tokens[1]], f"{where}: `{text}`: {flags - options[tokens[1]]} unknown"
            elif tokens[:2] == ["pip", "install"]:
                extras = {e for quoted in text.split('"')[1::2] if "[" in quoted
                          for e in quoted.split("[", 1)[1].rstrip("]").split(",")}
                assert extras <= EXTRAS, f"{where}: `{text}`: no extra {extras - EXTRAS}"
            elif tokens[1].endswith(".py") and tokens[1] != "main.py":
                assert (ROOT / tokens[1]).exists(), f"{where}: `{text}`: no {tokens[1]}"
    assert seen > 40


OUTPUT_FLAGS = ("--out", "--bundle", "--gif", "--plot", "--json")
OUTPUT_HOMES = ("runs/", "results/", "docs/media/", "bench_out/")   # ignored by git, or what the repo keeps


def test_documented_commands_write_only_where_git_ignores_it_or_the_repository_keeps_it():
    """A reader who copies a command into the repository root must not litter it (``--gif pcp.gif``)."""
    outputs = []
    for page in pages():
        quoted = [(where, text.split()) for where, text in inline_commands(page)]
        fenced = [(c.where, list(c.argv)) for c in page_items(page) if isinstance(c, Command)]
        for where, tokens in quoted + fenced:
            outputs += [(where, value) for flag, value in zip(tokens, tokens[1:]) if flag in OUTPUT_FLAGS]
    assert len(outputs) > 20
    stray = [(w, v) for w, v in outputs
             if not v.startswith(OUTPUT_HOMES) and not v.replace("_", "").isupper() and v != "..."]
    assert not stray, stray


# ---- slow: every page, commands and snippets, in a workspace of its own --------------------------------------

CHEAP = {   # subcommand -> options set to a cheap value (the docs' own values are what the default test parses)
    "train": {"--total-steps": "1", "--test-episodes": "4", "--eval-episodes": "8"},
    "benchmark": {"--total-steps": "1", "--eval-points": "1", "--test-episodes": "4", "--absolute-factor": "1",
                  "--seeds": "2"},
    "evaluate": {"--episodes": "8"},
    "report": {"--reps": "50"},
}
WHOLE_GRID = {"--algos": ["vdn"], "--scenarios": ["predator_capture_prey"]}   # one cell stands for the grid


def cheap(argv: list[str]) -> list[str]:
    """``marbler-jax`` arguments with :data:`CHEAP` budgets; a whole-grid ``benchmark`` trains one cell."""
    command, options = argv[0], dict(CHEAP.get(argv[0], {}))
    out, skip = [command], 0
    for arg in argv[1:]:
        if skip:
            skip -= 1
            continue
        if arg in options:
            skip = 1
            continue
        out.append(arg)
    for flag, value in options.items():
        out += [flag, value]
    if command == "benchmark":
        for flag, values in WHOLE_GRID.items():
            if flag not in argv:
                out += [flag, *values]
    return out + ["--no-progress"] * (command in ("train", "benchmark", "evaluate", "render"))


def _workspace(tmp_path: Path) -> Path:
    """A repository-shaped folder: the examples copied (builds write beside their sources), ``../shared`` linked."""
    ws = tmp_path / "repo"
    ws.mkdir()
    shutil.copytree(ROOT / "examples", ws / "examples", ignore=shutil.ignore_patterns("__pycache__", "*.egg-info"))
    if (ROOT.parent / "shared").exists():
        (tmp_path / "shared").symlink_to(ROOT.parent / "shared")
    return ws


def _rps_python() -> Path:
    from tests.test_bundle import _rps_python as rps

    return rps()


def _run(command: Command, ws: Path, cwd: Path, variables: dict, site: Path) -> Path:
    """Run one documented command (budgets made cheap); returns the working folder after it."""
    argv = [expand(a, variables) for a in command.argv]
    env = {**os.environ, **command.env, "MARBLER_JAX_HEADLESS": "1"}
    paths = [str(site), *(str(cwd / p) for p in command.env.get("PYTHONPATH", "").split(":") if p)]
    env["PYTHONPATH"] = os.pathsep.join(paths)
    if argv[0] == "cd":
        return cwd / argv[1]
    if argv[0] == "marbler-jax":
        argv = [sys.executable, "-m", "marbler_jax_rl", *cheap(argv[1:])]
    elif argv[:2] == ["pip", "install"] and "-e" not in argv:
        argv = [sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--target", str(site), *argv[2:]]
    elif argv == ["python", "main.py"]:
        argv = [str(_rps_python()), "main.py"]
    else:
        return cwd                                   # the environment this suite already runs in
    done = subprocess.run(argv, cwd=cwd, env=env, capture_output=True, text=True, timeout=1200)
    assert done.returncode == 0, f"{command.where}: {' '.join(argv)}\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}"
    return cwd


DISTRIBUTED = "--coordinator"    # needs N processes at once: tests/test_benchmark.py runs two on this host


@pytest.mark.slow
@pytest.mark.parametrize("name", PAGES)
def test_every_documented_command_runs(name, tmp_path, monkeypatch):
    ws = _workspace(tmp_path)
    site, cwd, variables, scope = tmp_path / "site", ws, {}, {}
    site.mkdir()
    monkeypatch.syspath_prepend(str(site))
    for item in page_items(ROOT / name):
        if isinstance(item, Snippet):
            monkeypatch.chdir(ws)
            exec(compile(item.code, item.where, "exec"), scope)
        elif not item.argv:
            variables.update(item.env)
        elif DISTRIBUTED not in item.argv:
            cwd = _run(item, ws, cwd, variables, site)
