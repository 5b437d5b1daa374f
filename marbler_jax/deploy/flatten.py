"""Flatten marbler-jax modules into the single folder the Robotarium accepts, without JAX.

The bundle does not carry a second, hand-maintained copy of any logic: each bundled file is the
package module itself, rewritten on its syntax tree by :func:`flatten_module`:

* package imports become flat ones (``from marbler_jax import physics`` -> ``import physics``,
  ``from marbler_jax.scenarios.base import X`` -> ``from scenario_base import X``);
* ``jax`` / ``flax`` imports are dropped, and so is every function that uses them -- only the
  JAX-only samplers (``reset`` and the spawn helpers, :data:`JAX_ONLY`) may be dropped; the bundle
  starts its episodes from initial states sampled at export time;
* ``@struct.dataclass`` scenario states become :func:`marbler_jax.xp.frozen_state` dataclasses;
* annotations that name JAX types become plain strings;
* f-strings become ``'...'.format(...)`` calls: ``ast.unparse`` on Python >= 3.12 may reuse an f-string's
  outer quotes inside it (PEP 701), which Python 3.11 and older cannot parse.

:func:`check_flat_source` then proves the result imports neither JAX nor flax nor ``marbler_jax``.
"""
from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = "marbler_jax"
PACKAGE_DIR = Path(__file__).resolve().parent.parent
JAX_MODULES = ("jax", "jaxlib", "flax", "optax", "orbax")
JAX_ONLY = frozenset({"reset", "grid_positions", "distinct_indices", "spawn_band", "sample_grid_points"})
ALLOWED_EXTENSIONS = frozenset({".py", ".npy", ".mat", ".tiff", ".png", ".jpg", ".jpeg", ".gif", ".bmp", ".m",
                                ".mexa64"})

# package module -> bundle file stem
CORE_MODULES = {
    "marbler_jax.xp": "xp",
    "marbler_jax.physics": "physics",
    "marbler_jax.controllers": "controllers",
    "marbler_jax.cbf": "cbf",
    "marbler_jax.control_loop": "control_loop",
    "marbler_jax.numpy_policy": "numpy_policy",
    "marbler_jax.scenarios.base": "scenario_base",
    "marbler_jax.deploy.robotarium_loop": "robotarium_loop",
    "marbler_jax.deploy.main": "main",
}


def module_path(module: str) -> Path:
    """Source file of module ``module`` (a package module or, e.g., a user's scenario module)."""
    import importlib.util
    import sys

    loaded = getattr(sys.modules.get(module), "__file__", None)
    if loaded and loaded.endswith(".py"):
        return Path(loaded)
    spec = importlib.util.find_spec(module)
    if spec is None or not spec.origin or not spec.origin.endswith(".py"):
        raise ValueError(f"cannot find the Python source of module {module!r}")
    return Path(spec.origin)


def _jax_imports(nodes) -> set[str]:
    """Names bound by ``import jax ...`` / ``from jax|flax ... import ...`` statements among ``nodes``."""
    names = set()
    for node in nodes:
        if isinstance(node, ast.Import):
            names |= {(a.asname or a.name).split(".")[0] for a in node.names if _is_jax_module(a.name)}
        elif isinstance(node, ast.ImportFrom) and _is_jax_module(node.module):
            names |= {a.asname or a.name for a in node.names}
    return names


def _uses(node: ast.AST, names: set[str]) -> bool:
    return any(isinstance(n, ast.Name) and n.id in names for n in ast.walk(node))


def _is_jax_module(name: str | None) -> bool:
    return bool(name) and name.split(".")[0] in JAX_MODULES


