"""The package's layout: imports run one way, from the bottom layer up, with no loop.

Every module under src/fwdfit is read with ``ast`` (``import`` and ``from`` forms, relative
and absolute, at the top, inside functions and under ``TYPE_CHECKING``). A module may
import its own folder and any folder of a lower rank; an import of a higher rank, or of
a sibling folder of the same rank, fails, and so does a cycle between modules (counting
the folders' ``__init__.py`` that an import runs first). A folder's ``__init__.py`` (its
public face) may also import the folders inside it. Names taken from the lazy top-level
face (``from fwdfit import simulate``) count as imports of the module that defines them.
Tests, benchmarks, notebooks and scripts import public names only.
"""

from __future__ import annotations

import ast
import json
from pathlib import Path

import fwdfit

# The layers, bottom to top (the same table as src/fwdfit/__init__.py's docstring).
RANKS = {
    "": 0,  # _errors, _version, _interrupt, _progress: the standard library only
    "io": 1,  # tables, time-of-flight readers
    "reference": 1,  # the exact tracer: independent of the model it checks
    "scene": 2,  # values, TOML, registry, limits, materials, spectra
    "model": 3,  # shared kernel and aperture
    "paganin": 3,  # phase retrieval from a scene's layer
    "model.block": 4,  # one folder per geometry
    "model.cylinder": 4,
    "inference": 5,  # free parameters, starts, search, solver, objective, predictor, gate, fitter, sampler
    "outputs": 6,  # a fit's files
    "images": 7,  # TIFF stacks to profiles, image fits and series
    "tof": 8,  # time-of-flight profiles (uses images' radiograph steps)
    "cli": 9,
    "__main__": 10,  # python -m fwdfit: runs the cli
}

ROOT = Path(__file__).resolve().parents[1]
LAYOUT_DATA = Path(__file__).parent / "data" / "layout"  # inputs of the checks' own tests
PACKAGE = ROOT / "src" / "fwdfit"


