"""Imports at the top of each module: a function-level import is a deferral, and only these are allowed.

`crater-synth --help` imports no command module (crater_synth/cli.py is a lazy group), so a module pays for
its imports only when one of its commands runs: it imports what it needs at its top, where a reader sees
its dependencies. What stays inside functions is what is heavy to load or only importable in some places,
each with its reason below. The walk reads the source (AST): nothing is imported.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("crater_core", "data_manifest", "blender_gen", "train", "crater_synth")

# Libraries imported where they are used, and why.
DEFERRED_LIBRARIES = {
    "torch": "seconds to load: only training, evaluation and the learned detector need it",
    "bpy": "Blender: importable only inside Blender or with the pip bpy module, and slow to load",
    "mathutils": "Blender's maths module, shipped with bpy",
    "scipy": "slow to load; most commands use it in one function",
    "torchvision": "imported by train.tv_ops.import_torchvision only, which first stands in for its NMS where "
    "its compiled ops do not load (a torch build they do not match)",
    "matplotlib": "slow to load; only the figure writers need it",
    "distributed": "Dask: only `launcher=dask` uses it, and a render-only install has none (docs/install.md)",
}
# Project modules that import a deferred library at their top (directly or through their own top-level
# imports): importing one counts as deferring that library. The test checks each still does.
DEFERRING_MODULES = {
    "crater_synth.dataset.dask_launcher": "distributed",
    "crater_synth.bench.distributed": "distributed",
    "crater_synth.bench.detector_layout": "torch",
    "crater_synth.dataset.detection_dask": "distributed",
    "train.crater_detector": "torch",
    "train.crater_detector_inference": "torch",
    "train.crater_verifier": "torch",
    "train.detector_fit": "torch",
    "train.data": "torch",
    "train.evaluate": "torch",
    "train.fcos_detector": "torch",
    "train.model_files": "torch",
    "train.models": "torch",
    "train.prefetch": "torch",
    "train.trainer": "torch",
    "train.tv_ops": "torch",
    "train.preprocess": "scipy",
    "train.realset": "scipy",
    "blender_gen.camera": "bpy",
    "blender_gen.material": "bpy",
    "blender_gen.mesh": "bpy",
    "blender_gen.render": "bpy",
    "blender_gen.scene": "bpy",
    "blender_gen.session": "bpy",
    "blender_gen.sun": "bpy",
}
# Files whose function-level imports are not checked, and why.
EXEMPT_FILES = {
    "blender_gen/worker.py": (
        "runs in Blender's own Python: it checks that numpy and OpenImageIO exist (one ERROR line when not) "
        "and pins the BLAS to one thread before numpy loads (its module docstring)"
    ),
}
# Single deferred imports of one module, and why.
EXEMPT_IMPORTS = {
    ("crater_core/exr.py", "OpenImageIO"): "importing crater_core needs only numpy and the standard library "
    "(its module docstring): the EXR libraries load on the first read or write",
    ("crater_core/exr.py", "OpenEXR"): "the encoder, where installed (a Blender binary's Python may lack it): "
    "loaded on the first write, as OpenImageIO",
    ("crater_core/progress.py", "tqdm"): "the terminal bar, imported only when the stream is a TTY",
}


def module_name(path: Path, root: Path = ROOT) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def project_files() -> dict[str, Path]:
    return {module_name(p): p for pkg in PACKAGES for p in sorted((ROOT / pkg).rglob("*.py"))}


def imported(module: str, node: ast.Import | ast.ImportFrom, is_pkg: bool, known) -> list[str]:
    """The modules an import statement names (``from pkg import mod`` -> ``pkg.mod``; relative resolved)."""
    if isinstance(node, ast.Import):
        return [a.name for a in node.names]
    if node.level:
        base = module.split(".")
        base = base[: len(base) - node.level + (1 if is_pkg else 0)]
        target = ".".join(base + ([node.module] if node.module else []))
    else:
        target = node.module or ""
    return [f"{target}.{a.name}" if f"{target}.{a.name}" in known else target for a in node.names]


def function_level_imports(path: Path):
    """(line, import node) of every import inside a function (nested blocks included)."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    out = []

    def walk(node, in_function: bool):
        for child in ast.iter_child_nodes(node):
            inside = in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda))
            if in_function and isinstance(child, (ast.Import, ast.ImportFrom)):
                out.append(child)
            walk(child, inside)

    walk(tree, False)
    return out


