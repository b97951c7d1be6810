"""Generate esc-bridge's MAVLink dialect module from ``esc_bridge.xml`` on first use, and load it.

Why generate at run time: pymavlink's bundled dialects lack ESC_INFO and ESC_STATUS, and
generated code must not live in the repository. The dialect XML ships as package data; mavgen
turns it into a Python module once per (XML content, pymavlink version) and the module is kept
in a cache directory, so a daemon start normally costs one import.

Where the cache is, first found wins:

1. ``$ESC_BRIDGE_CACHE``: the user's choice; an error if it cannot be written.
2. ``$CACHE_DIRECTORY``: what systemd sets for a unit's ``CacheDirectory=``
   (``/var/cache/esc-bridge`` for the shipped unit).
3. ``$XDG_CACHE_HOME/esc-bridge``, then ``~/.cache/esc-bridge``.

Without any of them, or when 2 or 3 cannot be written (a system user without a home, a
read-only home), the dialect is generated in memory instead: mavgen writes into a private
temporary directory that is removed at once, and the module runs from the source held in
memory. Nothing is left on disk, at the price of generating and compiling on every start
(0.5 to 0.8 s on a 2-core x86 at load 4, against 0.03 s from the cache and its bytecode).

Cache layout::

    <cache>/
    └── mavlink/
        ├── esc_bridge-<key>.py           the generated dialect; <key> = 16 hex digits of
        │                                 sha256(XML, pymavlink version, layout revision)
        ├── __pycache__/                  its bytecode, written with it
        └── .gen-*/                       a generation in progress (removed when it ends)

Each generation runs mavgen in a private temporary directory inside ``mavlink/`` and renames
the finished file into place, so a concurrent starter sees either no file or a whole one; two
processes that race both generate and the identical results replace each other harmlessly.
Files for older keys are left alone because another installed version may still use them.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import importlib.metadata
import importlib.util
import io
import logging
import os
import py_compile
import shutil
import sys
import tempfile
import threading
import time
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Final

from bridge.errors import BridgeError

__all__ = [
    "CACHE_ENV",
    "DIALECT_XML",
    "DialectError",
    "cache_root",
    "dialect_key",
    "generate_dialect",
    "install_dialect",
    "load_dialect",
    "stock_ardupilotmega_xml",
    "stock_dialects_dir",
]

log = logging.getLogger(__name__)

CACHE_ENV: Final = "ESC_BRIDGE_CACHE"
"""Environment variable naming the cache directory; overrides every other choice."""

SYSTEMD_CACHE_ENV: Final = "CACHE_DIRECTORY"
"""Set by systemd for a unit with ``CacheDirectory=``: the directories it made, ``:``-separated."""

DIALECT_XML: Final = "esc_bridge.xml"
"""The dialect file, shipped as package data of ``bridge.mavlink``."""

_BASE_INCLUDE: Final = "ardupilotmega.xml"
"""The include in our XML that means "the ardupilotmega.xml pymavlink installed"."""

_MODULE_STEM: Final = "esc_bridge"
"""mavgen names the dialect (its ``DIALECT`` constant) after the output file's stem."""

INSTALLED_NAME: Final = _MODULE_STEM
"""The dialect's name where stock pymavlink finds it: ``--dialect esc_bridge``."""

_LAYOUT_REVISION: Final = b"1"
"""Part of the cache key: bump it when this module changes what it feeds mavgen."""

_lock = threading.Lock()
_loaded: dict[tuple[str, Path | None], ModuleType] = {}  # by dialect key and cache root


class DialectError(BridgeError, RuntimeError):
    """The MAVLink dialect could not be generated, cached or imported.

    ``path`` is the file or directory involved; the message names it and the cause.
    """

    def __init__(self, message: str, path: Path) -> None:
        super().__init__(message)
        self.path = path


@dataclass(frozen=True)
class _WireMessage:
    """What decides a message's bytes and CRC_EXTRA: its name and its fields in XML order."""

    name: str
    fields: tuple[tuple[str, str, bool], ...]  # (C type, name, is an extension)


