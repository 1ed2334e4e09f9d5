"""The folders read as the pipeline, bottom to top, and the imports say so.

Read from the source (the AST of every module, imports inside functions included), not
from what happens to be imported at run time:
- each module belongs to one floor; a module imports only from its own floor and the
  floors below it (FLOORS, bottom first);
- the renderer never imports its applications (fitting, data_synth), and fitting never
  imports data_synth;
- there is no import circle anywhere, between modules of one floor included;
- fitting and data_synth use diffshade through its public faces only: the package itself
  and its floor packages (and the foundation's two modules), and only the names those list
  in `__all__` (PUBLIC_FACES).
An import of a package counts as an import of its `__init__`; `from P import m`, m a
submodule, as an import of P.m.
"""

import ast
import importlib
import importlib.util
import json
import types
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("diffshade", "fitting", "data_synth")

#: per package, its floors from the bottom: (name, modules). A module belongs to the floor
#: that names it or the folder it is in (a package's own name covers only its __init__).
FLOORS = {
    "diffshade": [
        ("foundation", ["diffshade.numerics", "diffshade.settings", "diffshade.budget"]),
        ("host", ["diffshade.host"]),
        ("scene", ["diffshade.scene"]),
        ("raster", ["diffshade.raster"]),
        ("shading", ["diffshade.shading"]),
        ("composite", ["diffshade.composite"]),
        ("pipeline", ["diffshade.pipeline"]),
        ("io", ["diffshade.io"]),
        ("faces", ["diffshade", "diffshade.cli", "diffshade.__main__", "diffshade.analytic"]),
    ],
    "fitting": [
        ("spec", ["fitting.spec"]),
        ("data", ["fitting.data"]),
        ("model", ["fitting.model"]),
        ("solve", ["fitting.solve"]),
        ("report", ["fitting.report"]),
        ("driver", ["fitting", "fitting.checkpoint", "fitting.cli", "fitting.driver",
                    "fitting.import_cli", "fitting.inputs", "fitting.plan", "fitting.precompile",
                    "fitting.refine", "fitting.run", "fitting.texture_fit",
                    "fitting.texture_run"]),
    ],
    "data_synth": [("data_synth", ["data_synth", "data_synth.background", "data_synth.cli",
                                   "data_synth.materials", "data_synth.options",
                                   "data_synth.scenes"])],
}
#: what fitting and data_synth may import diffshade through: the package, the floors' packages
#: and the foundation's modules (host has no public face)
PUBLIC_FACES = ("diffshade", "diffshade.numerics", "diffshade.settings", "diffshade.budget",
                "diffshade.scene",
                "diffshade.raster", "diffshade.shading", "diffshade.composite",
                "diffshade.pipeline", "diffshade.io")
#: which packages each package may import
ALLOWED = {"diffshade": {"diffshade"}, "fitting": {"diffshade", "fitting"},
           "data_synth": {"diffshade", "fitting", "data_synth"}}


def module_files():
    """{module name: path} of every module of the three packages."""
    found = {}
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            parts = path.relative_to(ROOT).with_suffix("").parts
            name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
            found[name] = path
    return found


MODULES = module_files()


def _target(name):
    """The module an import of `name` runs: name itself, or its closest enclosing module
    (for `from P import f`, f not a module)."""
    while name not in MODULES and "." in name:
        name = name.rpartition(".")[0]
    return name


def imports_of(name, path):
    """The project modules that module `name` imports (anywhere in its source)."""
    package_of_file = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            bases = [alias.name for alias in node.names]
            found.update(_target(b) for b in bases if b.split(".")[0] in PACKAGES)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package_of_file.split(".")
                anchor = anchor[:len(anchor) - (node.level - 1)]
                base = ".".join(anchor + ([base] if base else []))
            if base.split(".")[0] not in PACKAGES:
                continue
            for alias in node.names:
                full = f"{base}.{alias.name}"
                found.add(full if full in MODULES else _target(base))
    found.discard(name)
    return found


GRAPH = {name: imports_of(name, path) for name, path in MODULES.items()}