class _Flattener(ast.NodeTransformer):
    def __init__(self, names: dict[str, str], source: str, jax_names: set[str], dropped_elsewhere: dict):
        self.names = names
        self.dropped_elsewhere = dropped_elsewhere  # package module -> its dropped (JAX-only) functions
        self.source = source
        self.jax_names = jax_names   # module-level names bound to JAX/flax modules
        self.dropped: list[str] = []

    def _flat(self, module: str) -> str:
        if module not in self.names:
            raise ValueError(f"{self.source} imports {module}, which the bundle does not contain "
                             f"(bundled: {sorted(self.names)})")
        return self.names[module]

    def visit_Import(self, node):
        kept = []
        for alias in node.names:
            if _is_jax_module(alias.name):
                continue
            if alias.name.split(".")[0] == PACKAGE:
                raise ValueError(f"{self.source}: use 'from {PACKAGE} import x', not 'import {alias.name}'")
            kept.append(alias)
        if not kept:
            return None
        node.names = kept
        return node

    def visit_ImportFrom(self, node):
        if _is_jax_module(node.module):
            return None
        if node.module == PACKAGE:       # from marbler_jax import physics, cbf -> import physics, cbf
            aliases = []
            for a in node.names:
                flat = self._flat(f"{PACKAGE}.{a.name}")
                aliases.append(ast.alias(name=flat, asname=a.asname or (a.name if flat != a.name else None)))
            return ast.Import(names=aliases)
        if node.module and node.module.split(".")[0] == PACKAGE:
            gone = self.dropped_elsewhere.get(node.module, ())
            node.names = [a for a in node.names if a.name not in gone]
            node.module = self._flat(node.module)
            if not node.names:
                return None
        return node

    def _function(self, node):
        jax_names = self.jax_names | _jax_imports(ast.walk(node))
        if any(_uses(stmt, jax_names) for stmt in node.body + node.decorator_list):
            self.dropped.append(node.name)
            return None
        self._annotations(node)
        return self.generic_visit(node)

    visit_FunctionDef = _function
    visit_AsyncFunctionDef = _function

    def _annotations(self, node):
        args = node.args
        for arg in args.posonlyargs + args.args + args.kwonlyargs + [args.vararg, args.kwarg]:
            if arg is not None and arg.annotation is not None and _uses(arg.annotation, self.jax_names):
                arg.annotation = ast.Constant(ast.unparse(arg.annotation))
        if node.returns is not None and _uses(node.returns, self.jax_names):
            node.returns = ast.Constant(ast.unparse(node.returns))

    def visit_AnnAssign(self, node):
        if _uses(node.annotation, self.jax_names):
            node.annotation = ast.Constant(ast.unparse(node.annotation))
        return node

    def visit_JoinedStr(self, node):
        args = []
        template = self._format_template(node, args)
        return ast.Call(func=ast.Attribute(value=ast.Constant(template), attr="format", ctx=ast.Load()),
                        args=args, keywords=[])

    def _format_template(self, node, args: list) -> str:
        """``str.format`` template of the f-string ``node``; its expressions are appended to ``args`` in
        the order ``str.format`` numbers the fields (a field before the fields nested in its format spec)."""
        parts = []
        for value in node.values:
            if isinstance(value, ast.Constant):
                parts.append(value.value.replace("{", "{{").replace("}", "}}"))
                continue
            args.append(self.visit(value.value))
            conversion = "" if value.conversion == -1 else "!" + chr(value.conversion)
            spec = "" if value.format_spec is None else ":" + self._format_template(value.format_spec, args)
            parts.append("{" + conversion + spec + "}")
        return "".join(parts)

    def visit_ClassDef(self, node):
        decorators = []
        for d in node.decorator_list:
            if ast.unparse(d) == "struct.dataclass":
                decorators.append(ast.Name(id="frozen_state", ctx=ast.Load()))
                self.needs_frozen_state = True
            else:
                decorators.append(d)
        node.decorator_list = decorators
        return self.generic_visit(node)


def flatten_modules(names: dict[str, str]) -> dict[str, str]:
    """Flat, JAX-free sources ``{flat name: source}`` of the modules ``names`` maps to flat names.

    A module that imports names from another bundled module is flattened after it, so that the
    JAX-only functions the other module lost are dropped from its imports too (one pass per module;
    two passes where the imports form a cycle)."""
    trees = {module: _parse(module) for module in names}
    order = _imported_first(trees)
    if order is None:
        dropped = {module: flatten_module(module, names, tree=trees[module])[1] for module in names}
        return {names[module]: flatten_module(module, names, dropped)[0] for module in names}
    sources, dropped = {}, {}
    for module in order:
        sources[module], dropped[module] = flatten_module(module, names, dropped, tree=trees[module])
    return {names[module]: sources[module] for module in names}


def _parse(module: str) -> ast.Module:
    path = module_path(module)
    return ast.parse(path.read_text(), filename=str(path))


