"""The commands and code that README.md and docs/*.md show, read the way a reader copies them.

A page's fenced ``bash`` blocks become :class:`Command` s (one per ``&&``-joined segment, ``\\``-continued lines
joined, comments dropped), its ``python`` blocks :class:`Snippet` s, in page order. A block the docs show as an
outline rather than code to run carries ``<!-- docs-test: skip, REASON -->`` on the line above its fence.
"""
from __future__ import annotations

import dataclasses
import re
import shlex
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FENCE = re.compile(r"^```(\w*)\n(.*?)^```", re.S | re.M)
SKIP = re.compile(r"<!-- docs-test: skip, (.+?) -->\s*$")
RUNNABLE = {"bash", "python"}
NOT_CODE = {"bibtex", "text"}
ASSIGNMENT = re.compile(r"^([A-Za-z_][A-Za-z0-9_]*)=(.*)$")


@dataclasses.dataclass(frozen=True)
class Command:
    """One command of a bash block: ``env`` (``NAME=value`` prefixes), ``argv`` (``$NAME`` left as written)."""
    where: str
    env: dict
    argv: tuple[str, ...]

    @property
    def program(self) -> str:
        return self.argv[0] if self.argv else ""


@dataclasses.dataclass(frozen=True)
class Snippet:
    where: str
    code: str


@dataclasses.dataclass(frozen=True)
class Block:
    page: str
    line: int
    lang: str
    text: str
    skip: str | None          # the reason the page gives for not running it

    @property
    def where(self) -> str:
        return f"{self.page}:{self.line}"


INLINE = re.compile(r"`((?:marbler-jax|pip install|python) [^`]*)`")


def inline_commands(page: Path) -> list[tuple[str, str]]:
    """``(where, text)`` of every command quoted inline in the page's prose (synopses and fragments included)."""
    text = FENCE.sub(lambda m: "\n" * m.group(0).count("\n"), page.read_text())
    name = page.relative_to(ROOT).as_posix()
    return [(f"{name}:{text.count(chr(10), 0, m.start()) + 1}", m.group(1).replace("\\|", "|"))
            for m in INLINE.finditer(text)]


def pages() -> list[Path]:
    return [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]


def blocks(page: Path) -> list[Block]:
    text = page.read_text()
    found = []
    for match in FENCE.finditer(text):
        line = text.count("\n", 0, match.start()) + 1
        above = text[:match.start()].rstrip("\n").rsplit("\n", 1)[-1]
        skip = SKIP.search(above)
        found.append(Block(page.relative_to(ROOT).as_posix(), line, match.group(1), match.group(2),
                           skip.group(1) if skip else None))
    return found


def commands(block: Block) -> list[Command]:
    """The block's commands in order; a line that only assigns (``M=path``) is a command with no argv."""
    logical = re.sub(r"\\\n\s*", " ", block.text).splitlines()
    found = []
    for offset, line in enumerate(logical):
        tokens = shlex.split(line, comments=True)
        segment: list[str] = []
        for token in [*tokens, "&&"]:
            if token != "&&":
                segment.append(token)
                continue
            env = {}
            while segment and ASSIGNMENT.match(segment[0]):
                name, value = ASSIGNMENT.match(segment.pop(0)).groups()
                env[name] = value
            if env or segment:
                found.append(Command(f"{block.where}+{offset}", env, tuple(segment)))
            segment = []
    return found


def expand(token: str, variables: dict) -> str:
    """``$NAME`` / ``${NAME}`` replaced by the page's earlier assignments."""
    return re.sub(r"\$\{?([A-Za-z_][A-Za-z0-9_]*)\}?", lambda m: variables.get(m.group(1), m.group(0)), token)


def page_items(page: Path) -> list[Command | Snippet]:
    """The page's runnable items in reading order (skipped blocks left out)."""
    items: list[Command | Snippet] = []
    for block in blocks(page):
        if block.skip is not None:
            continue
        if block.lang == "bash":
            items.extend(commands(block))
        elif block.lang == "python":
            items.append(Snippet(block.where, block.text))
    return items
