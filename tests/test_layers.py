"""The layering you can draw: imports point down only, and no module imports itself back.

    crater_core  <  data_manifest  <  {blender_gen, train}  <  crater_synth

and inside ``crater_synth``, by what each part does:

    common (errors, config, cli_common, fetch)  <  terrain  <  dataset  <  {evaluation, navigation}
        <  {report, bench}  <  {tools, cli}

Every ``import`` of every module is read from the source (AST, so imports inside functions count too,
and nothing is executed). The test fails on
- an import cycle between modules (a strongly connected component of the module graph);
- an upward or sideways arrow between packages (``blender_gen`` and ``train`` never import each other),
  or between the parts of ``crater_synth`` (:data:`SUBRANK`);
- a third-party import a package must not make: the core is numpy + stdlib (OpenImageIO and OpenEXR only in
  ``crater_core.exr``), ``blender_gen`` runs inside Blender (bpy, mathutils, numpy; OpenImageIO only
  through ``crater_core.exr``), ``train`` never imports bpy or the CLI/config stack.
"""

from __future__ import annotations

import ast
import sys
from collections import defaultdict
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
# Lower rank = lower layer. An import between two packages must go to a strictly lower rank.
RANK = {"crater_core": 0, "data_manifest": 1, "blender_gen": 2, "train": 2, "crater_synth": 3}

# Inside crater_synth: the rank of each part (a subpackage, or a top-level module). An import from one part
# into another must go to a strictly lower rank; imports inside a part are free (its cycles are still caught).
# The top-level modules every command shares form one part, "common".
COMMON = {
    "crater_synth",
    "crater_synth.errors",
    "crater_synth.paths",
    "crater_synth.config",
    "crater_synth.cli_common",
    "crater_synth.fetch",
    "crater_synth.outfolder",
}
SUBRANK = {
    "common": 0,
    "crater_synth.terrain": 1,
    "crater_synth.dataset": 2,
    "crater_synth.data": 2,  # the public Dataset API over exports (re-exports train.exported)
    "crater_synth.evaluation": 3,
    "crater_synth.navigation": 3,
    "crater_synth.report": 4,
    "crater_synth.bench": 4,
    "crater_synth.tools": 5,
    "crater_synth.cli": 5,
    "crater_synth.config_cli": 5,
}

# Third-party top-level modules a package may import (the standard library is always allowed).
ALLOWED_THIRD_PARTY = {
    "crater_core": {"numpy"},
    "blender_gen": {"bpy", "mathutils", "numpy"},
}
# Single modules with a wider allowance than their package, and why.
MODULE_ALLOWANCE = {
    "crater_core.exr": {"OpenImageIO", "OpenEXR"},  # the project's one EXR reader/writer
    "crater_core.progress": {"tqdm"},  # the terminal bar, imported only when the stream is a TTY
}
FORBIDDEN_THIRD_PARTY = {
    "data_manifest": {"bpy", "mathutils", "torch", "click", "omegaconf", "hydra"},
    "train": {"bpy", "mathutils", "click", "omegaconf", "hydra"},
}

# Cycles another branch is known to remove. Each entry must still be a real cycle: once the fix lands this
# test fails and asks for the entry to be deleted. None pending (the dataset/launcher cycle is gone: the
# launcher owns the dataset command).
PENDING_CYCLES: set[frozenset[str]] = set()