def _imported_first(trees: dict[str, ast.Module]) -> list[str] | None:
    """The modules of ``trees`` ordered so that each comes after the bundled modules it imports names
    from (``from marbler_jax.x import f``); ``None`` if those imports form a cycle."""
    needs = {module: {node.module for node in ast.walk(tree)
                      if isinstance(node, ast.ImportFrom) and node.module in trees and node.module != module}
             for module, tree in trees.items()}
    order, state = [], {}

    def visit(module) -> bool:
        if state.get(module) == "done":
            return True
        if state.get(module) == "open":
            return False
        state[module] = "open"
        if not all(visit(other) for other in sorted(needs[module])):
            return False
        state[module] = "done"
        order.append(module)
        return True

    return order if all(visit(module) for module in trees) else None


def flatten_module(module: str, names: dict[str, str], dropped_elsewhere: dict | None = None,
                   tree: ast.Module | None = None) -> tuple[str, list[str]]:
    """Flat, JAX-free source of module ``module``; ``names`` maps bundled modules to their flat names,
    ``dropped_elsewhere`` their dropped functions (not importable); ``tree``: the module's parsed
    source (rewritten in place), parsed here if ``None``. Returns ``(source, dropped names)``."""
    path = module_path(module)
    tree = _parse(module) if tree is None else tree
    flattener = _Flattener(names, f"{module} ({path.name})", _jax_imports(tree.body), dropped_elsewhere or {})
    flattener.needs_frozen_state = False
    tree = flattener.visit(tree)
    unexpected = sorted(set(flattener.dropped) - JAX_ONLY)
    if unexpected:
        raise ValueError(f"{module}: {unexpected} use JAX, so the numpy bundle cannot run them; write them "
                         f"against the array namespace (marbler_jax.xp.namespace). Only {sorted(JAX_ONLY)} may be "
                         "JAX-only.")
    if flattener.needs_frozen_state:
        position = 0
        for position, stmt in enumerate(tree.body):
            if not (isinstance(stmt, ast.Expr) and isinstance(stmt.value, ast.Constant)) and not (
                    isinstance(stmt, ast.ImportFrom) and stmt.module == "__future__"):
                break
        tree.body.insert(position, ast.ImportFrom(module=names[f"{PACKAGE}.xp"],
                                                  names=[ast.alias(name="frozen_state")], level=0))
    ast.fix_missing_locations(tree)
    relative = path.relative_to(PACKAGE_DIR.parent).as_posix() if path.is_relative_to(PACKAGE_DIR.parent) else path.name
    header = (f"# Generated from {relative} by `marbler-jax export --bundle`: the package code with flat "
              "imports and without JAX. Do not edit; re-export instead.\n")
    source = header + ast.unparse(tree) + "\n"
    check_flat_source(source, f"{names[module]}.py")
    return source, flattener.dropped


def check_flat_source(source: str, name: str) -> None:
    """Raise ``ValueError`` if ``source`` imports JAX, flax or the ``marbler_jax`` package."""
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            modules = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            modules = [node.module or ""]
        else:
            continue
        for m in modules:
            if _is_jax_module(m) or m.split(".")[0] == PACKAGE:
                raise ValueError(f"{name} imports {m}")


def check_bundle_folder(folder) -> list[str]:
    """Raise ``ValueError`` unless ``folder`` is flat, has only allowed extensions and no JAX import;
    returns the file names."""
    folder = Path(folder)
    names = []
    for entry in sorted(folder.iterdir()):
        if entry.is_dir():
            raise ValueError(f"bundle must be flat, found folder {entry.name}/")
        if entry.suffix.lower() not in ALLOWED_EXTENSIONS:
            raise ValueError(f"{entry.name}: extension {entry.suffix!r} is not accepted by the Robotarium "
                             f"(allowed: {sorted(ALLOWED_EXTENSIONS)})")
        if entry.suffix == ".py":
            check_flat_source(entry.read_text(), entry.name)
        names.append(entry.name)
    if "main.py" not in names:
        raise ValueError("bundle has no main.py")
    return names


__all__ = ["CORE_MODULES", "ALLOWED_EXTENSIONS", "JAX_ONLY", "flatten_module", "flatten_modules", "check_flat_source",
           "check_bundle_folder", "module_path"]
