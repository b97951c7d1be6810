"""The package's shape, as docs/architecture.md draws it: data flows one way and the imports say so.

The rules, each checked on the source (ast and tokens, nothing imported) except the hot loop's,
which imports it in a fresh interpreter and looks at what came along:

- no import cycle between the bridge's modules, lazy imports included, and none either once the
  imports only the type checker follows (``TYPE_CHECKING`` blocks) are counted;
- the pure layers (ESC codecs, mixing, the ESC state and its Zenoh schema, the safety decision,
  the web monitor's page model) import no I/O layer: not the output loop, the daemon, the CLI
  or the configuration, at any depth of a function;
- the ESC families' layer (``bridge/escs/``) imports nothing above it, type-only imports
  included: a family gets its own keys and the few common values it needs, not the
  configuration;
- the output loop's process imports nothing it does not run: no CLI, daemon (its supervisor,
  health reports, motor-test control), telemetry side (reader, state, publishers), monitor,
  simulator, demo, Zenoh or rich;
- nothing outside ``bridge/escs/`` names an ESC family: the families are found through
  ``bridge.escs.registry``;
- no family imports another: what two families share (the UAVCAN v0 framing, the driver
  helpers, the filters) is a module directly under ``bridge/escs/``;
- the interface a family implements stays narrow (:data:`FAMILY_MEMBERS`), and every family
  implements exactly it, no stubs and no extras;
- no module imports another's private names (``_name``), and a private module (``_name.py``) is
  imported only from within its own package;
- nothing under ``bridge/`` is there only for the tests or the benches: every public function
  and class is used by the bridge itself (or is an entry point).
"""

from __future__ import annotations

import ast
import io
import re
import subprocess
import sys
import tokenize
from collections.abc import Iterator
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGE = ROOT / "bridge"


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


MODULES: dict[str, Path] = {module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}


def _is_type_checking(node: ast.If) -> bool:
    test = node.test
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _targets(module: str, node: ast.Import | ast.ImportFrom) -> Iterator[str]:
    """The bridge modules an import statement loads (``from a import b``: ``a.b`` when that is
    a module, else ``a``)."""
    if isinstance(node, ast.Import):
        names = [alias.name for alias in node.names]
    else:
        if node.level:
            package = module.split(".")
            if MODULES[module].name != "__init__.py":
                package = package[:-1]
            base = ".".join(package[: len(package) - node.level + 1])
            base = f"{base}.{node.module}" if node.module else base
        else:
            base = node.module or ""
        names = [f"{base}.{a.name}" if f"{base}.{a.name}" in MODULES else base for a in node.names]
    for name in names:
        while name and name not in MODULES:
            name = name.rpartition(".")[0]
        if name.startswith("bridge"):
            yield name


def imports(module: str, *, type_checking: bool = False) -> set[str]:
    """Every bridge module ``module`` imports, at any depth (lazy imports in functions too:
    they close a cycle just the same once called); with ``type_checking``, those of
    ``TYPE_CHECKING`` blocks too (imports for the type checker only)."""
    tree = ast.parse(MODULES[module].read_text(encoding="utf-8"))
    found: set[str] = set()

    def visit(nodes: list[ast.stmt]) -> None:
        for node in nodes:
            if isinstance(node, ast.Import | ast.ImportFrom):
                found.update(_targets(module, node))
            elif type_checking or not (isinstance(node, ast.If) and _is_type_checking(node)):
                for field in ("body", "orelse", "handlers", "finalbody"):
                    visit(getattr(node, field, []) or [])

    visit(tree.body)
    found.discard(module)
    return found


@pytest.mark.parametrize("type_checking", [False, True], ids=["run", "type-checking"])
def test_no_module_imports_itself_back(type_checking: bool) -> None:
    graph = {m: imports(m, type_checking=type_checking) for m in MODULES}
    cycles: list[list[str]] = []
    state: dict[str, int] = {}  # 1: on the path, 2: done

    def walk(node: str, path: list[str]) -> None:
        state[node] = 1
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                cycles.append([*path[path.index(nxt) :], nxt])
            elif nxt not in state:
                walk(nxt, [*path, nxt])
        state[node] = 2

    for module in MODULES:
        if module not in state:
            walk(module, [module])
    assert cycles == [], "import cycles:\n" + "\n".join(" -> ".join(c) for c in cycles)


PURE = re.compile(
    r"bridge\.(mixing(\..*)?|telemetry\.(state|payload|json_schema|mcap_channels)|output\.safety"
    r"|monitor\.web\.model"
    r"|can_errors|backoff"
    r"|escs\.(family|registry|uavcan_v0)"
    r"|escs\.\w+\.(records|layout|messages|services|codec|wire|telemetry))$"
)
"""The pure layers: no I/O of their own, so they run (and are tested) anywhere."""
IO_LAYERS = re.compile(r"bridge\.(output(\..*)?|daemon(\..*)?|cli(\..*)?|config|config_file)$")