def project_modules() -> dict[str, Path]:
    mods = {}
    for pkg in RANK:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            parts = list(path.relative_to(ROOT).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            mods[".".join(parts)] = path
    return mods


def _imports(module: str, path: Path, known: set[str]) -> list[tuple[str, int]]:
    """(imported name, line) for every import in the file; project names resolved to the deepest
    project module they name (``from pkg import mod`` -> ``pkg.mod``)."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    is_pkg = path.name == "__init__.py"
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(alias.name, node.lineno) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = module.split(".")
                base = base[: len(base) - node.level + (1 if is_pkg else 0)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            for alias in node.names:
                sub = f"{target}.{alias.name}"
                out.append((sub if sub in known else target, node.lineno))
    resolved = []
    for name, line in out:
        # ``import a.b.c`` where only ``a.b`` is a project module: depend on ``a.b``.
        while name not in known and "." in name and name.split(".")[0] in RANK:
            name = name.rsplit(".", 1)[0]
        if (name, line) not in resolved:
            resolved.append((name, line))
    return resolved


@pytest.fixture(scope="module")
def graph() -> dict[str, list[tuple[str, int]]]:
    mods = project_modules()
    known = set(mods)
    return {m: _imports(m, p, known) for m, p in mods.items()}


def _package(module: str) -> str:
    return module.split(".")[0]


def test_walker_sees_function_level_and_relative_imports(tmp_path):
    src = tmp_path / "mod.py"
    src.write_text("import os\n\ndef f():\n    from crater_core import geometry\n    from . import sibling\n")
    known = {"crater_core", "crater_core.geometry", "pkg", "pkg.sibling"}
    got = {name for name, _ in _imports("pkg.mod", src, known)}
    assert got == {"os", "crater_core.geometry", "pkg.sibling"}


def test_no_upward_or_sideways_imports_between_packages(graph):
    bad = []
    for mod, imports in graph.items():
        src = _package(mod)
        for name, line in imports:
            dst = _package(name)
            if dst in RANK and dst != src and not RANK[dst] < RANK[src]:
                bad.append(
                    f"{mod} (line {line}) imports {name}: {src} may only import "
                    f"{sorted(p for p in RANK if RANK[p] < RANK[src]) or 'nothing of the project'}"
                )
    assert not bad, "imports against the layering:\n" + "\n".join(bad)


def crater_synth_part(module: str) -> str | None:
    """The :data:`SUBRANK` part a crater_synth module belongs to (None: outside crater_synth)."""
    parts = module.split(".")
    if parts[0] != "crater_synth":
        return None
    part = ".".join(parts[:2])
    return "common" if part in COMMON else part


def test_every_crater_synth_module_has_a_rank(graph):
    missing = sorted({crater_synth_part(m) for m in graph if crater_synth_part(m) not in (None, *SUBRANK)})
    assert not missing, f"give these parts of crater_synth a rank in SUBRANK ({__file__}): {missing}"


def test_no_upward_or_sideways_imports_inside_crater_synth(graph):
    bad = []
    for mod, imports in graph.items():
        src = crater_synth_part(mod)
        if src is None:
            continue
        for name, line in imports:
            dst = crater_synth_part(name)
            if dst is None or dst == src or dst not in SUBRANK or src not in SUBRANK:
                continue
            if not SUBRANK[dst] < SUBRANK[src]:
                lower = sorted(p for p in SUBRANK if SUBRANK[p] < SUBRANK[src])
                bad.append(f"{mod} (line {line}) imports {name}: {src} may only import {lower}")
    assert not bad, "imports against crater_synth's sub-ranks:\n" + "\n".join(bad)


def test_subrank_check_catches_an_upward_arrow():
    fake = {"crater_synth.terrain.patch": [("crater_synth.evaluation.validation", 3)]}
    src, dst = crater_synth_part("crater_synth.terrain.patch"), crater_synth_part("crater_synth.evaluation.validation")
    assert (src, dst) == ("crater_synth.terrain", "crater_synth.evaluation")
    assert not SUBRANK[dst] < SUBRANK[src], fake


def test_third_party_imports_fit_each_layer(graph):
    bad = []
    stdlib = set(sys.stdlib_module_names) | {"__future__"}
    for mod, imports in graph.items():
        pkg = _package(mod)
        for name, line in imports:
            top = name.split(".")[0]
            if top in RANK or top in stdlib:
                continue
            if pkg in ALLOWED_THIRD_PARTY:
                allowed = ALLOWED_THIRD_PARTY[pkg] | MODULE_ALLOWANCE.get(mod, set())
                if top not in allowed:
                    bad.append(f"{mod} (line {line}) imports {top}: {pkg} allows only the stdlib and {sorted(allowed)}")
            elif top in FORBIDDEN_THIRD_PARTY.get(pkg, ()):
                bad.append(f"{mod} (line {line}) imports {top}, which {pkg} must never import")
    assert not bad, "third-party imports against the layering:\n" + "\n".join(bad)


def strongly_connected(edges: dict[str, set[str]]) -> list[set[str]]:
    """Tarjan's algorithm (iterative): components of more than one module, or a module importing itself."""
    index, low, on_stack, stack, out, counter = {}, {}, set(), [], [], [0]
    for root in edges:
        if root in index:
            continue
        work = [(root, iter(edges[root]))]
        index[root] = low[root] = counter[0]
        counter[0] += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            node, it = work[-1]
            for nxt in it:
                if nxt not in index:
                    index[nxt] = low[nxt] = counter[0]
                    counter[0] += 1
                    stack.append(nxt)
                    on_stack.add(nxt)
                    work.append((nxt, iter(edges[nxt])))
                    break
                if nxt in on_stack:
                    low[node] = min(low[node], index[nxt])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[node])
                if low[node] == index[node]:
                    comp = set()
                    while True:
                        n = stack.pop()
                        on_stack.discard(n)
                        comp.add(n)
                        if n == node:
                            break
                    if len(comp) > 1 or node in edges[node]:
                        out.append(comp)
    return out