def cache_root() -> Path | None:
    """The cache directory: ``$ESC_BRIDGE_CACHE``, else systemd's ``$CACHE_DIRECTORY`` (its
    first entry), else ``$XDG_CACHE_HOME/esc-bridge``, else ``~/.cache/esc-bridge``; ``None``
    when none is set and there is no home directory. A relative ``XDG_CACHE_HOME`` is ignored,
    as the XDG spec says."""
    override = os.environ.get(CACHE_ENV)
    if override:
        return Path(override).expanduser()
    systemd = os.environ.get(SYSTEMD_CACHE_ENV, "").split(":")[0]
    if systemd:
        return Path(systemd)
    xdg = os.environ.get("XDG_CACHE_HOME")
    if xdg and Path(xdg).is_absolute():
        return Path(xdg) / "esc-bridge"
    try:
        return Path.home() / ".cache" / "esc-bridge"
    except RuntimeError:  # no $HOME and no home in the password database
        return None


def stock_ardupilotmega_xml() -> Path:
    """The ``ardupilotmega.xml`` of the installed pymavlink, which our dialect extends.

    Raises:
        DialectError: pymavlink is installed without its dialect XML files.
    """
    import pymavlink

    path = Path(pymavlink.__file__).resolve().parent / "dialects" / "v20" / _BASE_INCLUDE
    if not path.is_file():
        raise DialectError(f"pymavlink's dialect definition {path} is missing", path)
    return path


def _pymavlink_version() -> str:
    try:
        return importlib.metadata.version("pymavlink")
    except importlib.metadata.PackageNotFoundError:
        # A source checkout on sys.path has no distribution metadata; its module still knows.
        import pymavlink

        return str(getattr(pymavlink, "__version__", "unknown"))


def dialect_key(xml: bytes) -> str:
    """The cache key of a dialect XML: a change to the XML or to pymavlink regenerates."""
    digest = hashlib.sha256()
    for part in (_LAYOUT_REVISION, _pymavlink_version().encode(), xml):
        digest.update(len(part).to_bytes(8, "little"))
        digest.update(part)
    return digest.hexdigest()[:16]


def _include_tree(root: Path) -> list[tuple[Path, ET.Element]]:
    """``root`` and every file it includes, transitively, parsed (each file once)."""
    seen: set[Path] = set()
    parsed: list[tuple[Path, ET.Element]] = []
    pending = [root.resolve()]
    while pending:
        path = pending.pop()
        if path in seen:
            continue
        seen.add(path)
        try:
            element = ET.parse(path).getroot()
        except (OSError, ET.ParseError) as err:
            raise DialectError(f"cannot read MAVLink definition {path}: {err}", path) from err
        parsed.append((path, element))
        pending.extend(
            (path.parent / (inc.text or "").strip()).resolve() for inc in element.findall("include")
        )
    return parsed


def _wire_message(message: ET.Element) -> _WireMessage:
    fields: list[tuple[str, str, bool]] = []
    extension = False
    for child in message:
        if child.tag == "extensions":
            extension = True
        elif child.tag == "field":
            fields.append((child.get("type", ""), child.get("name", ""), extension))
    return _WireMessage(message.get("name", ""), tuple(fields))