def floor_of(name):
    """(package, floor index, floor name) of a module; (package, None, None) if no floor
    names it."""
    package = name.split(".")[0]
    for index, (floor, prefixes) in enumerate(FLOORS[package]):
        for prefix in prefixes:
            if name == prefix or (prefix != package and name.startswith(prefix + ".")):
                return package, index, floor
    return package, None, None


def test_every_module_is_on_a_floor():
    """A new module is placed on a floor on purpose: in a floor's folder, or named."""
    loose = [name for name in MODULES if floor_of(name)[1] is None]
    assert loose == [], f"modules on no floor: {loose}"
    for floors in FLOORS.values():
        for _, prefixes in floors:
            for prefix in prefixes:
                assert prefix in MODULES, f"floor entry {prefix} names no module"


def test_imports_run_down_the_floors():
    upward = []
    for name, targets in GRAPH.items():
        package, index, floor = floor_of(name)
        for target in targets:
            other = target.split(".")[0]
            if other not in ALLOWED[package]:
                upward.append(f"{name} -> {target} ({package} must not import {other})")
            elif other == package:
                _, target_index, target_floor = floor_of(target)
                if target_index > index:
                    upward.append(f"{name} ({floor}) -> {target} ({target_floor})")
    assert upward == [], "imports that run up the floors:\n" + "\n".join(sorted(upward))


def find_cycle(graph):
    """One import circle of graph {node: targets} as a list of nodes, or None."""
    state = {}

    def visit(node, path):
        state[node] = "open"
        path.append(node)
        for target in sorted(graph.get(node, ())):
            if state.get(target) == "open":
                return path[path.index(target):] + [target]
            if target not in state:
                cycle = visit(target, path)
                if cycle:
                    return cycle
        state[node] = "done"
        path.pop()
        return None

    for node in sorted(graph):
        if node not in state:
            cycle = visit(node, [])
            if cycle:
                return cycle
    return None


def test_no_import_circle():
    assert find_cycle(GRAPH) is None, " -> ".join(find_cycle(GRAPH))


@pytest.mark.parametrize("graph, expected", [
    ({"a": {"b"}, "b": {"c"}, "c": set()}, None),
    ({"a": {"b"}, "b": {"c"}, "c": {"a"}}, ["a", "b", "c", "a"]),
    ({"a": {"a2"}, "a2": set(), "b": {"b"}}, ["b", "b"]),
])
def test_find_cycle_finds_circles(graph, expected):
    assert find_cycle(graph) == expected


def test_the_checks_see_a_back_arrow_and_a_circle(tmp_path):
    """The AST reading itself: a lazy import inside a function counts, a relative import
    resolves, and `from P import m` of a submodule points at P.m."""
    path = tmp_path / "mod.py"
    path.write_text("def f():\n    from fitting.cli import register\n"
                    "from .fragments import rasterize\nfrom diffshade.host import candidates\n")
    found = imports_of("diffshade.raster.search", path)
    assert found == {"fitting.cli", "diffshade.raster.fragments", "diffshade.host.candidates"}
    assert floor_of("diffshade.raster.search")[2] == "raster"
    assert floor_of("diffshade.cli")[2] == "faces"
    assert floor_of("fitting.solve.linear")[2] == "solve"


def exported(face):
    """The names a public face lists in its `__all__` (read from its source)."""
    for node in ast.parse(MODULES[face].read_text()).body:
        if isinstance(node, ast.Assign) and [getattr(n, "id", None) for n in node.targets] \
                == ["__all__"]:
            return set(ast.literal_eval(node.value))
    return set()


EXPORTED = {face: exported(face) for face in PUBLIC_FACES}


