"""The layering rule of docs/architecture.md, read from the source with ``ast``.

protocol < world < radio < runtime < nodes < gateway < view < experiments < bench < cli:
a module imports only from its own layer or the layers below it, and no two
modules import each other, directly or around a circle. Every import counts:
module level, inside functions and under ``TYPE_CHECKING``. No exception list.
"""

from __future__ import annotations

import ast
import importlib.metadata
import re
import sys
import tomllib
from collections.abc import Iterator, Mapping
from pathlib import Path

import pytest

import awaremw

LAYERS = (
    "protocol",
    "world",
    "radio",
    "runtime",
    "security",
    "nodes",
    "gateway",
    "view",
    "ops",
    "experiments",
    "bench",
    "cli",
)
PACKAGE = "awaremw"
ROOT = Path(awaremw.__file__).resolve().parent


def modules(root: Path) -> dict[str, Path]:
    """Dotted module name -> file, for every ``.py`` under ``root`` (a package)."""
    out: dict[str, Path] = {}
    for path in sorted(root.rglob("*.py")):
        parts = [root.name, *path.relative_to(root).with_suffix("").parts]
        if parts[-1] == "__init__":
            parts.pop()
        out[".".join(parts)] = path
    return out


def imports(name: str, path: Path, known: Mapping[str, Path]) -> Iterator[tuple[str, int]]:
    """(imported module of the package, line) for every import statement in the file.

    ``from pkg import sub`` names the submodule ``pkg.sub`` when it is one."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name, node.lineno
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                target = ".".join([*base, *([node.module] if node.module else [])])
            else:
                target = node.module or ""
            for alias in node.names:
                sub = f"{target}.{alias.name}"
                yield (sub if sub in known else target), node.lineno


def graph(root: Path) -> dict[str, dict[str, int]]:
    """module -> {imported module of the same package: first line}."""
    known = modules(root)
    top = root.name
    out: dict[str, dict[str, int]] = {}
    for name, path in known.items():
        edges: dict[str, int] = {}
        for target, line in imports(name, path, known):
            if (target == top or target.startswith(top + ".")) and target != name:
                edges.setdefault(target, line)
        out[name] = edges
    return out


def rank(module: str) -> int:
    """The layer index of a module: the package root sits below every layer,
    ``__main__`` with the CLI; anything else must be inside a layer."""
    parts = module.split(".")
    if len(parts) == 1:
        return -1
    if parts[1] == "__main__":
        return LAYERS.index("cli")
    if parts[1] not in LAYERS:
        raise AssertionError(f"{module} is in no layer: add its package to LAYERS and the docs")
    return LAYERS.index(parts[1])


def upward(g: Mapping[str, Mapping[str, int]]) -> list[str]:
    return [
        f"{src} (line {line}) imports {dst}: {LAYERS[rank(dst)]} sits above "
        f"{LAYERS[rank(src)] if rank(src) >= 0 else 'the package root'}"
        for src, edges in sorted(g.items())
        for dst, line in sorted(edges.items())
        if rank(dst) > rank(src)
    ]


def circles(g: Mapping[str, Mapping[str, int]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    found: list[list[str]] = []
    for start in g:
        if start in index:
            continue
        work: list[tuple[str, Iterator[str]]] = [(start, iter(g[start]))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on.add(start)
        while work:
            v, it = work[-1]
            for w in it:
                if w not in g:
                    continue
                if w not in index:
                    index[w] = low[w] = len(index)
                    stack.append(w)
                    on.add(w)
                    work.append((w, iter(g[w])))
                    break
                if w in on:
                    low[v] = min(low[v], index[w])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[v])
                if low[v] == index[v]:
                    comp: list[str] = []
                    while True:
                        w = stack.pop()
                        on.discard(w)
                        comp.append(w)
                        if w == v:
                            break
                    if len(comp) > 1:
                        found.append(sorted(comp))
    return found


def test_every_import_goes_down_the_layers() -> None:
    g = graph(ROOT)
    assert len(g) > 50  # the whole package was read
    assert upward(g) == []


def test_no_module_imports_one_that_imports_it_back() -> None:
    assert circles(graph(ROOT)) == []


def test_both_media_sit_side_by_side_on_the_radio_floor() -> None:
    """The media -- the modules that run radio/reception.py's rules on every
    frame -- are on one floor, named so that a folder listing tells them apart
    (docs/architecture.md). A medium that stops calling the rules, a third
    one, or a medium module back in runtime/ fails here."""
    g = graph(ROOT)
    media = sorted(m for m, edges in g.items() if "awaremw.radio.reception" in edges)
    assert media == ["awaremw.radio.virtual_medium", "awaremw.radio.zenoh_medium"]
    runtime = [m for m in g if m.startswith("awaremw.runtime.")]
    assert [m for m in runtime if "medium" in m or m.endswith(".virtual")] == []


def test_every_module_sits_in_a_layer() -> None:
    for name in modules(ROOT):
        rank(name)  # raises for a module outside the layers


def _canonical(dist: str) -> str:
    return re.sub(r"[-_.]+", "-", dist).lower()


def test_every_third_party_import_is_declared() -> None:
    """pip installs only the declared dependencies: an undeclared import works in
    a development venv (pulled in by another package) and breaks elsewhere."""
    project = tomllib.loads((ROOT.parent / "pyproject.toml").read_text(encoding="utf-8"))
    declared = {
        _canonical(re.split(r"[<>=!~;\[ ]", d, maxsplit=1)[0])
        for d in project["project"]["dependencies"]
    }
    dists = importlib.metadata.packages_distributions()
    missing: list[str] = []
    for name, path in modules(ROOT).items():
        for target, line in imports(name, path, {}):
            top = target.split(".")[0]
            if top == PACKAGE or top in sys.stdlib_module_names or not top:
                continue
            if not {_canonical(d) for d in dists.get(top, [top])} & declared:
                missing.append(f"{name} (line {line}) imports {top}")
    assert missing == []


def test_the_picture_in_the_docs_is_of_this_code() -> None:
    """docs/img/architecture.png was drawn from today's floors and modules
    (``python tests/architecture_picture.py`` draws it again)."""
    import architecture_picture as picture

    drawn = picture.read_structure()
    assert drawn is not None, "the picture carries no structure: draw it again"
    now = picture.structure()
    moved = {f: now[f] for f in now if drawn.get(f) != now[f]}
    assert moved == {}, "the code has moved on: python tests/architecture_picture.py"


# ------------------------------------------------------------------ the checker itself


def _tree(tmp: Path, files: Mapping[str, str]) -> Path:
    root = tmp / PACKAGE
    for rel, text in files.items():
        p = root / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(text, encoding="utf-8")
    return root


def test_the_checker_finds_an_upward_import_anywhere(tmp_path: Path) -> None:
    root = _tree(
        tmp_path,
        {
            "__init__.py": "",
            "radio/__init__.py": "",
            "radio/medium.py": (
                "from typing import TYPE_CHECKING\n"
                "if TYPE_CHECKING:\n"
                "    from awaremw.runtime.clock import Clock\n"
                "def f():\n"
                "    from ..gateway import bridge\n"
            ),
            "runtime/__init__.py": "",
            "runtime/clock.py": "from awaremw.radio import medium\n",
            "gateway/__init__.py": "",
            "gateway/bridge.py": "",
        },
    )
    found = upward(graph(root))
    assert found == [
        "awaremw.radio.medium (line 5) imports awaremw.gateway.bridge: gateway sits above radio",
        "awaremw.radio.medium (line 3) imports awaremw.runtime.clock: runtime sits above radio",
    ]


def test_the_checker_finds_a_circle_inside_a_layer(tmp_path: Path) -> None:
    root = _tree(
        tmp_path,
        {
            "__init__.py": "",
            "protocol/__init__.py": "",
            "protocol/a.py": "from awaremw.protocol import b\n",
            "protocol/b.py": "def f():\n    from awaremw.protocol.c import x\n",
            "protocol/c.py": "import awaremw.protocol.a\nx = 1\n",
            "protocol/d.py": "from awaremw.protocol import a\n",
        },
    )
    assert circles(graph(root)) == [
        ["awaremw.protocol.a", "awaremw.protocol.b", "awaremw.protocol.c"]
    ]


def test_a_module_outside_the_layers_is_refused() -> None:
    with pytest.raises(AssertionError, match="in no layer"):
        rank("awaremw.plugins.x")


# ------------------------------------------------------------------ private names


def private_imports(root: Path) -> list[str]:
    """Every use of another module's private (underscore) name in the package:
    ``from awaremw.x import _name``, and ``mod._name`` on a module imported as
    ``mod`` (``import awaremw.x as mod``, ``from awaremw import x``). Dunders
    (``__version__``) are public."""
    known = modules(root)
    top = root.name
    found: list[str] = []

    def private(name: str) -> bool:
        return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))

    for name, path in known.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
        aliases: dict[str, str] = {}  # local name -> package module it stands for
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                for alias in node.names:
                    if alias.name.startswith(top + ".") and alias.asname:
                        aliases[alias.asname] = alias.name
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = package.split(".")
                    base = base[: len(base) - (node.level - 1)]
                    target = ".".join([*base, *([node.module] if node.module else [])])
                else:
                    target = node.module or ""
                if target != top and not target.startswith(top + "."):
                    continue
                for alias in node.names:
                    sub = f"{target}.{alias.name}"
                    if sub in known:
                        aliases[alias.asname or alias.name] = sub
                    elif private(alias.name) and target != name:
                        found.append(f"{name} (line {node.lineno}) imports {target}.{alias.name}")
        for node in ast.walk(tree):
            if (
                isinstance(node, ast.Attribute)
                and isinstance(node.value, ast.Name)
                and node.value.id in aliases
                and private(node.attr)
                and aliases[node.value.id] != name
            ):
                mod = aliases[node.value.id]
                found.append(f"{name} (line {node.lineno}) uses {mod}.{node.attr}")
    return found


def test_no_module_imports_another_modules_private_names() -> None:
    assert private_imports(ROOT) == []


def test_the_checker_finds_a_private_import(tmp_path: Path) -> None:
    root = _tree(
        tmp_path,
        {
            "__init__.py": "__version__ = '1'\n",
            "radio/__init__.py": "",
            "radio/model.py": "_M64 = 1\nPUBLIC = 2\n_own = _M64\n",
            "radio/medium.py": (
                "from awaremw.radio.model import _M64, PUBLIC\n"
                "from awaremw import __version__\n"
                "def f():\n"
                "    from .model import _own\n"
            ),
            "runtime/__init__.py": "",
            "runtime/driver.py": (
                "from awaremw.radio import model\n"
                "import awaremw.radio.model as m\n"
                "x = model._M64 + m.PUBLIC + m._own\n"
            ),
        },
    )
    assert sorted(private_imports(root)) == [
        "awaremw.radio.medium (line 1) imports awaremw.radio.model._M64",
        "awaremw.radio.medium (line 4) imports awaremw.radio.model._own",
        "awaremw.runtime.driver (line 3) uses awaremw.radio.model._M64",
        "awaremw.runtime.driver (line 3) uses awaremw.radio.model._own",
    ]
