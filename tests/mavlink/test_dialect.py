"""bridge.mavlink: our generated dialect speaks ESC_INFO/ESC_STATUS exactly as upstream MAVLink.

Everything here runs the real mavgen into temporary directories (no mocks). The cross-checks
against a dialect generated from the upstream XML in ``../shared/mavlink`` are what make our
hand-written XML trustworthy: same message ids, same CRC_EXTRA and the same bytes both ways.
"""

from __future__ import annotations

import contextlib
import importlib.util
import io
import logging
import math
import os
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest
from pymavlink.dialects.v20 import ardupilotmega as stock
from pymavlink.generator import mavgen

import bridge.mavlink._dialect as dialect_impl
from bridge.errors import BridgeError
from bridge.mavlink import (
    CACHE_ENV,
    DialectError,
    cache_root,
    dialect_key,
    generate_dialect,
    load_dialect,
)

OWN_XML = Path(dialect_impl.__file__).with_name("esc_bridge.xml")
UPSTREAM = Path(__file__).resolve().parents[3] / "shared" / "mavlink"
needs_upstream = pytest.mark.skipif(
    not (UPSTREAM / "ardupilotmega.xml").is_file(),
    reason=f"upstream MAVLink XML not found at {UPSTREAM}; wire cross-checks need it",
)

# The wire facts the whole point of the dialect rests on: (message id, CRC_EXTRA).
EXPECTED_WIRE = {
    "ESC_INFO": (290, 251),
    "ESC_STATUS": (291, 10),
    "ESC_TELEMETRY_1_TO_4": (11030, 144),
}

# Non-trivial values: every array slot distinct, extremes of each type, negative rpm and
# temperature, floats exactly representable in float32 so equality is exact after a round trip.
ESC_INFO_ARGS: dict[str, Any] = {
    "index": 4,
    "time_usec": 1_700_000_000_123_456,
    "counter": 65_000,
    "count": 8,
    "connection_type": 4,  # ESC_CONNECTION_TYPE_CAN
    "info": 0b1011,
    "failure_flags": [0, 1 | 4, 64, 0x7F],
    "error_count": [0, 1, 70_000, 4_294_967_295],
    "temperature": [2_500, -1_000, 32_767, -32_768],
}
ESC_STATUS_ARGS: dict[str, Any] = {
    "index": 0,
    "time_usec": 123_456_789,
    "rpm": [12_000, -8_500, 0, -2_147_483_648],
    "voltage": [16.5, 16.25, 0.0, 25.125],
    "current": [12.75, -0.5, 0.0, 80.0],
}
ESC_TELEMETRY_ARGS: dict[str, Any] = {
    "temperature": [30, 255, 0, 45],
    "voltage": [1_650, 1_625, 65_535, 0],
    "current": [1_275, 0, 300, 9_999],
    "totalcurrent": [120, 0, 65_535, 7],
    "rpm": [42_000, 0, 1, 65_535],
    "count": [1, 2, 3, 65_535],
}
MESSAGES = {
    "ESC_INFO": ESC_INFO_ARGS,
    "ESC_STATUS": ESC_STATUS_ARGS,
    "ESC_TELEMETRY_1_TO_4": ESC_TELEMETRY_ARGS,
}


