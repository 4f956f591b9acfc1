"""Imports point down only (docs/architecture.md), read from the source: every ``import`` in
``sdh2svc/``, at a module's top, in a function or under ``TYPE_CHECKING`` — the import tests
that load a layer and look at ``sys.modules`` (tests/control/test_layering.py,
tests/sim/test_layers.py) see none that sits in a function until the function runs."""

from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "sdh2svc"
LAYERED = ("model", "protocol", "bus", "sim", "control", "service", "campaign")
# A part (a package, or a top-level module) → the parts it may import besides itself.
# "" is the package's own __init__ (its version): any part may import it.
ABOVE_THE_SEAM = {"model", "protocol", "bus", "sim", "control", "config", "connect", "files",
                  "workers", "provenance", "hosts", "heap"}  # fmt: skip
BELOW = {
    "protocol": set(),
    "model": {"protocol"},  # model/hand.py: the wire's axis count, written once (NUM_AXES)
    "bus": {"model", "protocol"},
    "sim": {"model", "protocol"},
    "control": {"model", "protocol", "bus"},
    "config": {"model", "protocol", "control", "sim", "hosts"},  # the composition root
    "connect": {"model", "protocol", "bus", "sim", "control", "config"},
    "service": ABOVE_THE_SEAM,
    "campaign": ABOVE_THE_SEAM,  # the service's sibling: not the service
    "client": {"files", "hosts"},  # the service from Python: imports nothing of the service
    "files": set(),
    "hosts": set(),
    "workers": set(),
    "provenance": set(),
    "heap": set(),
}
# Imports that break the order on purpose, each inside a function: (importer, imported).
EXCEPTIONS = {
    # `python -m sdh2svc.model.urdf`: an entry point composes the configuration it prints
    ("sdh2svc.model.urdf", "sdh2svc.config"),
    ("sdh2svc.model.urdf", "sdh2svc.files"),
    # a campaign's case is one headless run, as `sdh2svc run` makes it
    ("sdh2svc.campaign.run", "sdh2svc.service.headless"),
}


def _module(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _part(module: str) -> str:
    names = module.split(".")[1:]
    if not names:
        return ""
    return names[0]


def _imports(tree: ast.Module, module: str) -> Iterator[tuple[str, int]]:
    """Every sdh2svc module ``tree`` imports (``from sdh2svc import x``: ``sdh2svc.x`` when x
    is a module), with its line."""
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name, node.lineno
        elif isinstance(node, ast.ImportFrom):
            assert node.level == 0, f"{module}:{node.lineno}: a relative import"
            base = node.module or ""
            for alias in node.names:
                sub = PACKAGE.parent / f"{base}.{alias.name}".replace(".", "/")
                sub_mod = sub.with_suffix(".py").exists() or sub.is_dir()
                yield (f"{base}.{alias.name}" if sub_mod else base), node.lineno


def _edges() -> list[tuple[str, str, int]]:
    out = []
    for path in sorted(PACKAGE.rglob("*.py")):
        module = _module(path)
        for target, line in _imports(ast.parse(path.read_text(encoding="utf-8")), module):
            if target == "sdh2svc" or target.startswith("sdh2svc."):
                out.append((module, target, line))
    return out


def test_every_import_points_down() -> None:
    wrong = []
    for module, target, line in _edges():
        src, dst = _part(module), _part(target)
        if src not in BELOW or dst in ("", src) or (module, target) in EXCEPTIONS:
            continue  # the commands (cli, entry, __main__) may import anything
        if dst not in BELOW[src]:
            wrong.append(f"{module}:{line} imports {target} ({src} → {dst})")
    assert not wrong, "\n".join(wrong)


def test_the_exceptions_are_still_there() -> None:
    """An exception no longer needed is struck off, so that it cannot come back unseen."""
    edges = {(m, t) for m, t, _ in _edges()}
    assert EXCEPTIONS <= edges, sorted(EXCEPTIONS - edges)


def test_the_parts_are_all_named() -> None:
    parts = {_part(_module(p)) for p in PACKAGE.rglob("*.py")}
    commands = {"", "cli", "entry", "__main__"}
    assert parts - commands - set(BELOW) == set(), "a new part: say what it may import"
    assert set(LAYERED) <= set(BELOW)