@pytest.mark.parametrize("module", sorted(m for m in MODULES if PURE.match(m)))
def test_pure_layers_import_no_io_layer(module: str) -> None:
    reached = {m for m in imports(module) if IO_LAYERS.match(m)}
    assert reached == set(), f"{module} imports {sorted(reached)}"


def test_there_are_pure_layers_to_check() -> None:
    pure = {m for m in MODULES if PURE.match(m)}
    assert {"bridge.telemetry.state", "bridge.telemetry.payload", "bridge.escs.family"} <= pure
    assert "bridge.output.safety" in pure
    assert any(m.startswith("bridge.escs.ckesc.") for m in pure)
    assert any(m.startswith("bridge.mixing") for m in pure)


HOT_LOOP = "bridge.output.output_loop"
NOT_ON_THE_HOT_LOOP = re.compile(
    r"^(bridge\.(cli|daemon|demo|monitor|sim|telemetry"
    r"|mavlink\.telemetry_out)"
    r"|zenoh|rich|matplotlib|dronecan)(\.|$)"
)


def test_the_hot_loop_imports_nothing_it_does_not_run() -> None:
    probe = f"import sys, {HOT_LOOP}; print('\\n'.join(sorted(sys.modules)))"
    loaded = subprocess.run(
        [sys.executable, "-c", probe], cwd=ROOT, capture_output=True, text=True, check=True
    ).stdout.split()
    assert HOT_LOOP in loaded
    assert [m for m in loaded if NOT_ON_THE_HOT_LOOP.match(m)] == []


FAMILY = re.compile(r"bridge\.escs\.(\w+)\.")
"""A module in a family's folder: ``bridge.escs.<family>.<module>`` (group 1 the family)."""


def family_of(module: str) -> str | None:
    """The family whose folder holds ``module`` (its package ``__init__`` included), or None
    for a module directly under ``bridge/escs/`` or outside it."""
    found = FAMILY.match(module + ".")
    return found.group(1) if found and f"bridge.escs.{found.group(1)}" in PACKAGES else None


PACKAGES = {m for m, p in MODULES.items() if p.name == "__init__.py"}


def test_no_family_imports_another() -> None:
    crossing = [
        f"{module} imports {target}"
        for module in MODULES
        if (family := family_of(module)) is not None
        for target in sorted(imports(module))
        if family_of(target) not in (None, family)
    ]
    assert crossing == []


def test_every_family_folder_is_seen() -> None:
    families = {family_of(m) for m in MODULES} - {None}
    assert {"ckesc", "ft", "dronecan", "vesc"} <= families
    assert family_of("bridge.escs.uavcan_v0") is None
    assert family_of("bridge.escs.family") is None


VENDOR = re.compile(r"ckesc|flipsky|dronecan|vesc|\bft(_\w+)?\b", re.IGNORECASE)


HELP_KEYWORDS = {"help", "description", "epilog"}


def vendor_mentions(path: Path) -> list[str]:
    """Names and string literals (docstrings included) that name a family. Comments may, and
    so may the CLI's help texts (``help=``, ``description=``, ``epilog=``), which describe the
    families to the user and stay as they were."""
    found = []
    previous: list[tokenize.TokenInfo] = []
    in_help = False
    tokens = tokenize.generate_tokens(io.StringIO(path.read_text(encoding="utf-8")).readline)
    for token in tokens:
        if token.type == tokenize.STRING:
            if len(previous) >= 2 and previous[-1].string == "=":
                in_help = previous[-2].string in HELP_KEYWORDS
            if not in_help and VENDOR.search(token.string):
                found.append(f"{path.relative_to(ROOT)}:{token.start[0]}: {token.string[:60]}")
        elif token.type == tokenize.NAME and VENDOR.search(token.string):
            found.append(f"{path.relative_to(ROOT)}:{token.start[0]}: {token.string}")
        if token.type not in (tokenize.STRING, tokenize.NL, tokenize.COMMENT):
            in_help = False
            previous = [*previous[-1:], token]
    return found


def test_nothing_outside_escs_names_a_family() -> None:
    outside = [p for m, p in MODULES.items() if not m.startswith("bridge.escs")]
    assert [hit for p in outside for hit in vendor_mentions(p)] == []


BELOW_THE_FAMILIES = re.compile(
    r"bridge\.(escs(\..*)?|errors|config_checks|bitrate|_compat|sim\.(base|motor))$"
)
"""What a family may import: its own layer, the errors, the key validators (and the bit rates
they read), the standard library's backports, and the simulated ESC's base and motor."""


@pytest.mark.parametrize("module", sorted(m for m in MODULES if m.startswith("bridge.escs")))
def test_the_family_layer_imports_nothing_above_it(module: str) -> None:
    above = {m for m in imports(module, type_checking=True) if not BELOW_THE_FAMILIES.match(m)}
    assert above == set(), f"{module} imports {sorted(above)}"


