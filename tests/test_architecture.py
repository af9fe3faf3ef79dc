"""The house rules of docs/architecture.md, checked on the code itself (its imports and names, read with ``ast``).

- no import cycle among the project's modules, counting every import (inside functions and TYPE_CHECKING too);
- the layers import downwards only: ``sensors`` and ``sync`` never import ``logger``; ``sensors`` never imports
  ``sync``; ``logger.nav`` (the filter) imports nothing else of ``logger``;
- no module reads another module's private names (``obj._name`` for a ``_name`` it does not define itself, or
  ``from x import _name``);
- neither ``sync``, ``sensors`` nor ``logger.nav`` holds a topic name: topics and payload keys belong to the record
  layer, and the rest of ``logger`` names a topic by its constant in :mod:`logger.recording.topics`.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from logger.recording.topics import TOPICS

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("logger", "sync", "sensors")
CODE_DIRS = (*PACKAGES, "tools")
# Underscore names that are public API of the standard library or of a dependency, not anyone's private state;
# gpiod's ``_ext`` is its C extension, the documented seam the GPIO fake replaces.
PUBLIC_UNDERSCORE = {"_replace", "_asdict", "_fields", "_make", "_exit", "_getframe", "_field_defaults", "_SimpleCData",
                     "_ext"}


def module_name(path: Path) -> str:
    rel = path.relative_to(ROOT).with_suffix("")
    parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
    return ".".join(parts)


def project_modules() -> dict[str, Path]:
    return {module_name(p): p for pkg in PACKAGES for p in sorted((ROOT / pkg).rglob("*.py"))}


MODULES = project_modules()


def resolve(name: str, imported: str | None = None) -> str | None:
    """The project module an import brings in: ``from a.b import c`` is a.b.c when that is a module, else a.b."""
    if imported is not None and f"{name}.{imported}" in MODULES:
        return f"{name}.{imported}"
    return name if name in MODULES else None


def imports_of(path: Path) -> list[tuple[str, int]]:
    """(project module, line) of every import in the file, wherever it stands."""
    tree = ast.parse(path.read_text(), str(path))
    found: list[tuple[str, int]] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                mod = resolve(alias.name)
                if mod:
                    found.append((mod, node.lineno))
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            for alias in node.names:
                mod = resolve(node.module, alias.name)
                if mod:
                    found.append((mod, node.lineno))
    return found


def graph() -> dict[str, set[str]]:
    """Module -> the project modules it imports (a package's ``__init__`` is left out: it holds no code)."""
    out: dict[str, set[str]] = {}
    for name, path in MODULES.items():
        out[name] = {m for m, _ in imports_of(path) if m != name and MODULES[m].name != "__init__.py"}
    return out


def cycles(g: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []
    counter = [0]

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in g.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(g):
        if v not in index:
            visit(v)
    return out


def test_the_cycle_finder_finds_a_cycle() -> None:
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_no_import_cycle_in_the_project() -> None:
    found = cycles(graph())
    assert not found, "import cycles: " + "; ".join(" <-> ".join(c) for c in found)


LAYER_RULES = (  # (modules under, may not import modules under, why)
    ("sensors", "logger", "drivers and device models know nothing of the daemon"),
    ("sync", "logger", "the clock takes named inputs, not the logger's records"),
    ("sensors", "sync", "drivers stamp nothing: time is the runtime's and the clock's"),
    ("logger.nav", "logger.recording", "the filter takes typed inputs, not records"),
    ("logger.nav", "logger.runtime", "the filter runs in a thread, it does not own one"),
    ("logger.nav", "logger.cli", "the filter serves the commands, not the other way"),
    ("logger.nav", "logger.exports", "the filter serves the exports, not the other way"),
    ("logger.recording", "logger.runtime", "the file format does not depend on the daemon"),
    ("logger.recording", "logger.cli", "the file format does not depend on a command"),
    ("logger.runtime", "logger.cli", "the daemon does not depend on a command"),
    ("logger.exports", "logger.cli", "the exports do not depend on a command"),
)


def _under(module: str, prefix: str) -> bool:
    return module == prefix or module.startswith(prefix + ".")


@pytest.mark.parametrize(("low", "high", "why"), LAYER_RULES, ids=[f"{a}-not-{b}" for a, b, _ in LAYER_RULES])
def test_layers_import_downwards_only(low: str, high: str, why: str) -> None:
    bad = [f"{MODULES[name].relative_to(ROOT)}:{line} imports {mod}"
           for name in MODULES if _under(name, low)
           for mod, line in imports_of(MODULES[name]) if _under(mod, high)]
    assert not bad, f"{why}: " + "; ".join(bad)


def where(path: Path) -> str:
    return str(path.relative_to(ROOT)) if path.is_relative_to(ROOT) else path.name


def private_reads(path: Path) -> list[str]:
    """Reads of private names another module owns: ``x._name`` for a ``_name`` this module never defines, and
    ``from project.module import _name``."""
    tree = ast.parse(path.read_text(), str(path))
    own: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)) and node.name.startswith("_"):
            own.add(node.name)
        elif (isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Store) and isinstance(node.value, ast.Name)
              and node.value.id in ("self", "cls")):
            own.add(node.attr)  # a name is this module's when its own objects set it, not when it patches another
        elif isinstance(node, ast.Name) and isinstance(node.ctx, ast.Store):
            own.add(node.id)
        elif isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            own.add(node.target.id)
        elif isinstance(node, ast.ClassDef):
            for item in node.body:  # __slots__ names and class-level fields
                if isinstance(item, ast.Assign) and any(isinstance(t, ast.Name) and t.id == "__slots__"
                                                        for t in item.targets):
                    own |= {e.value for e in ast.walk(item.value) if isinstance(e, ast.Constant)
                            and isinstance(e.value, str)}
    bad: list[str] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__"):
            if node.attr not in own and node.attr not in PUBLIC_UNDERSCORE:
                bad.append(f"{where(path)}:{node.lineno} reads .{node.attr}")
        elif isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0] in PACKAGES:
            bad += [f"{where(path)}:{node.lineno} imports {node.module}.{a.name}" for a in node.names
                    if a.name.startswith("_") and not a.name.startswith("__")]
    return bad


