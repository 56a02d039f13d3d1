"""Imports point one way (DESIGN.md): every import of ours, module level or inside a function, is checked.

storage <- uncertainty <- orchestrator; workers import storage and only the wire contract of
orchestrator (protocol, messages, transport, and endpoints: the flags that name them; acl: who may send what in a
secure profile) and how a process is asked to stop (signals), which import nothing of ours outside that set.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("storage", "uncertainty", "workers", "orchestrator")
#: What workers may import of the orchestrator: the wire contract, and how a process is asked to stop.
SHARED = {"orchestrator.protocol", "orchestrator.messages", "orchestrator.transport", "orchestrator.tlscheck",
          "orchestrator.endpoints", "orchestrator.signals", "orchestrator.acl"}

#: For each package (or module), which of our modules it may import, besides its own package.
ALLOWED = {
    "storage": lambda mod: False,
    "uncertainty": lambda mod: mod.startswith("storage"),
    "workers": lambda mod: mod.startswith("storage") or mod in SHARED,
    "orchestrator": lambda mod: mod.split(".")[0] in ("storage", "uncertainty", "workers"),
}
#: Leaves: the modules they may import of ours (nothing else, not even their own package).
LEAVES = {
    "orchestrator.protocol": set(),
    "orchestrator.messages": {"orchestrator.protocol"},
    "orchestrator.transport": {"orchestrator.tlscheck", "orchestrator.linkprobe", "orchestrator.locators"},
    # (tlscheck: when a config names TLS files; linkprobe: when a session cannot reach its router)
    "orchestrator.linkprobe": {"orchestrator.locators"},
    "orchestrator.locators": set(),
    "orchestrator.tlscheck": {"orchestrator.transport"},
    "orchestrator.endpoints": {"orchestrator.transport", "orchestrator.locators"},
    "orchestrator.signals": set(),
    "orchestrator.acl": {"orchestrator.protocol", "orchestrator.transport"},
    "uncertainty.model": {"uncertainty.errors"},
}


def _modules() -> list[tuple[str, Path]]:
    out = []
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            rel = path.relative_to(ROOT).with_suffix("")
            out.append((".".join(p for p in rel.parts if p != "__init__"), path))
    return out


def _our_imports(path: Path) -> set[str]:
    """Every module of ours ``path`` imports, wherever the import statement is."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            # "from orchestrator import protocol" imports the submodule orchestrator.protocol.
            names = [f"{node.module}.{a.name}" if node.module in PACKAGES or node.module == "orchestrator.cli"
                     else node.module for a in node.names]
        else:
            continue
        found.update(n for n in names if n.split(".")[0] in PACKAGES)
    return found


@pytest.mark.parametrize("module,path", _modules(), ids=[m for m, _ in _modules()])
def test_imports_point_one_way(module: str, path: Path) -> None:
    package = module.split(".")[0]
    imports = _our_imports(path)
    if module in LEAVES:
        bad = imports - LEAVES[module]
    else:
        bad = {m for m in imports if m.split(".")[0] != package and not ALLOWED[package](m)}
    assert not bad, f"{module} imports {sorted(bad)}, against the layering of DESIGN.md"


def test_the_check_sees_an_upward_import(tmp_path: Path) -> None:
    """The checker itself: an import inside a function is found."""
    path = tmp_path / "m.py"
    path.write_text("def f():\n    from orchestrator import service\n    import uncertainty.train\n")
    assert _our_imports(path) == {"orchestrator.service", "uncertainty.train"}