def import_file(name: str, path: Path) -> ModuleType:
    spec = importlib.util.spec_from_file_location(name, path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def message_class(dialect: ModuleType, name: str) -> Any:
    return getattr(dialect, f"MAVLink_{name.lower()}_message")


def pack(dialect: ModuleType, name: str, args: dict[str, Any]) -> bytes:
    """One MAVLink 2 frame from a fresh sender, so sequence numbers agree between dialects."""
    mav = dialect.MAVLink(None, srcSystem=42, srcComponent=7)
    message = getattr(mav, f"{name.lower()}_encode")(**args)
    return bytes(message.pack(mav))


def decode(dialect: ModuleType, frame: bytes) -> Any:
    return dialect.MAVLink(None).decode(bytearray(frame))


def assert_fields(message: Any, args: dict[str, Any]) -> None:
    for field, expected in args.items():
        got = getattr(message, field)
        assert (list(got) if isinstance(expected, list) else got) == expected, field


@pytest.fixture(autouse=True)
def fresh_memo() -> Iterator[None]:
    """load_dialect() keeps modules per process; clear that so each test sees the disk cache."""
    dialect_impl._loaded.clear()
    yield
    dialect_impl._loaded.clear()


@pytest.fixture(scope="module")
def own(tmp_path_factory: pytest.TempPathFactory) -> ModuleType:
    """Our dialect, generated once for the module through the public entry point."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv(CACHE_ENV, str(tmp_path_factory.mktemp("cache")))
        return load_dialect()


@pytest.fixture(scope="module")
def upstream(tmp_path_factory: pytest.TempPathFactory) -> ModuleType:
    """A dialect from upstream's ardupilotmega.xml, generated the way the shared README says."""
    if not (UPSTREAM / "ardupilotmega.xml").is_file():
        pytest.skip(f"upstream MAVLink XML not found at {UPSTREAM}")
    output = tmp_path_factory.mktemp("upstream") / "upstream_ardupilotmega.py"
    opts = mavgen.Opts(str(output), wire_protocol="2.0", language="Python3")
    with contextlib.redirect_stdout(io.StringIO()):
        assert mavgen.mavgen(opts, [str(UPSTREAM / "ardupilotmega.xml")])
    return import_file("upstream_ardupilotmega_for_tests", output)


# --- our dialect on its own ----------------------------------------------------------------


@pytest.mark.parametrize("name", sorted(MESSAGES))
def test_round_trip(own: ModuleType, name: str) -> None:
    frame = pack(own, name, MESSAGES[name])
    message = decode(own, frame)
    assert message.get_type() == name
    assert_fields(message, MESSAGES[name])


@pytest.mark.parametrize("name", sorted(EXPECTED_WIRE))
def test_ids_and_crc_extra(own: ModuleType, name: str) -> None:
    msg_id, crc_extra = EXPECTED_WIRE[name]
    cls = message_class(own, name)
    assert (cls.id, cls.crc_extra) == (msg_id, crc_extra)
    assert own.mavlink_map[msg_id] is cls


def test_enums_and_wire_version(own: ModuleType) -> None:
    assert own.WIRE_PROTOCOL_VERSION == "2.0"
    assert own.DIALECT == "esc_bridge"
    assert own.ESC_CONNECTION_TYPE_CAN == 4
    assert own.ESC_CONNECTION_TYPE_DSHOT == 5
    assert own.ESC_FAILURE_MOTOR_STUCK == 32
    assert own.ESC_FAILURE_GENERIC == 64
    # Everything of pymavlink's ardupilotmega is still there (the include worked).
    assert set(stock.mavlink_map) < set(own.mavlink_map)
    assert set(own.mavlink_map) - set(stock.mavlink_map) == {290, 291}


def test_stock_receiver_sees_unknown(own: ModuleType) -> None:
    """Why the project carries its own dialect: pymavlink 2.4.50's cannot name these."""
    for name in ("ESC_INFO", "ESC_STATUS"):
        frame = pack(own, name, MESSAGES[name])
        message = stock.MAVLink(None).parse_char(bytearray(frame))
        assert message is not None
        assert message.get_type() == f"UNKNOWN_{EXPECTED_WIRE[name][0]}"


# --- wire compatibility with upstream -------------------------------------------------------


@needs_upstream
@pytest.mark.parametrize("name", sorted(EXPECTED_WIRE))
def test_same_id_and_crc_extra_as_upstream(
    own: ModuleType, upstream: ModuleType, name: str
) -> None:
    ours, theirs = message_class(own, name), message_class(upstream, name)
    assert (ours.id, ours.crc_extra) == (theirs.id, theirs.crc_extra) == EXPECTED_WIRE[name]
    assert ours.fieldnames == theirs.fieldnames
    assert ours.fieldtypes == theirs.fieldtypes
    assert ours.array_lengths == theirs.array_lengths
    assert ours.ordered_fieldnames == theirs.ordered_fieldnames
    assert ours.unpacker.format == theirs.unpacker.format
    assert ours.instance_field == theirs.instance_field


@needs_upstream
@pytest.mark.parametrize("name", sorted(MESSAGES))
def test_same_bytes_both_ways(own: ModuleType, upstream: ModuleType, name: str) -> None:
    args = MESSAGES[name]
    ours, theirs = pack(own, name, args), pack(upstream, name, args)
    assert ours == theirs
    for receiver, frame in ((upstream, ours), (own, theirs)):
        message = decode(receiver, frame)
        assert message.get_type() == name
        assert_fields(message, args)


@needs_upstream
def test_unset_temperature_and_nan_survive(own: ModuleType, upstream: ModuleType) -> None:
    """INT16_MAX ("not reported") and NaN floats travel unchanged between the two dialects."""
    info = dict(ESC_INFO_ARGS, temperature=[32_767] * 4)
    assert pack(own, "ESC_INFO", info) == pack(upstream, "ESC_INFO", info)
    status = dict(ESC_STATUS_ARGS, voltage=[math.nan] * 4)
    frame = pack(own, "ESC_STATUS", status)
    assert frame == pack(upstream, "ESC_STATUS", status)
    assert all(math.isnan(v) for v in decode(upstream, frame).voltage)


@needs_upstream
def test_definitions_already_in_base_step_aside(tmp_path: Path) -> None:
    """Upstream ardupilotmega already has ESC_INFO/ESC_STATUS and both enums, as a future
    pymavlink will: our copies are dropped instead of making mavgen fail on duplicates."""
    dest = tmp_path / "esc_bridge.py"
    generate_dialect(OWN_XML, dest, base_xml=UPSTREAM / "ardupilotmega.xml")
    module = import_file("esc_bridge_on_upstream_base", dest)
    for name, (msg_id, crc_extra) in EXPECTED_WIRE.items():
        assert (message_class(module, name).id, message_class(module, name).crc_extra) == (
            msg_id,
            crc_extra,
        )
    assert module.ESC_FAILURE_GENERIC == 64


@needs_upstream
def test_base_that_differs_on_the_wire_is_refused(tmp_path: Path) -> None:
    changed = tmp_path / "esc_bridge.xml"
    changed.write_text(
        OWN_XML.read_text().replace('type="int32_t[4]" name="rpm"', 'type="uint32_t[4]" name="rpm"')
    )
    with pytest.raises(DialectError, match=r"ESC_STATUS \(291\).*defined differently"):
        generate_dialect(changed, tmp_path / "out.py", base_xml=UPSTREAM / "ardupilotmega.xml")


# --- the cache --------------------------------------------------------------------------


def test_second_load_reuses_cache(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    monkeypatch.setenv(CACHE_ENV, str(tmp_path))
    caplog.set_level(logging.INFO, logger=dialect_impl.__name__)
    first = load_dialect()
    assert load_dialect() is first  # same process: the very same module
    path = Path(first.__file__ or "")
    assert path.parent == tmp_path / "mavlink"
    assert path.name == f"esc_bridge-{dialect_key(OWN_XML.read_bytes())}.py"
    stamp = path.stat().st_mtime_ns, path.stat().st_ino
    generated = [r for r in caplog.records if r.getMessage().startswith("generated")]
    assert len(generated) == 1

    dialect_impl._loaded.clear()  # as a new process would start
    second = load_dialect()
    assert second is not first
    assert Path(second.__file__ or "") == path
    assert (path.stat().st_mtime_ns, path.stat().st_ino) == stamp
    assert len([r for r in caplog.records if r.getMessage().startswith("generated")]) == 1
    assert second.MAVLink_esc_info_message.crc_extra == 251
    # Nothing but the module (and perhaps bytecode) is left: no temporary directories.
    assert {p.name for p in path.parent.iterdir()} <= {path.name, "__pycache__"}


def test_processes_starting_together_share_one_cache(tmp_path: Path) -> None:
    """Both generate or one reuses; neither may import a half-written module."""
    script = (
        "from bridge.mavlink import load_dialect\n"
        "m = load_dialect()\n"
        "print(m.__file__, m.MAVLink_esc_info_message.crc_extra)\n"
    )
    env = dict(os.environ, **{CACHE_ENV: str(tmp_path)})
    starters = [
        subprocess.Popen([sys.executable, "-c", script], env=env, stdout=subprocess.PIPE, text=True)
        for _ in range(3)
    ]
    outputs = [starter.communicate(timeout=60)[0].split() for starter in starters]
    assert [starter.returncode for starter in starters] == [0, 0, 0]
    assert len({path for path, _ in outputs}) == 1
    assert {crc for _, crc in outputs} == {"251"}
    assert [p.name for p in (tmp_path / "mavlink").iterdir() if p.name.startswith(".gen-")] == []


def test_changed_xml_regenerates(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(CACHE_ENV, str(tmp_path / "cache"))
    xml = tmp_path / "esc_bridge.xml"
    shutil.copy(OWN_XML, xml)
    first = Path(load_dialect(xml=xml).__file__ or "")
    stamp = first.stat().st_mtime_ns

    # A real change: one more message, which only a regenerated module can know.
    xml.write_text(
        xml.read_text().replace(
            "  </messages>",
            '    <message id="42290" name="ESC_BRIDGE_PROBE">\n'
            "      <description>Test-only message.</description>\n"
            '      <field type="uint8_t" name="value">Any byte.</field>\n'
            "    </message>\n  </messages>",
        )
    )
    second_module = load_dialect(xml=xml)
    second = Path(second_module.__file__ or "")
    assert second != first
    assert second.name == f"esc_bridge-{dialect_key(xml.read_bytes())}.py"
    assert second_module.MAVLINK_MSG_ID_ESC_BRIDGE_PROBE == 42290
    assert first.stat().st_mtime_ns == stamp  # the old entry is left for whoever uses it


def test_damaged_cache_file_is_regenerated(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(CACHE_ENV, str(tmp_path))
    path = Path(load_dialect().__file__ or "")
    path.write_text("this is not python (\n")
    dialect_impl._loaded.clear()
    assert load_dialect().MAVLink_esc_status_message.crc_extra == 10


def test_key_depends_on_content() -> None:
    xml = OWN_XML.read_bytes()
    assert dialect_key(xml) == dialect_key(bytes(xml))
    assert dialect_key(xml) != dialect_key(xml + b"\n")
    assert len(dialect_key(xml)) == 16


def test_cache_root_precedence(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(CACHE_ENV, raising=False)
    monkeypatch.delenv("CACHE_DIRECTORY", raising=False)
    monkeypatch.delenv("XDG_CACHE_HOME", raising=False)
    assert cache_root() == Path.home() / ".cache" / "esc-bridge"
    monkeypatch.setenv("XDG_CACHE_HOME", "relative/ignored")
    assert cache_root() == Path.home() / ".cache" / "esc-bridge"
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert cache_root() == tmp_path / "xdg" / "esc-bridge"
    # systemd's CacheDirectory= (several directories are ":"-separated; the first is ours).
    monkeypatch.setenv("CACHE_DIRECTORY", f"{tmp_path / 'systemd'}:{tmp_path / 'other'}")
    assert cache_root() == tmp_path / "systemd"
    monkeypatch.setenv(CACHE_ENV, str(tmp_path / "mine"))
    assert cache_root() == tmp_path / "mine"


def test_systemd_cache_directory_keeps_the_dialect(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv(CACHE_ENV, raising=False)
    monkeypatch.setenv("CACHE_DIRECTORY", str(tmp_path / "var-cache"))
    path = Path(load_dialect().__file__ or "")
    assert path.parent == tmp_path / "var-cache" / "mavlink"
    assert path.name == f"esc_bridge-{dialect_key(OWN_XML.read_bytes())}.py"


IN_MEMORY_PROBE = """
import logging, sys
logging.basicConfig(level=logging.INFO, stream=sys.stdout, format="%(message)s")
from bridge.mavlink import load_dialect
m = load_dialect()
print(getattr(m, "__file__", None), m.MAVLink_esc_status_message.crc_extra, m.DIALECT)
"""


def test_without_a_writable_cache_the_dialect_is_made_in_memory(tmp_path: Path) -> None:
    """A system user whose home cannot hold a cache (here: $HOME is a file) still gets the
    dialect, and nothing is written: not beside the home, not in the temporary directory."""
    home = tmp_path / "home-is-a-file"
    home.write_text("")
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    env = {k: v for k, v in os.environ.items() if k not in (CACHE_ENV, "XDG_CACHE_HOME")}
    env.pop("CACHE_DIRECTORY", None)
    env.update(HOME=str(home), TMPDIR=str(tmp))
    done = subprocess.run(
        [sys.executable, "-c", IN_MEMORY_PROBE],
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
    )
    lines = done.stdout.splitlines()
    assert lines[-1] == "None 10 esc_bridge"
    assert any(
        line.startswith("cannot write the MAVLink dialect cache ") and "Not a directory" in line
        for line in lines
    ), lines
    assert any(line.startswith("generated the MAVLink dialect in memory in ") for line in lines)
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["home-is-a-file", "tmp"]


def test_default_cache_is_outside_the_repository(monkeypatch: pytest.MonkeyPatch) -> None:
    """Generated code must never land in the source tree, whatever the working directory."""
    monkeypatch.delenv(CACHE_ENV, raising=False)
    monkeypatch.delenv("CACHE_DIRECTORY", raising=False)
    monkeypatch.delenv("XDG_CACHE_HOME", raising=False)
    repo = Path(__file__).resolve().parents[2]
    root = cache_root()
    assert root is not None
    assert not root.resolve().is_relative_to(repo)


# --- errors ---------------------------------------------------------------------------


def test_unwritable_cache_names_the_path(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    monkeypatch.setenv(CACHE_ENV, str(blocker / "cache"))
    with pytest.raises(DialectError, match=CACHE_ENV) as caught:
        load_dialect()
    assert isinstance(caught.value, BridgeError)
    assert str(blocker / "cache") in str(caught.value)
    assert isinstance(caught.value.__cause__, OSError)


def test_mavgen_failure_names_the_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(CACHE_ENV, str(tmp_path / "cache"))
    xml = tmp_path / "broken.xml"
    xml.write_text(
        OWN_XML.read_text().replace(
            'type="uint16_t" name="counter"', 'type="uint7_t" name="counter"'
        )
    )
    with pytest.raises(DialectError, match="mavgen failed") as caught:
        load_dialect(xml=xml)
    assert caught.value.path == xml
    assert str(xml) in str(caught.value)
    assert [p.name for p in (tmp_path / "cache" / "mavlink").iterdir()] == []


# --- stock pymavlink after `esc-bridge mavlink-dialect` -------------------------------------


def stock_pymavlink_copy(root: Path) -> Path:
    """A pymavlink package under ``root`` that is the installed one (every file a symlink to it)
    except for a dialects/v20 directory of its own: the step may write there without touching
    this environment. Returns that v20 directory."""
    real = Path(stock.__file__).resolve().parents[2]  # .../pymavlink
    copy = root / "pymavlink"
    copy.mkdir(parents=True)
    for entry in real.iterdir():
        if entry.name not in ("dialects", "__pycache__"):
            (copy / entry.name).symlink_to(entry)
    (copy / "dialects").mkdir()
    for entry in (real / "dialects").iterdir():
        if entry.name not in ("v20", "__pycache__"):
            (copy / "dialects" / entry.name).symlink_to(entry)
    v20 = copy / "dialects" / "v20"
    v20.mkdir()
    for entry in (real / "dialects" / "v20").iterdir():
        if entry.name != "__pycache__":
            (v20 / entry.name).symlink_to(entry)
    return v20


STOCK_READER = """
import sys
from pymavlink import mavutil
log = mavutil.mavlink_connection(sys.argv[1], dialect=sys.argv[2])
while (msg := log.recv_msg()) is not None:
    print(msg.get_type(), getattr(msg, "index", ""), getattr(msg, "info", ""),
          list(getattr(msg, "rpm", [])))
"""


def test_stock_pymavlink_mavproxy_and_mavlogdump_decode_after_the_documented_step(
    own: ModuleType, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from bridge.cli import main

    v20 = stock_pymavlink_copy(tmp_path / "site")
    tlog = tmp_path / "flight.tlog"
    mav = own.MAVLink(None, srcSystem=1, srcComponent=191)
    frames = [
        own.MAVLink_esc_info_message(**ESC_INFO_ARGS).pack(mav),
        own.MAVLink_esc_status_message(**ESC_STATUS_ARGS).pack(mav),
    ]
    tlog.write_bytes(
        b"".join(
            (1_700_000_000_000_000 + i).to_bytes(8, "big") + bytes(f) for i, f in enumerate(frames)
        )
    )
    env = dict(os.environ, PYTHONPATH=str(tmp_path / "site"), MAVLINK20="1")
    env.pop("MAVLINK_DIALECT", None)

    def read(dialect: str) -> str:
        done = subprocess.run(
            [sys.executable, "-c", STOCK_READER, str(tlog), dialect],
            env=env,
            capture_output=True,
            text=True,
            timeout=120,
            check=True,
        )
        return done.stdout

    assert read("ardupilotmega").split("\n")[:2] == ["UNKNOWN_290   []", "UNKNOWN_291   []"]
    assert main(["mavlink-dialect", "--into", str(v20)]) == 0
    out = capsys.readouterr().out
    assert f"installed the esc_bridge MAVLink dialect: {v20 / 'esc_bridge.py'}" in out
    assert "--dialect esc_bridge" in out and "MAVLINK_DIALECT=esc_bridge" in out
    assert read("esc_bridge").split("\n")[:2] == [
        "ESC_INFO 4 11 []",
        "ESC_STATUS 0  [12000, -8500, 0, -2147483648]",
    ]
    # MAVProxy and mavlogdump load dialects the same way (--dialect): mavlogdump itself here.
    mavlogdump = Path(sys.executable).with_name("mavlogdump.py")
    dump = subprocess.run(
        [
            sys.executable,
            str(mavlogdump),
            "--dialect",
            "esc_bridge",
            "--types",
            "ESC_INFO,ESC_STATUS",
            str(tlog),
        ],
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
    ).stdout
    assert "ESC_INFO {index : 4" in dump and "ESC_STATUS {index : 0" in dump
    assert "UNKNOWN" not in dump
    # And the environment this test runs in was not touched.
    assert not (Path(stock.__file__).parent / "esc_bridge.py").exists()
