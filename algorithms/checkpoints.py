"""Checkpoints a resume can trust: a SHA-256 manifest beside every checkpoint, checked before a restore.

Orbax commits a checkpoint atomically but does not notice a file that changed afterwards (a flipped
byte restores silently as other numbers). Each orbax step folder therefore gets ``manifest.sha256``,
written last, listing every file's digest; a step folder without one was interrupted before it was
verified. :func:`restore_latest` walks back from the newest step to the newest one whose manifest
matches and that restores, with one warning line per skipped step. Single files (``params.npz``) get a
``<name>.sha256`` beside them.
"""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Callable

from marbler_jax.numpy_policy import file_sha256

MANIFEST = "manifest.sha256"


def atomic_write(path: Path, data: bytes | str) -> None:
    """Write ``data`` to ``path`` through a temporary file and a rename: never a half-written file."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(data.encode() if isinstance(data, str) else data)
    os.replace(tmp, path)


def read_json(path, default=None, kind=dict):
    """The JSON value in the file ``path`` (``default`` where the file does not exist, if given), checked to
    be a ``kind``; a damaged or misshapen file is a ``ValueError`` naming it and the place."""
    path = Path(path)
    if default is not None and not path.exists():
        return default
    try:
        value = json.loads(path.read_text())
    except json.JSONDecodeError as err:
        raise ValueError(f"{path} is not valid JSON (line {err.lineno}, column {err.colno}: {err.msg})") from None
    except (OSError, UnicodeDecodeError) as err:
        raise ValueError(f"cannot read {path}: {err}") from None
    if not isinstance(value, kind):
        raise ValueError(f"{path} holds a JSON {type(value).__name__}, expected an object")
    return value


def read_json_lines(path) -> list:
    """The JSON values of the file ``path``, one per non-empty line; a damaged line is a ``ValueError``
    naming the file and the line."""
    path = Path(path)
    values = []
    for number, line in enumerate(path.read_text().splitlines(), 1):
        if line.strip():
            try:
                values.append(json.loads(line))
            except json.JSONDecodeError as err:
                raise ValueError(f"{path} line {number} is not valid JSON ({err.msg}, column {err.colno})") from None
    return values


def write_manifest(folder: Path) -> None:
    """``folder/manifest.sha256``: ``<digest>  <relative path>`` for every file below ``folder``."""
    folder = Path(folder)
    files = sorted(p for p in folder.rglob("*") if p.is_file() and p.name != MANIFEST)
    atomic_write(folder / MANIFEST, "".join(f"{file_sha256(p)}  {p.relative_to(folder).as_posix()}\n"
                                            for p in files))


def manifest_problem(folder: Path) -> str | None:
    """What is wrong with ``folder`` against its manifest (``None``: every listed file is intact)."""
    folder = Path(folder)
    manifest = folder / MANIFEST
    if not manifest.exists():
        return "it has no manifest (written before it was verified)"
    for line in manifest.read_text().splitlines():
        digest, _, name = line.partition("  ")
        if not name or len(digest) != 64:
            return f"its manifest is damaged ({MANIFEST})"
        path = folder / name
        if not path.is_file():
            return f"{name} is missing"
        if file_sha256(path) != digest:
            return f"{name} changed after it was written (checksum mismatch)"
    return None


def save(manager, step: int, tree) -> None:
    """Save ``tree`` as orbax step ``step`` of ``manager`` and then its manifest."""
    import orbax.checkpoint as ocp

    manager.save(step, args=ocp.args.StandardSave(tree), force=True)
    manager.wait_until_finished()
    write_manifest(step_folder(manager, step))


def step_folder(manager, step: int) -> Path:
    return Path(manager.directory) / str(step)


def latest_step(directory: Path) -> int | None:
    """The newest step orbax holds in the checkpoint folder ``directory`` (None where there is none);
    reads only."""
    if not Path(directory).is_dir():
        return None
    import orbax.checkpoint as ocp

    manager = ocp.CheckpointManager(Path(directory).absolute(), options=ocp.CheckpointManagerOptions(create=False))
    try:
        return manager.latest_step()
    finally:
        manager.close()


def restore_latest(manager, template=None, warn: Callable[[str], None] = print, manifests: bool = True):
    """``(step, tree)`` of the newest intact step of ``manager`` (``(None, None)`` when it has none).

    A step is intact when its manifest matches and orbax restores it. Newer steps that are not are
    reported through ``warn`` (one line each) and moved to ``<checkpoints>.damaged/`` (kept for a look,
    out of orbax's way), so the run writes them anew. ``manifests=False`` (a run folder from before
    manifests): where no step has one, orbax's restore alone is trusted. ``ValueError`` when steps exist
    but none is intact."""
    import orbax.checkpoint as ocp

    steps = sorted(manager.all_steps(), reverse=True)
    verified = manifests or any((step_folder(manager, s) / MANIFEST).exists() for s in steps)
    args = ocp.args.StandardRestore(template) if template is not None else ocp.args.StandardRestore()
    for step in steps:
        problem = manifest_problem(step_folder(manager, step)) if verified else None
        if problem is None:
            try:
                return step, manager.restore(step, args=args)
            except Exception as err:   # orbax and TensorStore raise many types for damaged folders
                problem = f"it cannot be restored ({type(err).__name__}: {str(err).splitlines()[0][:160]})"
        aside = _move_aside(step_folder(manager, step))
        warn(f"warning: skipping checkpoint {step_folder(manager, step)}: {problem}; moved to {aside}")
        manager.reload()
    if steps:
        raise ValueError(f"no intact checkpoint left in {manager.directory}; start the run anew in another folder")
    return None, None


def _move_aside(folder: Path) -> Path:
    import shutil

    target = folder.parent.with_name(folder.parent.name + ".damaged") / folder.name
    n = 1
    while target.exists():
        target = target.with_name(f"{folder.name}.{n}")
        n += 1
    target.parent.mkdir(parents=True, exist_ok=True)
    shutil.move(str(folder), str(target))
    return target


def write_file_checksum(path: Path) -> None:
    """``<path>.sha256`` beside ``path``."""
    path = Path(path)
    atomic_write(path.with_name(path.name + ".sha256"), f"{file_sha256(path)}  {path.name}\n")


def check_file(path: Path) -> None:
    """``ValueError`` naming ``path`` when it differs from its ``.sha256`` (no checksum file: unchecked)."""
    path = Path(path)
    sidecar = path.with_name(path.name + ".sha256")
    if sidecar.exists() and sidecar.read_text().split("  ")[0] != file_sha256(path):
        raise ValueError(f"{path} changed after it was written (checksum mismatch with {sidecar.name})")


__all__ = ["MANIFEST", "write_manifest", "manifest_problem", "save", "restore_latest", "write_file_checksum",
           "check_file", "atomic_write", "step_folder"]
