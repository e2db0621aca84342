"""The workspace's import structure: no import loops anywhere, and the package layering that docs/design.md
states in its "Structure" table, read from there so that the page cannot drift from the code.

Every module of every package in ``ros2_ws/src`` is parsed with ``ast``; nothing is imported (no torch, no
ROS needed). An import is an arrow from its module to the workspace module it names (``from a.b import c``
names ``a.b.c`` when that is a module, else ``a.b``), or to an outside module (its top-level name: ``torch``,
``rclpy``). Every import counts: at module level, inside functions, and under ``if TYPE_CHECKING:`` (a loop
there still ties the modules together for a reader, a type checker and the docs). A package's ``__init__``
that runs on the way to a module counts for what loads at import time (``never imports``) but not as an
arrow of a loop.

The checks:

- no import loop among the modules (each loop is named, with the file and line of each arrow);
- the arrows between packages are exactly the table's ``imports`` column;
- a package's ``never imports`` names (outside modules, or ``ROS``: rclpy, message and interface packages,
  launch, ament) appear in no import of its modules, and importing any of its modules loads none of them
  through the workspace modules it imports at import time (module level, outside ``TYPE_CHECKING``).
  (``tests/test_policy_weights.py`` checks the nodes' imports at run time, beyond the workspace's modules.)
- the core's layers, the numbered list of docs/design.md's "The core, module by module": a module of
  ``morph_core`` imports no module of a layer above its own, at any level (inside functions too), and every
  subpackage of the core is in one layer;
- the trainer's library modules never import its command-line modules (``trainer.cli.*``, a room's ``cli``,
  a ``__main__``): the commands import the library, not the reverse.
"""

from __future__ import annotations

import ast
import re
from collections import deque
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "ros2_ws" / "src"
DESIGN = ROOT / "docs" / "design.md"
ROS_NAMES = {"rclpy", "launch", "launch_ros", "ament_index_python", "rosbag2_py", "message_filters", "tf2_ros"}
"""outside modules that are ROS beside the ``rosidl*`` ones and the ``*_msgs``, ``*_srvs``, ``*_interfaces``
packages"""


def is_ros(name: str) -> bool:
    return (
        name in ROS_NAMES or name.startswith("rosidl") or name.endswith(("_msgs", "_srvs", "_interfaces"))
    )  # fmt: skip


@dataclass(frozen=True)
class Import:
    source: str
    """the importing module"""
    target: str
    """the workspace module imported, or an outside module's top-level name"""
    line: int
    at_import_time: bool
    """runs when ``source`` is imported: at module or class level, not under ``if TYPE_CHECKING:``"""


def workspace_modules() -> dict[str, Path]:
    """Dotted name -> file of every module of every package in ros2_ws/src (a package is a directory with an
    ``__init__.py`` beside a ``package.xml``)."""
    modules = {}
    for package in sorted(p.parent for p in SRC.glob("*/*/__init__.py") if (p.parents[1] / "package.xml").exists()):
        for path in sorted(package.rglob("*.py")):
            name = ".".join(path.relative_to(package.parent).with_suffix("").parts).removesuffix(".__init__")
            modules[name] = path
    return modules


class _Imports(ast.NodeVisitor):
    def __init__(self, module: str, is_package: bool, modules: dict[str, Path]):
        self.module, self.is_package, self.modules = module, is_package, modules
        self.found: list[Import] = []
        self._deferred = 0  # inside a function body or under TYPE_CHECKING

    def _resolve(self, name: str) -> str:
        """The workspace module ``name`` is (or is inside), else the outside module's top-level name."""
        parts = name.split(".")
        for k in range(len(parts), 0, -1):
            if ".".join(parts[:k]) in self.modules:
                return ".".join(parts[:k])
        return parts[0]

    def _add(self, name: str, node: ast.AST) -> None:
        self.found.append(Import(self.module, self._resolve(name), node.lineno, self._deferred == 0))

    def visit_Import(self, node: ast.Import) -> None:
        for alias in node.names:
            self._add(alias.name, node)

    def visit_ImportFrom(self, node: ast.ImportFrom) -> None:
        base = node.module or ""
        if node.level:
            package = self.module.split(".")[: None if self.is_package else -1]
            package = package[: len(package) - (node.level - 1)]
            base = ".".join([*package, base] if base else package)
        for alias in node.names:
            full = f"{base}.{alias.name}"
            self._add(full if full in self.modules else base, node)

    def _deferring(self, node: ast.AST) -> None:
        self._deferred += 1
        self.generic_visit(node)
        self._deferred -= 1

    visit_FunctionDef = visit_AsyncFunctionDef = visit_Lambda = _deferring

    def visit_If(self, node: ast.If) -> None:
        test = node.test
        if (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
            isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
        ):
            self.visit(test)
            self._deferred += 1
            for child in node.body:
                self.visit(child)
            self._deferred -= 1
            for child in node.orelse:
                self.visit(child)
        else:
            self.generic_visit(node)