def _drop_duplicates(own: ET.Element, own_path: Path, base: Path) -> None:
    """Remove from ``own`` what the base include tree already defines identically.

    mavgen refuses a message id or name defined twice, and an enum entry whose name or value
    is defined twice (enums of the same name are merged entry by entry). Once a pymavlink
    release bundles ESC_INFO, ESC_STATUS or their enums, our copies must step aside; if its
    definition differs from ours on the wire, generating would silently change our bytes, so
    that is an error instead.
    """
    messages: dict[str, tuple[str, _WireMessage, Path]] = {}  # by id and by name
    entries: dict[str, dict[str, tuple[int, Path]]] = {}  # enum name -> entry name -> value
    for path, root in _include_tree(base):
        for message in root.iter("message"):
            wire = _wire_message(message)
            msg_id = message.get("id", "")
            messages[msg_id] = messages[wire.name] = (msg_id, wire, path)
        for enum in root.iter("enum"):
            known = entries.setdefault(enum.get("name", ""), {})
            for entry in enum.findall("entry"):
                known[entry.get("name", "")] = (int(entry.get("value", "0"), 0), path)

    def conflict(what: str, theirs: Path) -> DialectError:
        return DialectError(
            f"{own_path}: {what} is already defined differently by {theirs} "
            f"(pymavlink {_pymavlink_version()}); the wire format would change",
            own_path,
        )

    for container in own.findall("messages"):
        for message in container.findall("message"):
            msg_id, wire = message.get("id", ""), _wire_message(message)
            found = messages.get(msg_id) or messages.get(wire.name)
            if found is None:
                continue
            their_id, their_wire, theirs = found
            if (their_id, their_wire) != (msg_id, wire):
                raise conflict(f"message {wire.name} ({msg_id})", theirs)
            log.info("pymavlink already defines %s (%s); using its definition", wire.name, msg_id)
            container.remove(message)
    for container in own.findall("enums"):
        for enum in container.findall("enum"):
            name = enum.get("name", "")
            known = entries.get(name, {})
            values = {value: entry for entry, (value, _) in known.items()}
            for entry in enum.findall("entry"):
                entry_name, value = entry.get("name", ""), int(entry.get("value", "0"), 0)
                if entry_name in known:
                    if known[entry_name][0] != value:
                        raise conflict(f"enum entry {name}.{entry_name}", known[entry_name][1])
                    enum.remove(entry)
                elif value in values:
                    raise conflict(f"value {value} of enum {name}", known[values[value]][1])
            if not enum.findall("entry"):
                log.info("pymavlink already defines enum %s; using its definition", name)
                container.remove(enum)
        if not container.findall("enum"):
            own.remove(container)


def _resolved_xml(own_xml: Path, base_xml: Path) -> bytes:
    """Our XML as mavgen must see it from a temporary directory: includes as absolute paths
    (the base include pointing at ``base_xml``) and duplicates of the base dropped."""
    try:
        root = ET.parse(own_xml).getroot()
    except (OSError, ET.ParseError) as err:
        raise DialectError(f"cannot read dialect definition {own_xml}: {err}", own_xml) from err
    for include in root.findall("include"):
        name = (include.text or "").strip()
        target = base_xml if name == _BASE_INCLUDE else own_xml.parent / name
        include.text = str(target.resolve())
    _drop_duplicates(root, own_xml, base_xml)
    resolved: bytes = ET.tostring(root, encoding="utf-8", xml_declaration=True)
    return resolved


def generate_dialect(own_xml: Path, dest: Path, *, base_xml: Path | None = None) -> None:
    """Run mavgen (MAVLink 2, Python 3) on ``own_xml`` and atomically create ``dest``.

    ``base_xml`` is what the ``ardupilotmega.xml`` include means; the installed pymavlink's
    by default. Tests pass the upstream one to check the duplicate handling.

    Raises:
        DialectError: reading the XML, a conflicting duplicate, mavgen's failure (its output
            is in the message), or a directory that cannot be written.
    """
    from pymavlink.generator import mavgen

    base = base_xml if base_xml is not None else stock_ardupilotmega_xml()
    resolved = _resolved_xml(own_xml, base)
    try:
        dest.parent.mkdir(parents=True, exist_ok=True)
        work = Path(tempfile.mkdtemp(prefix=".gen-", dir=dest.parent))
    except OSError as err:
        raise DialectError(
            f"cannot write the MAVLink dialect into {dest.parent}: {err}", dest.parent
        ) from err
    try:
        source = work / f"{_MODULE_STEM}.xml"
        output = work / f"{_MODULE_STEM}.py"
        source.write_bytes(resolved)
        opts = mavgen.Opts(str(output), wire_protocol="2.0", language="Python3")
        # mavgen reports on stdout/stderr and stops with exit(); keep both inside this call.
        chatter = io.StringIO()
        started = time.monotonic()
        try:
            with contextlib.redirect_stdout(chatter), contextlib.redirect_stderr(chatter):
                ok = mavgen.mavgen(opts, [str(source)])
        except (Exception, SystemExit) as err:
            report = f"{chatter.getvalue()}{type(err).__name__}: {err}"
            raise DialectError(_mavgen_failure(own_xml, source, report), own_xml) from err
        if not ok or not output.is_file():
            raise DialectError(_mavgen_failure(own_xml, source, chatter.getvalue()), own_xml)
        os.replace(output, dest)
        log.info("generated MAVLink dialect %s in %.2f s", dest, time.monotonic() - started)
    except OSError as err:
        raise DialectError(f"cannot write the MAVLink dialect {dest}: {err}", dest) from err
    finally:
        shutil.rmtree(work, ignore_errors=True)