def top_level_imports(module: str, path: Path, known) -> list[str]:
    """What importing the module imports (everything outside its functions)."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    out = []

    def walk(node):
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
                continue
            if isinstance(child, (ast.Import, ast.ImportFrom)):
                out.extend(imported(module, child, path.name == "__init__.py", known))
            walk(child)

    walk(tree)
    return out


def _project(name: str, known) -> str | None:
    while name not in known and "." in name:
        name = name.rsplit(".", 1)[0]
    return name if name in known else None


def _exempt_file(rel: str) -> bool:
    return any(rel == f or (f.endswith("/") and rel.startswith(f)) for f in EXEMPT_FILES)


def violations(files: dict[str, Path], root: Path = ROOT) -> list[str]:
    known = set(files)
    bad = []
    for module, path in files.items():
        rel = path.relative_to(root).as_posix()
        if _exempt_file(rel):
            continue
        for node in function_level_imports(path):
            for name in imported(module, node, path.name == "__init__.py", known):
                top = name.split(".")[0]
                if top in DEFERRED_LIBRARIES or (rel, top) in EXEMPT_IMPORTS:
                    continue
                if _project(name, known) in DEFERRING_MODULES:
                    continue
                bad.append(f"{rel}:{node.lineno}: import of {name} inside a function: move it to the top")
    return bad


def test_imports_are_at_the_top():
    bad = violations(project_files())
    assert not bad, "\n".join(bad)


def test_the_walker_catches_a_function_level_import(tmp_path):
    pkg = tmp_path / "crater_synth"
    pkg.mkdir()
    (pkg / "mod.py").write_text(
        "import json\n\ndef f():\n    if json:\n        import yaml\n    import torch\n    from . import other\n"
    )
    (pkg / "other.py").write_text("")
    files = {module_name(p, tmp_path): p for p in sorted(pkg.rglob("*.py"))}
    assert violations(files, tmp_path) == [
        "crater_synth/mod.py:5: import of yaml inside a function: move it to the top",
        "crater_synth/mod.py:7: import of crater_synth.other inside a function: move it to the top",
    ]


@pytest.mark.parametrize("module", sorted(DEFERRING_MODULES))
def test_each_deferring_module_still_imports_its_library_at_its_top(module):
    files = project_files()
    known = set(files)
    seen, todo = set(), [module]
    while todo:
        m = todo.pop()
        if m in seen:
            continue
        seen.add(m)
        for name in top_level_imports(m, files[m], known):
            if name.split(".")[0] == DEFERRING_MODULES[module]:
                return
            sub = _project(name, known)
            if sub is not None:
                todo.append(sub)
    pytest.fail(f"{module} no longer imports {DEFERRING_MODULES[module]} at its top: drop it from DEFERRING_MODULES")


def test_every_exemption_is_still_needed():
    files = project_files()
    known = set(files)
    used_files, used_imports = set(), set()
    for module, path in files.items():
        rel = path.relative_to(ROOT).as_posix()
        nodes = function_level_imports(path)
        for f in EXEMPT_FILES:
            if nodes and (rel == f or (f.endswith("/") and rel.startswith(f))):
                used_files.add(f)
        for node in nodes:
            for name in imported(module, node, path.name == "__init__.py", known):
                if (rel, name.split(".")[0]) in EXEMPT_IMPORTS:
                    used_imports.add((rel, name.split(".")[0]))
    assert set(EXEMPT_FILES) == used_files, f"stale: {set(EXEMPT_FILES) - used_files}"
    assert set(EXEMPT_IMPORTS) == used_imports, f"stale: {set(EXEMPT_IMPORTS) - used_imports}"