def all_imports(modules: dict[str, Path]) -> list[Import]:
    found = []
    for name, path in modules.items():
        visitor = _Imports(name, path.name == "__init__.py", modules)
        visitor.visit(ast.parse(path.read_text(encoding="utf-8"), filename=str(path)))
        found += [i for i in visitor.found if i.target != name]
    return found


def package_of(module: str) -> str:
    return module.split(".")[0]


def strongly_connected(graph: dict[str, list[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan's algorithm, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components = []
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(graph[root]))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            node, edges = work[-1]
            for nxt in edges:
                if nxt not in index:
                    index[nxt] = low[nxt] = len(index)
                    stack.append(nxt)
                    on_stack.add(nxt)
                    work.append((nxt, iter(graph[nxt])))
                    break
                if nxt in on_stack:
                    low[node] = min(low[node], index[nxt])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[node])
                if low[node] == index[node]:
                    component = []
                    while True:
                        member = stack.pop()
                        on_stack.discard(member)
                        component.append(member)
                        if member == node:
                            break
                    if len(component) > 1:
                        components.append(sorted(component))
    return components


def a_loop(component: list[str], imports: list[Import]) -> str:
    """One loop through the modules of ``component``, each arrow with its file and line."""
    members = set(component)
    arrows = {}
    for i in imports:
        if i.source in members and i.target in members:
            arrows.setdefault(i.source, {}).setdefault(i.target, i)
    start = component[0]
    parent = {start: None}
    queue = deque([start])
    while queue:  # the shortest way back to start
        node = queue.popleft()
        for nxt, arrow in arrows.get(node, {}).items():
            if nxt == start:
                path = [arrow]
                while parent[node] is not None:
                    path.append(parent[node])
                    node = parent[node].source
                steps = [f"{a.source} -> {a.target} (line {a.line})" for a in reversed(path)]
                return "; ".join(steps)
            if nxt not in parent:
                parent[nxt] = arrow
                queue.append(nxt)
    raise AssertionError(f"no loop found in {component}")


def structure_table() -> dict[str, dict[str, set[str]]]:
    """docs/design.md's "Structure" table: package -> {"imports": {...}, "never imports": {...}}; a cell lists
    backticked names (or ROS), "—" for none."""
    text = DESIGN.read_text(encoding="utf-8")
    section = text.split("\n## Structure\n", 1)[1].split("\n## ", 1)[0]
    rows = [line for line in section.splitlines() if line.startswith("|")]
    header = [cell.strip() for cell in rows[0].strip("|").split("|")]
    table = {}
    for row in rows[2:]:
        cells = dict(zip(header, (cell.strip() for cell in row.strip("|").split("|")), strict=True))
        names = {column: set(re.findall(r"`([\w.]+)`", cells[column])) for column in ("imports", "never imports")}
        if re.search(r"(?<!`)\bROS\b", cells["never imports"]):
            names["never imports"].add("ROS")
        (package,) = re.findall(r"`(\w+)`", cells["package"])
        table[package] = names
    return table


def core_layers() -> dict[str, int]:
    """docs/design.md's layers of the core: unit -> its layer's number (1 at the bottom), from the numbered list
    of "The core, module by module" (a unit is a subpackage, a module of the package's top, or ``__init__``)."""
    text = DESIGN.read_text(encoding="utf-8")
    section = text.split("\n## The core, module by module\n", 1)[1].split("\n## ", 1)[0]
    layers = {}
    for number, names in re.findall(r"^(\d+)\. ((?:`\w+`(?:, )?)+):", section, flags=re.MULTILINE):
        for name in re.findall(r"`(\w+)`", names):
            assert name not in layers, f"docs/design.md puts {name} in two layers"
            layers[name] = int(number)
    return layers


def core_unit(module: str) -> str | None:
    """The layer unit of a ``morph_core`` module (``morph_core.policy.tree`` -> ``policy``), else None."""
    parts = module.split(".")
    if parts[0] != "morph_core":
        return None
    return parts[1] if len(parts) > 1 else "__init__"


def upward_imports(imports: list[Import], layers: dict[str, int]) -> list[str]:
    """The imports of a core module from a layer above its own, each with its file line."""
    found = []
    for i in imports:
        source, target = core_unit(i.source), core_unit(i.target)
        if source is not None and target is not None and layers[target] > layers[source]:
            found.append(
                f"{i.source} (layer {layers[source]}, {source}) imports {i.target} "
                f"(layer {layers[target]}, {target}), line {i.line}"
            )
    return found


def is_command_line(module: str) -> bool:
    """A command-line module of the trainer: ``trainer.cli`` and its modules, a room's ``cli``, a ``__main__``."""
    parts = module.split(".")
    return parts[0] == "trainer" and (parts[1:2] == ["cli"] or parts[-1] in ("cli", "__main__"))


def library_imports_of_command_lines(imports: list[Import]) -> list[str]:
    return [
        f"{i.source} imports {i.target} (line {i.line})"
        for i in imports
        if package_of(i.source) == "trainer" and not is_command_line(i.source) and is_command_line(i.target)
    ]


def forbidden(name: str, never: set[str]) -> bool:
    return name in never or ("ROS" in never and is_ros(name))


def test_the_parser_sees_every_kind_of_import():
    modules = workspace_modules()
    imports = all_imports(modules)
    assert len(modules) > 80 and {package_of(m) for m in modules} == {
        "morph_core", "morph_ros_util", "swimmer_sim_node", "morph_policy_node", "trainer",
    }  # fmt: skip
    # relative imports would resolve too, but the project has none; every kind it has is found:
    by_source = {}
    for i in imports:
        by_source.setdefault(i.source, []).append(i)
    # a module-level import of a workspace module, and an outside module's top-level name
    assert any(
        i.target == "morph_core.algo.trust_region" and i.at_import_time for i in by_source["morph_core.algo.ppo"]
    )
    assert any(i.target == "torch" for i in by_source["morph_core.algo.ppo"])
    # under TYPE_CHECKING: seen, but not at import time
    tree = [i for i in by_source["morph_core.env.render"] if i.target == "morph_core.policy.tree"]
    assert tree and not any(i.at_import_time for i in tree)
    assert [i.at_import_time for i in by_source["morph_core.env.render"] if i.target == "numpy"] == [True]
    # inside a function: seen, but not at import time
    robot = [i for i in by_source["morph_core.env.mjcf_body"] if i.target == "morph_core.env.mjcf_robot"]
    assert robot and not any(i.at_import_time for i in robot)


def test_no_import_loops():
    modules = workspace_modules()
    imports = all_imports(modules)
    graph: dict[str, list[str]] = {module: [] for module in modules}
    for i in imports:
        if i.target in modules and i.target not in graph[i.source]:
            graph[i.source].append(i.target)
    loops = [a_loop(component, imports) for component in strongly_connected(graph)]
    assert loops == [], "import loops:\n" + "\n".join(loops)


def test_the_packages_import_each_other_as_the_design_page_says():
    table = structure_table()
    modules = workspace_modules()
    assert set(table) == {package_of(m) for m in modules}, "docs/design.md's Structure table lists other packages"
    arrows: dict[tuple[str, str], Import] = {}
    for i in all_imports(modules):
        if i.target in modules and package_of(i.target) != package_of(i.source):
            arrows.setdefault((package_of(i.source), package_of(i.target)), i)
    stated = {(package, other) for package, row in table.items() for other in row["imports"]}
    undocumented = [
        f"{a} -> {b} ({i.source}, line {i.line})" for (a, b), i in sorted(arrows.items()) if (a, b) not in stated
    ]
    unused = [f"{a} -> {b}" for a, b in sorted(stated - set(arrows))]
    assert undocumented == [], "imports docs/design.md's Structure table does not list: " + ", ".join(undocumented)
    assert unused == [], "docs/design.md's Structure table lists imports no module makes: " + ", ".join(unused)


def test_no_package_imports_what_the_design_page_says_it_never_imports():
    table = structure_table()
    modules = workspace_modules()
    imports = all_imports(modules)
    assert "ROS" in table["morph_core"]["never imports"] and "torch" in table["morph_policy_node"]["never imports"]
    by_source: dict[str, list[Import]] = {}
    for i in imports:
        by_source.setdefault(i.source, []).append(i)
    offenders = []
    for module in modules:
        never = table[package_of(module)]["never imports"]
        # anywhere in its own source: a direct import, at any level
        for i in by_source.get(module, []):
            if forbidden(package_of(i.target), never):
                offenders.append(f"{module} imports {i.target} (line {i.line})")
        # at import time, through the workspace modules it loads (and the packages' __init__ on the way)
        parent = {module: None}
        queue = deque([module])
        while queue:
            node = queue.popleft()
            ancestors = [".".join(node.split(".")[:k]) for k in range(1, node.count(".") + 1)]
            loaded = [i.target for i in by_source.get(node, []) if i.at_import_time] + ancestors
            for target in loaded:
                if target in modules:
                    if target not in parent:
                        parent[target] = node
                        queue.append(target)
                elif forbidden(target, never) and node != module:
                    chain = [target, node]
                    while parent[chain[-1]] is not None:
                        chain.append(parent[chain[-1]])
                    offenders.append("importing " + " -> ".join(reversed(chain)))
    assert offenders == [], "\n".join(sorted(set(offenders)))


def test_the_cores_layers_point_down_as_the_design_page_says():
    layers = core_layers()
    modules = workspace_modules()
    units = {core_unit(m) for m in modules} - {None}
    assert units == set(layers), (
        f"docs/design.md's layers of the core list {sorted(set(layers) - units)} that do not exist and leave out "
        f"{sorted(units - set(layers))}"
    )
    assert layers["constants"] == 1 < layers["policy"] < layers["msgs"] < layers["env"] < layers["algo"]
    imports = all_imports(modules)
    # the check sees an upward import wherever it is: one inside a function of the bottom layer
    planted = Import("morph_core.constants", "morph_core.algo.train", 1, at_import_time=False)
    assert upward_imports([planted], layers) == [
        "morph_core.constants (layer 1, constants) imports morph_core.algo.train (layer 6, algo), line 1"
    ]
    assert any(not i.at_import_time for i in imports if core_unit(i.source) and core_unit(i.target))
    upward = upward_imports(imports, layers)
    assert upward == [], "imports from a layer above (docs/design.md, The core, module by module):\n" + "\n".join(
        upward
    )


def test_the_trainer_s_library_never_imports_its_command_lines():
    modules = workspace_modules()
    commands = sorted(m for m in modules if is_command_line(m))
    assert {
        "trainer.cli.train",
        "trainer.cli.eval",
        "trainer.bags.cli",
        "trainer.sweep.cli",
        "trainer.sweep.__main__",
    } <= set(commands)
    assert not is_command_line("trainer.live.bringup") and not is_command_line("trainer.client")
    planted = Import("trainer.live.bringup", "trainer.cli.train", 7, at_import_time=False)  # inside a function
    assert library_imports_of_command_lines([planted]) == ["trainer.live.bringup imports trainer.cli.train (line 7)"]
    offenders = library_imports_of_command_lines(all_imports(modules))
    assert offenders == [], "library modules that import a command line:\n" + "\n".join(offenders)


def _import_runs(body: list[ast.stmt]) -> list[list[ast.stmt]]:
    """The runs of consecutive import statements in one body of statements."""
    runs, run = [], []
    for stmt in body:
        if isinstance(stmt, ast.Import | ast.ImportFrom):
            run.append(stmt)
        elif run:
            runs, run = [*runs, run], []
    return [*runs, run] if run else runs


def unexplained_function_imports(path: Path) -> list[int]:
    """Lines that start a run of imports inside a function with no comment on it or on the line above: an
    import there hides an edge of the graph, so it needs its reason (an optional or heavy dependency, the
    order a library must load in)."""
    lines = path.read_text().splitlines()
    out = []
    for func in ast.walk(ast.parse(path.read_text())):
        if not isinstance(func, ast.FunctionDef | ast.AsyncFunctionDef):
            continue
        for node in ast.walk(func):
            for field in ("body", "orelse", "finalbody"):
                body = getattr(node, field, None)
                for run in _import_runs(body if isinstance(body, list) else []):
                    if not any("#" in text for text in lines[run[0].lineno - 2 : run[-1].end_lineno]):
                        out.append(run[0].lineno)
    return sorted(set(out))


def test_an_import_inside_a_function_says_why(tmp_path):
    planted = tmp_path / "planted.py"
    planted.write_text("def f():\n    import json\n\n    return json\n\n\ndef g():\n    # json only here\n"
                       "    import json\n\n    return json\n")  # fmt: skip
    assert unexplained_function_imports(planted) == [2]
    offenders = [f"{path.relative_to(ROOT)}:{line}" for path in workspace_modules().values()
                 for line in unexplained_function_imports(path)]  # fmt: skip
    assert offenders == [], "imports inside functions without a reason:\n" + "\n".join(offenders)