def _mavgen_failure(own_xml: Path, source: Path, report: str) -> str:
    """mavgen's last words (it prints its reason just before giving up), naming our file.

    mavgen saw the resolved copy, which is deleted afterwards and lacks the comments, so its
    line numbers can be off by the length of the header comment.
    """
    tail = "\n".join(report.strip().splitlines()[-8:]).replace(str(source), f"{own_xml} (resolved)")
    return f"mavgen failed on {own_xml}:\n{tail}"


def _import_file(name: str, path: Path) -> ModuleType:
    spec = importlib.util.spec_from_file_location(name, path)
    if spec is None or spec.loader is None:
        raise DialectError(f"cannot import the MAVLink dialect {path}", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    try:
        spec.loader.exec_module(module)
    except BaseException:
        del sys.modules[name]
        raise
    return module


def load_dialect(*, xml: Path | None = None) -> ModuleType:
    """esc-bridge's MAVLink 2 dialect module: pymavlink's ardupilotmega plus ESC_INFO/ESC_STATUS.

    Generated into :func:`cache_root` on first use (about half a second), then imported from
    there; repeated calls in one process return the same module object. Thread-safe. Without
    a writable cache (and without ``$ESC_BRIDGE_CACHE``, which must be writable when set) it is
    generated in memory and has no ``__file__``. ``xml`` replaces the packaged
    ``esc_bridge.xml``, to try an edit (or, in tests, to prove that a changed XML regenerates)
    without touching the installed file.

    Raises:
        DialectError: the dialect could not be generated, written or imported; the message
            names the path and the cause.
    """
    own_xml = xml if xml is not None else Path(__file__).with_name(DIALECT_XML)
    try:
        content = own_xml.read_bytes()
    except OSError as err:
        raise DialectError(f"cannot read dialect definition {own_xml}: {err}", own_xml) from err
    key = dialect_key(content)
    name = f"_esc_bridge_dialect_{key}"
    root = cache_root()
    with _lock:
        module = _loaded.get((key, root))
        if module is None:
            module = _from_cache(own_xml, root, name, key) or _in_memory(own_xml, name)
            _loaded[key, root] = module
        return module


def _from_cache(own_xml: Path, root: Path | None, name: str, key: str) -> ModuleType | None:
    """The dialect imported from the cache ``root``, generated there first if need be; ``None``
    when there is no cache directory or it cannot be written (unless ``$ESC_BRIDGE_CACHE`` named
    it: then that is an error)."""
    if root is None:
        log.info("no cache directory for the MAVLink dialect (no home directory)")
        return None
    directory = root / "mavlink"
    dest = directory / f"{_MODULE_STEM}-{key}.py"
    if dest.is_file():
        if not Path(importlib.util.cache_from_source(str(dest))).is_file():
            _write_bytecode(dest)  # a cache from before its bytecode was written with it
        try:
            return _import_file(name, dest)
        # A damaged cache file (disk full, a hand edit) should cost a rebuild, not a start.
        except (SyntaxError, ValueError, ImportError, NameError, AttributeError) as err:
            log.warning("regenerating damaged MAVLink dialect %s: %s", dest, err)
    try:
        directory.mkdir(parents=True, exist_ok=True)
        if not os.access(directory, os.W_OK | os.X_OK):
            raise PermissionError(errno.EACCES, "not writable", str(directory))
    except OSError as err:
        if os.environ.get(CACHE_ENV):
            raise DialectError(
                f"cannot write the MAVLink dialect cache {directory} (set {CACHE_ENV} to a "
                f"writable directory): {err}",
                directory,
            ) from err
        log.info("cannot write the MAVLink dialect cache %s: %s", directory, err)
        return None
    generate_dialect(own_xml, dest)
    _write_bytecode(dest)
    return _import_generated(name, dest)


def _write_bytecode(dest: Path) -> None:
    """The cached dialect's bytecode, in its ``__pycache__``, written whether or not Python
    writes bytecode on import: the module is over two megabytes of generated Python, which every
    process that imports it (the main process and the control loop's, at every start) would
    otherwise compile again where Python writes none (``PYTHONDONTWRITEBYTECODE``, as container
    images often set). Best effort: without it the import compiles the source, as before."""
    try:
        py_compile.compile(str(dest), doraise=True)
    except (OSError, py_compile.PyCompileError) as err:
        log.info("cannot write the MAVLink dialect's bytecode beside %s: %s", dest, err)


def _in_memory(own_xml: Path, name: str) -> ModuleType:
    """The dialect generated and run without leaving a file: mavgen writes into a private
    temporary directory, removed before the module runs from the source read back."""
    started = time.monotonic()
    try:
        with tempfile.TemporaryDirectory(prefix="esc-bridge-dialect-") as work:
            generated = Path(work) / f"{_MODULE_STEM}.py"
            generate_dialect(own_xml, generated)
            source = generated.read_text(encoding="utf-8")
    except OSError as err:
        raise DialectError(
            f"cannot generate the MAVLink dialect: no writable cache and no temporary "
            f"directory ({err}); set {CACHE_ENV} to a writable directory",
            Path(tempfile.gettempdir()),
        ) from err
    module = ModuleType(name)
    sys.modules[name] = module
    try:
        exec(compile(source, f"<{_MODULE_STEM} dialect, in memory>", "exec"), module.__dict__)
    except Exception as err:
        del sys.modules[name]
        raise DialectError(
            f"cannot import the MAVLink dialect generated in memory: {err}", own_xml
        ) from err
    log.info(
        "generated the MAVLink dialect in memory in %.2f s (no writable cache: set %s or run "
        "under systemd with CacheDirectory= to keep it between starts)",
        time.monotonic() - started,
        CACHE_ENV,
    )
    return module


def _import_generated(name: str, path: Path) -> ModuleType:
    try:
        return _import_file(name, path)
    except Exception as err:
        raise DialectError(
            f"cannot import the generated MAVLink dialect {path}: {err}", path
        ) from err


def stock_dialects_dir() -> Path:
    """The installed pymavlink's ``dialects/v20`` directory, where ``mavutil.set_dialect``,
    MAVProxy's and mavlogdump's ``--dialect`` and ``MAVLINK_DIALECT`` look (MAVLink 2)."""
    return stock_ardupilotmega_xml().parent


def install_dialect(into: Path | None = None) -> Path:
    """Put the dialect (generated as for :func:`load_dialect`) where stock pymavlink finds it:
    ``esc_bridge.py`` in ``into``, by default :func:`stock_dialects_dir`. Returns the file.

    Stock pymavlink, MAVProxy and mavlogdump then decode ESC_INFO/ESC_STATUS with
    ``--dialect esc_bridge`` or ``MAVLINK_DIALECT=esc_bridge`` (with ``MAVLINK20=1``, which
    MAVProxy and mavlogdump set themselves). A reinstalled or upgraded pymavlink loses it.

    Raises:
        DialectError: the dialect could not be generated, or ``into`` is no directory or
            cannot be written (the message names it).
    """
    target_dir = into if into is not None else stock_dialects_dir()
    if not (target_dir / "__init__.py").is_file():
        raise DialectError(
            f"{target_dir} is not a pymavlink dialects directory (no __init__.py there): "
            "give a pymavlink installation's pymavlink/dialects/v20",
            target_dir,
        )
    dest = target_dir / f"{INSTALLED_NAME}.py"
    # Generated straight into place (atomically: mavgen works in a temporary directory beside
    # it), so the step needs no cache.
    generate_dialect(Path(__file__).with_name(DIALECT_XML), dest)
    try:
        os.chmod(dest, 0o644)  # readable by every user of a system-wide pymavlink
    except OSError as err:
        raise DialectError(f"cannot install the MAVLink dialect into {dest}: {err}", dest) from err
    log.info("installed MAVLink dialect %s", dest)
    return dest