def _module_name(path: Path, package: Path) -> str:
    parts = path.relative_to(package.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _modules(package: Path) -> dict[str, Path]:
    return {_module_name(path, package): path for path in sorted(package.rglob("*.py"))}


def _lazy_table(package: Path) -> dict[str, str]:
    """The top-level face's table of public names and their modules (PEP 562)."""
    tree = ast.parse((package / "__init__.py").read_text())
    for node in tree.body:
        if isinstance(node, ast.Assign) and any(getattr(t, "id", None) == "_PUBLIC" for t in node.targets):
            return ast.literal_eval(node.value)
    return {}


def _imports(name: str, path: Path, modules: dict[str, Path], lazy: dict[str, str]) -> list[tuple[str, int]]:
    """(module imported, line) for every import in ``path``, resolved to fwdfit's modules."""
    top = name.split(".")[0]
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found += [(alias.name, node.lineno) for alias in node.names if alias.name.split(".")[0] == top]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                source = ".".join(base + ([node.module] if node.module else []))
            else:
                source = node.module or ""
            if source.split(".")[0] != top:
                continue
            for alias in node.names:
                if f"{source}.{alias.name}" in modules:
                    found.append((f"{source}.{alias.name}", node.lineno))
                elif source == top and alias.name in lazy:
                    found.append((f"{top}.{lazy[alias.name]}", node.lineno))
                elif source in modules and alias.name != "*" and alias.name not in _defined(modules[source]):
                    found.append((f"{source}.{alias.name}", node.lineno))  # neither a module nor a name there
                else:
                    found.append((source, node.lineno))
    return found


def _defined(path: Path) -> set[str]:
    """The names a module binds at its top level (also inside top-level if/try blocks)."""
    names, body = set(), list(ast.parse(path.read_text()).body)
    while body:
        node = body.pop()
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names.add(node.name)
        elif isinstance(node, (ast.Import, ast.ImportFrom)):
            names.update((a.asname or a.name).split(".")[0] for a in node.names)
        elif isinstance(node, (ast.Assign, ast.AnnAssign, ast.AugAssign)):
            for target in node.targets if isinstance(node, ast.Assign) else [node.target]:
                names.update(n.id for n in ast.walk(target) if isinstance(n, ast.Name))
        elif isinstance(node, (ast.If, ast.Try, ast.With)):
            for field in ("body", "orelse", "finalbody", "handlers"):
                body.extend(getattr(node, field, []))
        elif isinstance(node, ast.ExceptHandler):
            body.extend(node.body)
    return names


def _rank(module: str) -> tuple[str, int]:
    """(folder key, rank) of a module: the longest folder of RANKS holding it."""
    parts = module.split(".")[1:]
    for n in range(len(parts), -1, -1):
        key = ".".join(parts[:n])
        if key in RANKS:
            return key, RANKS[key]
    raise KeyError(module)


def _folder(module: str, modules: dict[str, Path]) -> str:
    return module if modules[module].name == "__init__.py" else module.rpartition(".")[0]


def layout_problems(package: Path) -> list[str]:
    """Every upward import, sibling import, unresolved import and cycle in ``package``."""
    modules, lazy = _modules(package), _lazy_table(package)
    problems, graph = [], {}
    for name, path in modules.items():
        key, rank = _rank(name)
        edges = set()
        for target, line in _imports(name, path, modules, lazy):
            where = f"{path.relative_to(package.parent)}:{line}"
            if target not in modules:
                problems.append(f"{where}: imports {target}, neither a module of the package nor a name in one")
                continue
            edges.add(target)
            # importing a module first runs the __init__.py of each folder above it
            parts = target.split(".")
            edges.update(parent for parent in (".".join(parts[:n]) for n in range(2, len(parts)))
                         if not name.startswith(parent + ".") and parent != name)
            face_below = path.name == "__init__.py" and target.startswith(name + ".")
            target_key, target_rank = _rank(target)
            if face_below or target_key == key or target == name:
                continue
            if target_rank > rank:
                problems.append(f"{where}: {name} (rank {rank}, {key or 'root'}) imports {target} "
                                f"(rank {target_rank}, {target_key}): upward")
            elif target_rank == rank and target_key.split(".")[0] != key.split(".")[0]:
                problems.append(f"{where}: {name} ({key}) imports {target} ({target_key}): sibling folders "
                                f"of rank {rank}")
        graph[name] = edges - {name}
    problems += [f"cycle: {' -> '.join(cycle)}" for cycle in _cycles(graph)]
    folders = {_folder(name, modules) for name in modules}
    problems += [f"{folder}: a folder without a rank in RANKS" for folder in sorted(folders)
                 if folder.count(".") and folder.split(".", 1)[1] not in RANKS]
    return problems


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """One cycle through each strongly connected group of modules (Tarjan)."""
    index, low, stack, on_stack, groups = {}, {}, [], set(), []

    def visit(node):
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for nxt in sorted(graph.get(node, ())):
            if nxt not in index:
                visit(nxt)
                low[node] = min(low[node], low[nxt])
            elif nxt in on_stack:
                low[node] = min(low[node], index[nxt])
        if low[node] == index[node]:
            group = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                group.append(member)
                if member == node:
                    break
            if len(group) > 1:
                groups.append(group)

    for node in sorted(graph):
        if node not in index:
            visit(node)
    cycles = []
    for group in groups:
        members, path, node = set(group), [], min(group)
        while node not in path:
            path.append(node)
            node = min(n for n in graph[node] if n in members)
        cycles.append(path[path.index(node):] + [node])
    return cycles


def test_imports_run_one_way_without_a_loop():
    """Every import of every module goes to its own folder or a lower rank; no cycle."""
    assert layout_problems(PACKAGE) == []


def test_the_check_fails_on_an_upward_import_and_a_cycle(tmp_path):
    """The check itself: a package with a scene module importing inference (upward),
    two inference modules importing each other (one inside a function), an import of a
    missing module and a folder without a rank is refused on each count."""
    package = tmp_path / "fwdfit"
    files = json.loads((LAYOUT_DATA / "package.json").read_text())  # path -> source of a small package
    for name, text in files.items():
        (package / name).parent.mkdir(parents=True, exist_ok=True)
        (package / name).write_text(text)
    problems = "\n".join(layout_problems(package))
    assert "fwdfit.scene._scene (rank 2, scene) imports fwdfit.inference._a (rank 5, inference): upward" in problems
    assert "cycle: fwdfit.inference._a -> fwdfit.inference._b -> fwdfit.inference._a" in problems
    assert "cli/__init__.py:2: imports fwdfit.scene._gone, neither a module" in problems
    assert "fwdfit.extra: a folder without a rank" in problems
    assert "cli/__init__.py:1" not in problems  # the lazy face's name resolves to inference._a


def test_the_docstring_states_the_ranks():
    """src/fwdfit/__init__.py's docstring names every folder of RANKS with its rank."""
    for key, rank in RANKS.items():
        if key and key != "__main__":
            assert f"{rank} {key.replace('.', '/')}/" in " ".join(fwdfit.__doc__.split()), key


def _private(dotted: str) -> bool:
    return any(part.startswith("_") and not (part.startswith("__") and part.endswith("__"))
               for part in dotted.split("."))


def _private_uses(tree: ast.AST) -> list[tuple[int, str]]:
    """Imports of a private fwdfit name, attributes ``fwdfit._x`` and strings naming one."""
    uses = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            uses += [(node.lineno, a.name) for a in node.names if a.name.startswith("fwdfit") and _private(a.name)]
        elif isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] == "fwdfit" and not node.level:
            uses += [(node.lineno, f"{node.module}.{a.name}") for a in node.names
                     if _private(f"{node.module}.{a.name}")]
        elif isinstance(node, ast.Attribute) and _private(node.attr):
            chain, inner = [node.attr], node.value
            while isinstance(inner, ast.Attribute):
                chain.append(inner.attr)
                inner = inner.value
            if isinstance(inner, ast.Name) and inner.id == "fwdfit":
                uses.append((node.lineno, ".".join(["fwdfit", *reversed(chain)])))
        elif isinstance(node, ast.Constant) and isinstance(node.value, str):
            text = node.value
            if text.startswith("fwdfit.") and text.replace(".", "").replace("_", "").isalnum() and _private(text):
                uses.append((node.lineno, text))
    return sorted(set(uses))