FAMILY_MEMBERS = frozenset(
    {
        "name",
        "title",
        "node_ids",
        "default_rate_hz",
        "default_bitrate",
        "keys",
        "owns",
        "decoder",
        "reader_filters",
        "check",
        "driver",
        "bus_figures",
    }
)
"""What the core needs of a family (bridge/escs/family.py): a dozen members. The simulator,
set-up commands and ID learning are the family's tool modules, not members."""


def _members(tree: ast.Module, class_name: str) -> set[str]:
    """The attributes and methods a class defines in its body (not ``__init__``, not private)."""
    body = next(n for n in tree.body if isinstance(n, ast.ClassDef) and n.name == class_name).body
    names = set()
    for node in body:
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            names.add(node.name)
        elif isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            names.add(node.target.id)
        elif isinstance(node, ast.Assign):
            names.update(t.id for t in node.targets if isinstance(t, ast.Name))
    return {n for n in names if not n.startswith("_")}


def test_the_family_interface_is_narrow() -> None:
    tree = ast.parse(MODULES["bridge.escs.family"].read_text(encoding="utf-8"))
    assert _members(tree, "EscFamily") == FAMILY_MEMBERS


def _registered_families() -> dict[str, tuple[str, str]]:
    """name -> (module, class) of every family in the registry, read from its source."""
    tree = ast.parse(MODULES["bridge.escs.registry"].read_text(encoding="utf-8"))
    table = next(
        n.value
        for n in tree.body
        if isinstance(n, ast.AnnAssign)
        and isinstance(n.target, ast.Name)
        and n.target.id == "FAMILIES"
    )
    assert isinstance(table, ast.Dict)
    found = {}
    for key, value in zip(table.keys, table.values, strict=True):
        assert isinstance(key, ast.Constant) and isinstance(value, ast.Constant)
        module, _, class_name = str(value.value).partition(":")
        found[str(key.value)] = (module, class_name)
    return found


@pytest.mark.parametrize("family", sorted(_registered_families()))
def test_every_family_implements_exactly_the_interface(family: str) -> None:
    module, class_name = _registered_families()[family]
    tree = ast.parse(MODULES[module].read_text(encoding="utf-8"))
    assert _members(tree, class_name) == FAMILY_MEMBERS


def private_imports(module: str) -> list[str]:
    """Private names ``module`` imports from another module (``from x import _y``), and private
    modules (``_x.py``) it imports from outside their package."""
    tree = ast.parse(MODULES[module].read_text(encoding="utf-8"))
    found = []
    for node in ast.walk(tree):
        if not isinstance(node, ast.Import | ast.ImportFrom):
            continue
        if isinstance(node, ast.ImportFrom) and node.module != "__future__":
            found += [
                f"{node.module}.{a.name}"
                for a in node.names
                if a.name.startswith("_") and not a.name.startswith("__")
            ]
        for target in _targets(module, node):
            package, _, name = target.rpartition(".")
            if name.startswith("_") and not (module + ".").startswith(package + "."):
                found.append(target)
    return found


def test_no_module_imports_another_s_private_names() -> None:
    found = {m: private_imports(m) for m in MODULES}
    assert {m: names for m, names in found.items() if names} == {}


def _defined(tree: ast.Module) -> list[str]:
    """The public functions and classes a module defines at its top level."""
    return [
        n.name
        for n in tree.body
        if isinstance(n, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef)
        and not n.name.startswith("_")
    ]


def _used(tree: ast.Module) -> set[str]:
    """Every name a module reads: names, attributes, imported names and the attribute names it
    looks up by string (``getattr(tool, "simulators")``)."""
    used = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Name) and not isinstance(node.ctx, ast.Store):
            used.add(node.id)
        elif isinstance(node, ast.Attribute):
            used.add(node.attr)
        elif isinstance(node, ast.ImportFrom):
            used.update(a.name for a in node.names)
        elif (
            isinstance(node, ast.Call)
            and isinstance(node.func, ast.Name)
            and node.func.id in ("getattr", "hasattr")
            and len(node.args) >= 2
            and isinstance(node.args[1], ast.Constant)
        ):
            used.add(str(node.args[1].value))
    return used


def test_nothing_in_the_package_is_there_only_for_tests_or_benches() -> None:
    """Every public function and class of ``bridge/`` is used somewhere in ``bridge/``: what
    only the tests or the benches use belongs with them. Entry points are used from outside:
    the command (pyproject's ``[project.scripts]``) and the families (the registry's table)."""
    trees = {m: ast.parse(p.read_text(encoding="utf-8")) for m, p in MODULES.items()}
    used = set().union(*(_used(tree) for tree in trees.values()))
    entry_points = {"main"} | {cls for _, cls in _registered_families().values()}
    unused = [
        f"{module}.{name}"
        for module, tree in trees.items()
        for name in _defined(tree)
        if name not in used and name not in entry_points
    ]
    assert unused == []
