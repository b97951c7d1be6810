"""The package's shape, as docs/architecture.md draws it: data flows one way and the imports say so.

The rules, each checked on the source (ast and tokens, nothing imported) except the hot loop's,
which imports it in a fresh interpreter and looks at what came along:

- no import cycle between the bridge's modules, lazy imports included (``TYPE_CHECKING`` blocks
  are for the type checker only);
- the pure layers (ESC codecs, mixing, the ESC state and its Zenoh schema, the safety decision)
  import no I/O layer: not the output loop, the daemon, the CLI or the configuration, at any
  depth of a function;
- the output loop's process imports nothing it does not run: no CLI, daemon (its supervisor,
  health reports, motor-test control), telemetry side (reader, state, publishers), monitor,
  simulator, demo, Zenoh or rich;
- nothing outside ``bridge/escs/`` names an ESC family: the families are found through
  ``bridge.escs.registry``;
- no family imports another: what two families share (the UAVCAN v0 framing, the driver
  protocol, the filters) is a module directly under ``bridge/escs/``.
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


def imports(module: str) -> set[str]:
    """Every bridge module ``module`` imports, at any depth (lazy imports in functions too:
    they close a cycle just the same once called), outside ``TYPE_CHECKING`` blocks."""
    tree = ast.parse(MODULES[module].read_text(encoding="utf-8"))
    found: set[str] = set()

    def visit(nodes: list[ast.stmt]) -> None:
        for node in nodes:
            if isinstance(node, ast.Import | ast.ImportFrom):
                found.update(_targets(module, node))
            elif not (isinstance(node, ast.If) and _is_type_checking(node)):
                for field in ("body", "orelse", "handlers", "finalbody"):
                    visit(getattr(node, field, []) or [])

    visit(tree.body)
    found.discard(module)
    return found


def test_no_module_imports_itself_back() -> None:
    graph = {m: imports(m) for m in MODULES}
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
    r"bridge\.(mixing(\..*)?|telemetry\.(state|payload|json_schema)|output\.safety"
    r"|can_errors|backoff"
    r"|escs\.(family|registry|uavcan_v0)"
    r"|escs\.\w+\.(_codec|_frame|_messages|_records|_services|_wire|codec|wire|telemetry))$"
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
    assert {"ckesc", "ft", "dronecan"} <= families
    assert family_of("bridge.escs.uavcan_v0") is None
    assert family_of("bridge.escs.family") is None


VENDOR = re.compile(r"ckesc|flipsky|dronecan|\bft(_\w+)?\b", re.IGNORECASE)


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
