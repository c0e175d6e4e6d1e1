"""The package's imports against the dependencies it declares.

``make run`` installs the package with its ``io`` extra only (``make test`` adds the ``test``
extra), so a module of ``src/redman_jax`` that imported a test reference, or a package that is
only installed because another dependency needs it, would work in the tests and fail, or break
with that dependency's next release, in a user's study.
"""

from __future__ import annotations

import ast
import importlib.metadata as md
import re
import sys
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src" / "redman_jax"


def _imports(tree: ast.AST):
    """``(top-level module, guarded)`` for every absolute import; guarded: inside the body of a
    ``try`` whose handlers catch ``ImportError`` (or a base of it), i.e. an optional import."""
    out = []

    def catches_import_error(handler: ast.ExceptHandler) -> bool:
        names = handler.type
        if names is None:
            return True
        elts = names.elts if isinstance(names, ast.Tuple) else [names]
        return any(isinstance(e, ast.Name) and e.id in ("ImportError", "ModuleNotFoundError", "Exception")
                   for e in elts)

    def visit(node, guarded):
        if isinstance(node, ast.Try):
            inner = guarded or any(catches_import_error(h) for h in node.handlers)
            for child in node.body:
                visit(child, inner)
            for child in node.handlers + node.orelse + node.finalbody:
                visit(child, guarded)
            return
        if isinstance(node, ast.Import):
            out.extend((a.name.split(".")[0], guarded) for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            out.append((node.module.split(".")[0], guarded))
        for child in ast.iter_child_nodes(node):
            visit(child, guarded)

    visit(tree, False)
    return out


def _norm(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def _requirements():
    """``(core, extras)``: the distributions the installed package requires, always and by extra."""
    core, extras = set(), set()
    for req in md.requires("redman-jax") or ():
        name = _norm(re.match(r"[A-Za-z0-9_.\-]+", req).group(0))
        (extras if "extra ==" in req else core).add(name)
    return core, extras


def test_every_import_of_the_package_is_a_declared_dependency():
    core, extras = _requirements()
    assert {"jax", "diffrax", "equinox", "optax", "numpy", "matplotlib"} <= core
    dists = md.packages_distributions()
    stdlib = set(sys.stdlib_module_names)
    problems = []
    for path in sorted(SRC.glob("*.py")):
        for module, guarded in _imports(ast.parse(path.read_text())):
            if module in stdlib or module == "redman_jax" or module == "__future__":
                continue
            # what installs the module; a module no distribution provides here (an optional one
            # that is not installed, or a data-only wheel: example-robot-data 6) by its own name
            provided = {_norm(d) for d in dists.get(module, ())} or {_norm(module)}
            if provided & core:
                continue
            if guarded and provided & extras:  # optional, with a fallback or a clear error
                continue
            problems.append(f"{path.name}: import {module} (from {sorted(provided)}), which "
                            f"{'no extra names' if guarded else 'the dependencies do not name'}")
    assert not problems, "\n".join(problems)


def test_the_import_scan_sees_guarded_and_unguarded_imports():
    """The scan itself: what the test above relies on, on a module written for it."""
    src = ("import os\nimport numpy as np\nfrom jax import numpy\nfrom . import _sim\n"
           "try:\n    import pandas\nexcept ImportError:\n    pandas = None\n"
           "def f():\n    import osqp\n    try:\n        import example_robot_data\n    except Exception:\n        pass\n")
    assert _imports(ast.parse(src)) == [("os", False), ("numpy", False), ("jax", False), ("pandas", True),
                                        ("osqp", False), ("example_robot_data", True)]