def test_cycle_finder_finds_cycles():
    edges = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"d"}, "e": {"a"}}
    assert sorted(map(sorted, strongly_connected(edges))) == [["a", "b", "c"], ["d"]]
    assert strongly_connected({"a": {"b"}, "b": set()}) == []


def test_no_import_cycles(graph):
    edges: dict[str, set[str]] = defaultdict(set)
    for mod, imports in graph.items():
        edges[mod] |= {name for name, _ in imports if name in graph}
    for mod in graph:
        edges.setdefault(mod, set())
    cycles = strongly_connected(dict(edges))
    stale = [sorted(c) for c in PENDING_CYCLES if not any(c <= comp for comp in cycles)]
    assert not stale, f"these cycles are gone: delete them from PENDING_CYCLES in {__file__}: {stale}"
    real = [c for c in cycles if frozenset(c) not in PENDING_CYCLES]

    def describe(comp: set[str]) -> str:
        arrows = [f"{m} -> {n} (line {line})" for m in sorted(comp) for n, line in graph[m] if n in comp]
        return "; ".join(arrows)

    assert not real, "import cycles:\n" + "\n".join(describe(c) for c in real)


# Modules whose whole import closure (every project module they can reach, function-level imports included)
# must stay free of a heavy dependency, and why.
LIGHT_CLOSURES = {
    "crater_synth.report": ("torch", "the report summarises a run without loading the training stack"),
    "train.registry": ("torch", "the model list is read by the report and the CLI"),
}


def _closure(graph, start: str) -> set[str]:
    seen, todo = set(), [m for m in graph if m == start or m.startswith(start + ".")]
    while todo:
        mod = todo.pop()
        if mod in seen:
            continue
        seen.add(mod)
        todo += [name for name, _ in graph[mod] if name in graph]
    return seen


def test_light_modules_never_reach_heavy_dependencies(graph):
    bad = []
    for start, (heavy, why) in LIGHT_CLOSURES.items():
        for mod in sorted(_closure(graph, start)):
            hits = [line for name, line in graph[mod] if name.split(".")[0] == heavy]
            if hits:
                bad.append(f"{start} reaches {mod}, which imports {heavy} (line {hits[0]}): {why}")
    assert not bad, "\n".join(bad)


MAX_MODULE_LINES = 500
LENGTH_REASON = "Length:"  # a paragraph of the module docstring starting with this says why it is longer


def test_long_modules_say_why():
    """No module over MAX_MODULE_LINES lines without a reason written at its top."""
    bad = []
    for path in project_modules().values():
        text = path.read_text(encoding="utf-8")
        n = text.count("\n") + 1
        if n > MAX_MODULE_LINES and LENGTH_REASON not in (ast.get_docstring(ast.parse(text)) or ""):
            bad.append(
                f"{path.relative_to(ROOT)}: {n} lines; split it, or say why in a '{LENGTH_REASON} ...' "
                "paragraph of its docstring"
            )
    assert not bad, "\n".join(bad)


# Inside navigation: the rank of each part (a subpackage or a shared top-level module). The map and the
# georeference are at the bottom, the detectors and the fix above them, then the modules both evaluations
# share (the protocol, the settings, the outputs); real mosaic windows and rendered frames sit side by side
# and never import each other; only the commands that see both (navigate, the demo) sit on top.
NAV = "crater_synth.navigation"
NAV_RANK = {
    f"{NAV}": 0,
    f"{NAV}.georef": 0,
    f"{NAV}.frame_file": 1,
    f"{NAV}.map": 1,
    f"{NAV}.detectors": 2,
    f"{NAV}.fix": 3,
    f"{NAV}.protocol": 4,
    f"{NAV}.settings": 5,
    f"{NAV}.output": 5,
    f"{NAV}.windows": 6,
    f"{NAV}.rendered": 6,
    f"{NAV}.navigate": 7,
    f"{NAV}.demo": 7,
    f"{NAV}.detect_cmd": 7,
    f"{NAV}.train_cmd": 7,
}
# The longest chain of imports between navigation modules (counted in modules, the first included).
NAV_MAX_CHAIN = 8