def test_private_reads_are_found(tmp_path: Path) -> None:
    probe = tmp_path / "probe.py"
    probe.write_text("from logger.nav.engine import _x\n\nclass A:\n    def f(self, e):\n"
                     "        self._mine = 1\n        e._patched = 2\n"
                     "        return e._theirs, self._mine, e._patched\n")
    found = private_reads(probe)
    assert sorted(f.split()[-1] for f in found) == ["._patched", "._patched", "._theirs", "logger.nav.engine._x"]


def test_no_module_reads_another_modules_private_names() -> None:
    bad = [line for d in CODE_DIRS for p in sorted((ROOT / d).rglob("*.py")) for line in private_reads(p)]
    assert not bad, "\n".join(bad)


def topic_strings(path: Path) -> list[str]:
    tree = ast.parse(path.read_text(), str(path))
    return [f"{path.relative_to(ROOT)}:{node.lineno} {node.value!r}" for node in ast.walk(tree)
            if isinstance(node, ast.Constant) and isinstance(node.value, str) and node.value in TOPICS]


def test_topic_strings_are_found() -> None:
    assert topic_strings(ROOT / "logger" / "recording" / "topics.py")  # the one place that spells them


@pytest.mark.parametrize("folder", ["sync", "sensors", "logger/nav"])
def test_the_clock_the_drivers_and_the_filter_hold_no_topic_name(folder: str) -> None:
    bad = [line for p in sorted((ROOT / folder).rglob("*.py")) for line in topic_strings(p)]
    assert not bad, "topics belong to the record layer: " + "; ".join(bad)


def test_the_logger_spells_each_topic_name_once() -> None:
    """Everywhere else in ``logger`` a topic is named by its constant from :mod:`logger.recording.topics`."""
    spelled = ROOT / "logger" / "recording" / "topics.py"
    bad = [line for p in sorted((ROOT / "logger").rglob("*.py")) if p != spelled for line in topic_strings(p)]
    assert not bad, "use the constants of logger.recording.topics: " + "; ".join(bad)


def test_the_logger_probes_none_of_its_own_objects_with_getattr() -> None:
    """A contract's optional parts have their defaults in its base class (docs/architecture.md): the daemon once
    asked the clock ``getattr(self.clock, "chrony", None)``, past ``StampClock``."""
    probes = []
    for path in sorted((ROOT / "logger").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "getattr":
                target = ast.unparse(node.args[0]) if node.args else ""
                if target.startswith("self.") or target in ("clock", "source", "driver"):
                    probes.append(f"{path.relative_to(ROOT)}:{node.lineno} getattr({target}, ...)")
    assert probes == []