def private_uses(path, exported_names=EXPORTED):
    """What the module at `path` takes from diffshade other than a public face's listed
    names: `import diffshade.x.y`, `from diffshade.x.y import`, a name missing from the
    face's __all__, or an attribute of `import diffshade as ds` missing from its __all__."""
    found, aliases = [], set()
    tree = ast.parse(path.read_text(), str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name == "diffshade":
                    aliases.add(alias.asname or alias.name)
                elif alias.name.startswith("diffshade."):
                    found.append(f"{node.lineno}: import {alias.name}")
        elif isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] == "diffshade":
            face = node.module
            if face not in exported_names:
                found.append(f"{node.lineno}: from {face} import ...")
                continue
            found += [f"{node.lineno}: {alias.name} is not in {face}.__all__"
                      for alias in node.names if alias.name not in exported_names[face]]
    for node in ast.walk(tree):
        if (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name)
                and node.value.id in aliases and node.attr not in exported_names["diffshade"]):
            found.append(f"{node.lineno}: {node.value.id}.{node.attr} is not in "
                         "diffshade.__all__")
    return found


def test_every_public_face_lists_its_names():
    for face, names in EXPORTED.items():
        assert names, f"{face} has no __all__"


def test_applications_use_diffshade_through_public_faces():
    """fitting and data_synth import from diffshade and its floors' packages, never from a
    module below a floor's face, so that diffshade can move its modules freely."""
    private = [f"{name} {use}" for name, path in MODULES.items()
               if name.split(".")[0] in ("fitting", "data_synth")
               for use in private_uses(path)]
    assert private == [], "diffshade used past its public faces:\n" + "\n".join(private)


def test_the_public_face_check_sees_private_uses(tmp_path):
    path = tmp_path / "mod.py"
    path.write_text("import diffshade as ds\nimport diffshade.shading.samples\n"
                    "from diffshade.scene import Mesh, take_material, _check_arrays\n"
                    "from diffshade.raster.search import search_faces\n"
                    "def f():\n    from diffshade import render, view_dirs\n"
                    "    return ds.render, ds.scene_to_dict\n")
    assert sorted(private_uses(path)) == sorted([
        "2: import diffshade.shading.samples",
        "3: _check_arrays is not in diffshade.scene.__all__",
        "4: from diffshade.raster.search import ...",
        "6: view_dirs is not in diffshade.__all__",
        "7: ds.scene_to_dict is not in diffshade.__all__",
    ])


def test_no_name_shadows_a_module():
    """`package.name` is the module package/name.py wherever that module exists: a
    function exported under a module's name would hide it (`import a.b as m` gives the
    function), so modules and the functions they export have different names."""
    shadowed = []
    for name in MODULES:
        if "." not in name or name.endswith("__main__"):
            continue
        parent, _, leaf = name.rpartition(".")
        importlib.import_module(name)
        attribute = getattr(importlib.import_module(parent), leaf)
        if not isinstance(attribute, types.ModuleType):
            shadowed.append(f"{name} is hidden by {parent}.{leaf} = {attribute!r}")
    assert shadowed == [], "\n".join(shadowed)


def _project_imports(source):
    """(module, names) of each absolute import of the three packages in source."""
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.ImportFrom) and not node.level and node.module \
                and node.module.split(".")[0] in PACKAGES:
            yield node.module, [alias.name for alias in node.names]
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.split(".")[0] in PACKAGES:
                    yield alias.name, []


def test_benchmarks_and_notebooks_import_what_exists():
    """Benchmarks and notebooks are not all run by the tests, so a moved module or a name
    left out of a public face would first show when someone runs them: each of their
    imports (inside functions too) must resolve."""
    sources = {str(p.relative_to(ROOT)): p.read_text()
               for folder in ("benchmarks", "docs", "notebooks")
               for p in (ROOT / folder).glob("*.py")}
    for path in (ROOT / "notebooks").glob("*.ipynb"):
        cells = json.loads(path.read_text())["cells"]
        sources |= {f"{path.name} cell {i}": "".join(cell["source"])
                    for i, cell in enumerate(cells) if cell["cell_type"] == "code"}
    missing = []
    for where, source in sources.items():
        for module, names in _project_imports(source):
            try:
                imported = importlib.import_module(module)
            except ImportError as err:
                missing.append(f"{where}: {module} ({err})")
                continue
            missing += [f"{where}: {module}.{name}" for name in names
                        if not hasattr(imported, name)
                        and importlib.util.find_spec(f"{module}.{name}") is None]
    assert missing == [], "\n".join(missing)