def nav_part(module: str) -> str | None:
    """The :data:`NAV_RANK` part a navigation module belongs to (None: outside navigation)."""
    parts = module.split(".")
    if parts[:2] != NAV.split("."):
        return None
    return ".".join(parts[:3])


def test_every_navigation_module_has_a_rank(graph):
    missing = sorted({nav_part(m) for m in graph if nav_part(m) not in (None, *NAV_RANK)})
    assert not missing, f"give these parts of navigation a rank in NAV_RANK ({__file__}): {missing}"


def nav_violations(graph) -> list[str]:
    bad = []
    for mod, imports in graph.items():
        src = nav_part(mod)
        if src is None:
            continue
        for name, line in imports:
            dst = nav_part(name)
            if dst is None or dst == src:
                continue
            if not NAV_RANK[dst] < NAV_RANK[src]:
                lower = sorted(p.removeprefix(NAV + ".") for p in NAV_RANK if NAV_RANK[p] < NAV_RANK[src])
                bad.append(f"{mod} (line {line}) imports {name}: {src} may only import {lower}")
    return bad


def test_navigation_parts_import_down_only(graph):
    bad = nav_violations(graph)
    assert not bad, "imports against navigation's ranks:\n" + "\n".join(bad)


def test_navigation_rank_check_catches_windows_and_rendered_importing_each_other():
    fake = {f"{NAV}.windows.navigate": [(f"{NAV}.rendered.navigate", 7)], f"{NAV}.rendered.navigate": []}
    assert len(nav_violations(fake)) == 1


def longest_chain(graph, prefix: str) -> list[str]:
    """The longest import chain between modules under ``prefix`` (the graph has no cycle there)."""
    edges = {m: [n for n, _ in imports if n.startswith(prefix) and n != m] for m, imports in graph.items()}
    memo: dict[str, list[str]] = {}

    def chain(m: str) -> list[str]:
        if m not in memo:
            memo[m] = [m]
            memo[m] = max(([m, *chain(n)] for n in edges.get(m, ()) if n in edges), key=len, default=[m])
        return memo[m]

    return max((chain(m) for m in edges if m.startswith(prefix)), key=len, default=[])


def test_longest_navigation_import_chain(graph):
    chain = longest_chain(graph, NAV + ".")
    assert len(chain) <= NAV_MAX_CHAIN, f"{len(chain)} modules: " + " -> ".join(chain)


def test_chain_finder_counts_modules():
    fake = {"p.a": [("p.b", 1)], "p.b": [("p.c", 1)], "p.c": [], "q.x": [("p.a", 1)]}
    assert longest_chain(fake, "p.") == ["p.a", "p.b", "p.c"]


def test_no_private_name_is_imported_across_modules(graph):
    """A name with a leading underscore is its module's own: another module that needs it names it public."""
    bad = []
    for path in sorted(p for pkg in RANK for p in (ROOT / pkg).rglob("*.py")) + sorted((ROOT / "tests").rglob("*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and (node.level or (node.module or "").split(".")[0] in RANK):
                bad += [
                    f"{path.relative_to(ROOT)}:{node.lineno} imports {node.module}.{a.name}"
                    for a in node.names
                    if a.name.startswith("_") and not a.name.startswith("__")
                ]
    assert not bad, "private names imported across modules:\n" + "\n".join(bad)


def test_one_function_per_name_in_navigation():
    """Two top-level functions or classes of one name in navigation are two meanings for one word."""
    seen: dict[str, list[str]] = defaultdict(list)
    for path in sorted((ROOT / "crater_synth" / "navigation").rglob("*.py")):
        for node in ast.parse(path.read_text(encoding="utf-8")).body:
            if isinstance(node, (ast.FunctionDef, ast.ClassDef)):
                seen[node.name].append(str(path.relative_to(ROOT)))
    dup = {k: v for k, v in seen.items() if len(v) > 1}
    assert not dup, f"names defined more than once: {dup}"