def _sources():
    """(file, parsed source) of every script, test, benchmark and notebook code cell."""
    for folder in ("tests", "benchmarks", "notebooks"):
        for path in sorted((ROOT / folder).rglob("*.py")):
            yield path, ast.parse(path.read_text())
        for path in sorted((ROOT / folder).rglob("*.ipynb")):
            for i, cell in enumerate(json.loads(path.read_text())["cells"]):
                if cell["cell_type"] == "code":
                    lines = cell["source"] if isinstance(cell["source"], list) else cell["source"].splitlines(True)
                    code = "".join(line for line in lines if not line.lstrip().startswith(("%", "!")))
                    yield path.with_name(f"{path.name}[cell {i}]"), ast.parse(code)


def test_tests_benchmarks_and_notebooks_import_public_names_only():
    """No test, benchmark, notebook or script imports (or patches) a private fwdfit name."""
    found = [f"{path.relative_to(ROOT)}:{line}: {name}" for path, tree in _sources()
             for line, name in _private_uses(tree)]
    assert found == []


def test_the_private_name_check_fails_on_each_form():
    """Each form of a private use, one per line of ``data/layout/private_name_forms.txt`` (kept
    out of this file, which the check reads too); its last line, a public name, passes."""
    code = (LAYOUT_DATA / "private_name_forms.txt").read_text()
    assert sorted({line for line, _ in _private_uses(ast.parse(code))}) == [1, 2, 3, 4, 5]


def test_every_public_name_of_the_top_level_face_resolves():
    """``fwdfit``'s lazy table: each name of ``__all__`` is found where the table says."""
    assert sorted(dir(fwdfit)) == sorted(fwdfit.__all__)
    for name in fwdfit.__all__:
        assert getattr(fwdfit, name) is not None
