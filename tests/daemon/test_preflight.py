"""Start-up checks (bridge.daemon.preflight): each check on its own, each through `esc-bridge run
--check` as a subprocess (exit 2, the message names the thing, nothing opened and nothing sent),
the shipped example configs, unreadable config files, a fuzz of the config reader, and `run`
agreeing with `--check` on a table of good and bad configurations (`run` refusing the bad ones
before a single CAN frame, on a udp_multicast bus observed as in test_daemon_e2e.py)."""

from __future__ import annotations

import json
import math
import os
import shutil
import socket
import subprocess
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from conftest import ESC_BRIDGE, ROOT, STARTUP_TIMEOUT_S, Daemon, Observer, can_args
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from bridge.can_interface import assess, read_link
from bridge.config import SECTIONS, BridgeConfig, build_config
from bridge.config_file import read_config_file
from bridge.daemon.preflight import SOURCE_VALID_RANGES, plan
from bridge.errors import ConfigError
from bridge.mavlink import CACHE_ENV
from bridge.mavlink.endpoints import Endpoint, check_endpoints
from bridge.mavlink.link import MavlinkLink
from bridge.mixing.loader import load_mixer
from bridge.mixing.mixer import Mixer

EXAMPLES = sorted((ROOT / "config").glob("*.toml"))
QUIET_S = 0.3  # how long a refused start is watched for stray frames


def config_of(raw: dict[str, Any]) -> BridgeConfig:
    return build_config(raw, "v.toml")


def refused(raw: dict[str, Any], *parts: str, record_dir: Path | str | None = None) -> str:
    """plan() on ``raw`` must raise a ConfigError naming the file and each of ``parts``."""
    with pytest.raises(ConfigError) as caught:
        plan(config_of(raw), record_dir=record_dir)
    message = str(caught.value)
    assert message.startswith(("v.toml: ", "command line: ", "MAVLink dialect: ")), message
    for part in parts:
        assert part in message, f"{part!r} not in {message!r}"
    return message


# -- MAVLink URLs and outputs ----------------------------------------------------------------


def test_plan_carries_what_it_worked_out() -> None:
    checked = plan(
        config_of(
            {
                "mavlink": {
                    "url": "udpin:127.0.0.1:14551",
                    "outputs": ["udpout:10.0.0.1:14550", "tcp:10.0.0.2:5760"],
                    "source": "hil_actuator_controls",
                },
            }
        )
    )
    assert checked.autopilot == Endpoint("udpin:127.0.0.1:14551", "udpin", "127.0.0.1:14551")
    assert [(e.kind, e.address) for e in checked.outputs] == [
        ("udpout", "10.0.0.1:14550"),
        ("tcp", "10.0.0.2:5760"),
    ]
    assert checked.input_range == (0.0, 1.0)
    assert checked.valid_range == (-1.5, 1.5)
    assert checked.config.escs.ids == (1, 2, 3, 4)
    assert checked.record_dir is None
    assert checked.passed[:3] == (
        "MAVLink: autopilot on udpin 127.0.0.1:14551; outputs: udpout 10.0.0.1:14550, "
        "tcp 10.0.0.2:5760",
        "mixer inputs ch1..ch4: all carried by hil_actuator_controls",
        "valid range [-1.5, 1.5] contains the input range [0, 1]",
    )


@pytest.mark.parametrize(
    ("mavlink", "parts"),
    [
        ({"url": "carrier-pigeon:/dev/coop"}, ["[mavlink] url 'carrier-pigeon:/dev/coop'"]),
        ({"url": "udpin:0.0.0.0:70000"}, ["[mavlink] url", "port 70000 is not 1..65535"]),
        ({"url": "serial:/dev/ttyS0:0"}, ["[mavlink] url", "baud rate 0"]),
        ({"outputs": ["udp:10.0.0.1:14550"]}, ["[mavlink] outputs 'udp:10.0.0.1:14550'"]),
    ],
    ids=["scheme", "port", "baud", "output"],
)
def test_malformed_urls_are_refused(mavlink: dict[str, Any], parts: list[str]) -> None:
    refused({"mavlink": mavlink}, *parts, "expected one of udpin:HOST:PORT")


@pytest.mark.parametrize(
    ("url", "outputs", "same_as"),
    [
        ("udpin:0.0.0.0:14550", ["udpin:0.0.0.0:14550"], "[mavlink] url 'udpin:0.0.0.0:14550'"),
        ("tcp:h:5760", ["udpout:h:1455", "udpout:h:01455"], "'udpout:h:1455'"),
    ],
    ids=["url", "output"],
)
def test_a_connection_listed_twice_is_refused(url: str, outputs: list[str], same_as: str) -> None:
    message = refused(
        {"mavlink": {"url": url, "outputs": outputs}}, "is the same connection as " + same_as
    )
    # MavlinkLink.start refuses it with the same words, through the same function.
    config = config_of({"mavlink": {"url": url, "outputs": outputs}})
    with pytest.raises(ConfigError) as caught:
        check_endpoints(config.mavlink)
    assert message == f"v.toml: {caught.value}"
    link = MavlinkLink(config.mavlink)
    with pytest.raises(ConfigError) as at_start:
        link.start()
    link.close()
    assert str(at_start.value) == str(caught.value)


# -- inputs the source must carry ------------------------------------------------------------


def test_geometry_mixer_without_axis_channels_is_refused() -> None:
    # Today's behaviour it replaces: the daemon would start, and every SERVO_OUTPUT_RAW would
    # mix to None (its axes are absent), so the loop would send safe values for ever.
    servo_output_raw = [1500.0] * 32 + [math.nan] * 4
    assert Mixer(load_mixer("quad-x")).mix(servo_output_raw, armed=True) is None
    refused(
        {"mixer": {"name": "quad-x"}},
        "[mixer] name 'quad-x' reads roll, pitch, yaw, thrust",
        "[mavlink] source 'servo_output_raw' carries ch1..ch32",
        "no motor would ever spin",
        "expected [mixer] axis_channels",
        '[mavlink] source = "actuator_control_target"',
    )


@pytest.mark.parametrize(
    ("raw", "parts"),
    [
        (
            {"mixer": {"name": "hex-x", "axis_channels": {"roll": 1, "pitch": 2, "thrust": 3}}},
            ["reads yaw, but", "and [mixer] axis_channels roll, pitch, thrust"],
        ),
        (
            {"mavlink": {"source": "actuator_control_target"}},
            ["[mixer] name 'passthrough-4' reads ch1..ch4", "a geometry mixer such as quad-x"],
        ),
        (
            {
                "mavlink": {"source": "actuator_control_target"},
                "mixer": {
                    "name": "quad-x",
                    "axis_channels": {"roll": 1, "pitch": 2, "thrust": 3, "yaw": 4},
                },
            },
            ["axis_channels takes roll from channel 1", "carries roll, pitch, yaw, thrust"],
        ),
        (
            {
                "mavlink": {"source": "hil_actuator_controls"},
                "mixer": {
                    "name": "quad-x",
                    "axis_channels": {"roll": 1, "pitch": 2, "thrust": 3, "yaw": 17},
                },
            },
            ["takes yaw from channel 17", "'hil_actuator_controls' carries ch1..ch16"],
        ),
    ],
    ids=["three-axes", "channels-from-axes-source", "axes-source-with-channels", "hil-ch17"],
)
def test_inputs_the_source_never_carries_are_refused(raw: dict[str, Any], parts: list[str]) -> None:
    refused(raw, *parts)


@pytest.mark.parametrize(
    ("raw", "line"),
    [
        ({}, "mixer inputs ch1..ch4: all carried by servo_output_raw"),
        (
            {"mavlink": {"source": "actuator_control_target"}, "mixer": {"name": "octo-x"}},
            "mixer inputs roll, pitch, yaw, thrust: all carried by actuator_control_target",
        ),
        (
            {
                "mavlink": {"source": "actuator_output_status"},
                "mixer": {
                    "name": "hex-x",
                    "axis_channels": {"roll": 1, "pitch": 2, "thrust": 3, "yaw": 32},
                },
            },
            "mixer inputs roll, pitch, yaw, thrust: all carried by actuator_output_status "
            "(roll, pitch, yaw, thrust by [mixer] axis_channels)",
        ),
        (
            {
                "mavlink": {"source": "hil_actuator_controls"},
                "mixer": {"name": "passthrough-16"},
                "can": {"bitrate": 1_000_000},
            },
            "mixer inputs ch1..ch16: all carried by hil_actuator_controls",
        ),
    ],
    ids=["passthrough", "axes-source", "axis-channels", "hil-16"],
)
def test_inputs_the_source_carries_pass(raw: dict[str, Any], line: str) -> None:
    assert line in plan(config_of(raw)).passed


# -- valid range -----------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("source", "mixer"),
    [
        ("servo_output_raw", "passthrough-4"),
        ("actuator_output_status", "passthrough-4"),
        ("hil_actuator_controls", "passthrough-4"),
        ("actuator_control_target", "quad-x"),
    ],
)
def test_valid_range_defaults_by_source(source: str, mixer: str) -> None:
    checked = plan(config_of({"mavlink": {"source": source}, "mixer": {"name": mixer}}))
    assert checked.valid_range == SOURCE_VALID_RANGES[source]
    pwm = source in ("servo_output_raw", "actuator_output_status")
    assert checked.valid_range == ((800.0, 2200.0) if pwm else (-1.5, 1.5))


def test_valid_range_given() -> None:
    checked = plan(config_of({"mixer": {"valid_range": [900, 2100]}}))
    assert checked.valid_range == (900.0, 2100.0)
    assert "valid range [900, 2100] contains the input range [1000, 2000]" in checked.passed
    axes = {"name": "quad-x", "axis_channels": {"roll": 1, "pitch": 2, "thrust": 3, "yaw": 4}}
    # The axes read from channels over the PWM range, which [1000, 2000] contains exactly.
    assert plan(config_of({"mixer": axes | {"valid_range": [1000, 2000]}})).valid_range == (
        1000.0,
        2000.0,
    )


@pytest.mark.parametrize(
    ("raw", "parts"),
    [
        (
            {"mixer": {"valid_range": [1100, 1900]}},
            [
                "[mixer] valid_range [1100, 1900] does not contain",
                "mixer 'passthrough-4' output 'm1' input_range [1000, 2000]",
            ],
        ),
        (
            {"mixer": {"input_range": [0, 1]}},
            [
                "[mixer] valid_range (default for servo_output_raw) [800, 2200]",
                "does not contain [mixer] input_range [0, 1]",
            ],
        ),
        (
            {"mavlink": {"source": "hil_actuator_controls"}, "mixer": {"valid_range": [0, 0.5]}},
            [
                "[mixer] valid_range [0, 0.5]",
                "the input range of [mavlink] source 'hil_actuator_controls' [0, 1]",
            ],
        ),
        (
            {
                "mavlink": {"source": "actuator_control_target"},
                "mixer": {"name": "quad-x", "valid_range": [0, 1]},
            },
            ["[mixer] valid_range [0, 1]", "the ACTUATOR_CONTROL_TARGET axis range [-1, 1]"],
        ),
        (
            {
                "mixer": {
                    "name": "quad-x",
                    "axis_channels": {"roll": 1, "pitch": 2, "thrust": 3, "yaw": 4},
                    "valid_range": [1000, 1900],
                },
            },
            ["[mixer] valid_range [1000, 1900]", "the PWM range [mixer] axis_channels read"],
        ),
    ],
    ids=["given", "default", "source-range", "axes", "axis-channels"],
)
def test_valid_range_must_contain_the_input_range(raw: dict[str, Any], parts: list[str]) -> None:
    refused(raw, *parts, "expected a valid range that contains the input range")


# -- the recording directory -----------------------------------------------------------------


def test_record_dir_that_exists_is_checked_without_leaving_a_file(tmp_path: Path) -> None:
    (tmp_path / "keep").write_text("x")
    checked = plan(config_of({}), record_dir=tmp_path)
    assert checked.record_dir == tmp_path
    assert checked.passed[-1] == f"recording into {tmp_path} (exists, writable)"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep"]


def test_record_dir_to_be_created_is_not_created(tmp_path: Path) -> None:
    target = tmp_path / "new" / "deeper"
    checked = plan(config_of({}), record_dir=str(target))
    assert checked.passed[-1] == f"recording into {target} (to be created in {tmp_path}, writable)"
    assert list(tmp_path.iterdir()) == []


def test_bad_record_dirs_are_refused(tmp_path: Path) -> None:
    a_file = tmp_path / "a-file"
    a_file.write_text("")
    refused({}, "command line: --record", "not a directory", record_dir=a_file)
    refused(
        {},
        f"cannot be created: {a_file} is not a directory",
        "expected a writable directory",
        record_dir=a_file / "sub",
    )
    (tmp_path / "dangling").symlink_to(tmp_path / "nowhere")
    refused({}, "a broken symbolic link", record_dir=tmp_path / "dangling")
    # /proc takes no new files, whoever asks (root included).
    refused(
        {},
        "--record '/proc/esc-bridge-record'",
        "cannot write in /proc",
        record_dir="/proc/esc-bridge-record",
    )


# -- the dialect, device paths ---------------------------------------------------------------


def test_a_dialect_that_cannot_be_generated_is_a_config_error(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    (tmp_path / "a-file").write_text("")
    monkeypatch.setenv(CACHE_ENV, str(tmp_path / "a-file" / "cache"))
    refused({}, "MAVLink dialect: cannot write the MAVLink dialect cache", f"${CACHE_ENV}")


def test_a_device_as_mixer_is_refused_unread() -> None:
    refused({"mixer": {"name": "/dev/zero"}}, "[mixer] name '/dev/zero': a device, not a file")


def test_the_new_keys_are_described() -> None:
    config = config_of(
        {
            "output": {"motor_test": True, "arming_timeout_ms": 1500},
            "mavlink": {"command_senders": [7, 255]},
        }
    )
    assert plan(config).passed[3] == (
        "arming state older than 1500 ms counts as disarmed; motor test on, from system IDs 7, 255"
    )
    assert plan(config_of({})).passed[3] == (
        "arming state older than 3000 ms counts as disarmed; motor test off "
        "(MAV_CMD_DO_MOTOR_TEST refused)"
    )


# -- unreadable config files -----------------------------------------------------------------


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (b"[output]\nrate_hz = \xff\xfe\n", "not UTF-8 text: byte 0xFF at offset 19"),
        (b"\xef\xbb\xbf[output]\n\xc3(\n", "not UTF-8 text: byte 0xC3 at offset 12"),
        (b"\x7fELF\x02\x01\x01\x00\x00\xff", "a binary file (NUL byte at offset 7)"),
        (b"[output]\nrate_hz = 1\x00\n", "a binary file (NUL byte at offset 20)"),
        (b"[output\n", "not valid TOML"),
        (b"x = " + b"[" * 5000 + b"]" * 5000, "nested too deeply"),
        # Python's own words, which go on differently in 3.10 and 3.11.
        (b"[mavlink]\nstream_rate_hz = " + b"9" * 5000, "Exceeds the limit (4300"),
        (b"x" * (1024 * 1024 + 1), "larger than 1024 KiB"),
    ],
    ids=["non-utf8", "bad-after-bom", "elf", "nul", "toml", "nested", "digits", "big"],
)
def test_unreadable_files_name_the_problem(tmp_path: Path, content: bytes, message: str) -> None:
    path = tmp_path / "bridge.toml"
    path.write_bytes(content)
    with pytest.raises(ConfigError, match=r"^" + str(path).replace(".", r"\.") + ": ") as caught:
        read_config_file(path)
    assert message in str(caught.value)


def test_empty_and_bom_files_are_valid(tmp_path: Path) -> None:
    empty = tmp_path / "empty.toml"
    empty.write_bytes(b"")
    assert read_config_file(empty) == {}
    assert build_config(read_config_file(empty), str(empty)) == BridgeConfig(source=str(empty))
    bom = tmp_path / "bom.toml"
    bom.write_bytes(b"\xef\xbb\xbf[output]\nrate_hz = 200\n")
    assert read_config_file(bom) == {"output": {"rate_hz": 200}}


def test_directories_and_devices_are_refused_unread(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"is a directory; expected a TOML config file"):
        read_config_file(tmp_path)
    # /dev/zero would never end; a serial port would wait for its carrier.
    with pytest.raises(ConfigError, match=r"^/dev/zero: a device, not a file"):
        read_config_file("/dev/zero")


def test_numbers_beyond_a_float_are_config_errors() -> None:
    for raw in (
        {"mavlink": {"stream_rate_hz": 10**400}},
        {"mixer": {"input_range": [0, 10**400]}},
        {"mixer": {"valid_range": [-(10**400), 1]}},
        {"escs": {"ckesc_msg_hz": [10**400, 10, 2]}},
    ):
        with pytest.raises(ConfigError, match=r"got .{0,80}$"):
            config_of(raw)
    with pytest.raises(ConfigError, match=r"input_range: expected two different numbers"):
        config_of({"mixer": {"input_range": [True, False]}})


def toml_value(value: Any) -> str:
    """TOML for the values the fuzz below generates (strings as JSON, a subset of TOML's)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float) and not math.isfinite(value):
        return "nan" if math.isnan(value) else ("inf" if value > 0 else "-inf")
    if isinstance(value, int | float):
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, list):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    assert isinstance(value, dict)
    return "{" + ", ".join(f"{json.dumps(k)} = {toml_value(v)}" for k, v in value.items()) + "}"


KEYS = [(name, f) for name, cls in SECTIONS.items() for f in cls.__dataclass_fields__]
scalars = st.one_of(
    st.booleans(),
    st.integers(min_value=-(10**400), max_value=10**400),
    st.integers(min_value=-3000, max_value=70_000),
    st.floats(),
    st.text(max_size=12),
    st.sampled_from(["ft", "10b", "quad-x", "hil_actuator_controls", "udpin:0.0.0.0:1"]),
)
toml_values = st.recursive(
    scalars,
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=6), inner),
    max_leaves=8,
)
documents = st.lists(
    st.tuples(
        st.sampled_from(KEYS) | st.tuples(st.text(min_size=1), st.text(min_size=1)),
        toml_values,
    ),
    max_size=6,
)


@pytest.fixture(scope="module")
def fuzz_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("fuzz") / "bridge.toml"


def only_config_errors(path: Path, data: bytes) -> None:
    path.write_bytes(data)
    try:
        build_config(read_config_file(path), str(path))
    except ConfigError as exc:
        assert str(exc).startswith(f"{path}: ")
        assert len(str(exc)) < 2000  # long values are shortened


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.binary(max_size=300))
def test_fuzz_random_bytes_only_config_errors(fuzz_file: Path, data: bytes) -> None:
    only_config_errors(fuzz_file, data)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(document=documents)
def test_fuzz_toml_documents_only_config_errors(
    fuzz_file: Path, document: list[tuple[tuple[str, str], Any]]
) -> None:
    tables: dict[str, list[str]] = {}
    for (section, key), value in document:
        tables.setdefault(section, []).append(f"{json.dumps(key)} = {toml_value(value)}")
    text = "".join(
        f"[{json.dumps(section)}]\n" + "\n".join(lines) + "\n" for section, lines in tables.items()
    )
    only_config_errors(fuzz_file, text.encode("utf-8", "surrogatepass"))


# -- through the command line ----------------------------------------------------------------


def esc_bridge(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [ESC_BRIDGE, *args],
        capture_output=True,
        text=True,
        timeout=60,
        env={**os.environ, **(env or {})},
    )


@pytest.fixture
def gcs() -> Iterator[socket.socket]:
    """A UDP socket where `--mavlink udpout:...` points: an opened link would send it a
    HEARTBEAT at once."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.setblocking(False)
    yield sock
    sock.close()


def bus_flags(can_port: int) -> list[str]:
    return [*can_args(can_port), "--no-zenoh-scouting"]


def assert_nothing_opened(gcs: socket.socket, observer: Observer) -> None:
    time.sleep(QUIET_S)
    with pytest.raises(BlockingIOError):
        gcs.recv(2048)
    assert observer.frames == []


@pytest.fixture
def a_file(tmp_path: Path) -> Path:
    path = tmp_path / "a-file"
    path.write_text("")
    return path


# (config file bytes, extra args, extra environment, words of the message); "{gcs}" is the
# GCS socket's URL, "{tmp}" the test's directory.
BAD_CHECKS: dict[str, tuple[bytes, list[str], dict[str, str], list[str]]] = {
    "url": (
        b"",
        ["--mavlink", "carrier-pigeon:/dev/coop"],
        {},
        ["command line: --mavlink 'carrier-pigeon:/dev/coop' is not a connection string"],
    ),
    "url-in-file": (
        b'[mavlink]\nurl = "udpin:0.0.0.0:99999"\n',
        [],
        {},
        ["bridge.toml: [mavlink] url 'udpin:0.0.0.0:99999': port 99999 is not 1..65535"],
    ),
    "output-repeats-url": (
        b'[mavlink]\noutputs = ["{gcs}"]\n',
        ["--mavlink", "{gcs}"],
        {},
        ["bridge.toml: [mavlink] outputs '{gcs}' is the same connection as --mavlink '{gcs}'"],
    ),
    "geometry-without-axes": (
        b'[mixer]\nname = "quad-x"\n',
        [],
        {},
        ["bridge.toml: [mixer] name 'quad-x' reads roll, pitch, yaw, thrust", "axis_channels"],
    ),
    "geometry-by-flag": (
        b"",
        ["--mixer", "quad-x"],
        {},
        ["--mixer 'quad-x' reads roll, pitch, yaw, thrust, but [mavlink] source"],
    ),
    "valid-range": (
        b"[mixer]\nvalid_range = [1100, 1900]\n",
        [],
        {},
        ["bridge.toml: [mixer] valid_range [1100, 1900] does not contain"],
    ),
    "record-unwritable": (
        b"",
        ["--record", "/proc/esc-bridge-record"],
        {},
        ["command line: --record '/proc/esc-bridge-record': cannot write in /proc"],
    ),
    "record-a-file": (
        b"",
        ["--record", "{tmp}/a-file"],
        {},
        ["command line: --record '{tmp}/a-file': not a directory"],
    ),
    "dialect": (
        b"",
        [],
        {CACHE_ENV: "{tmp}/a-file/cache"},
        ["MAVLink dialect: cannot write the MAVLink dialect cache {tmp}/a-file/cache"],
    ),
    "non-utf8": (
        b"[output]\nrate_hz = 400 # \xe9\n",
        [],
        {},
        ["bridge.toml: not UTF-8 text: byte 0xE9 at offset 25"],
    ),
    "binary": (b"\x00\x01\x02", [], {}, ["bridge.toml: a binary file (NUL byte at offset 0)"]),
    "can-not-a-table": (b"can = 1\n", [], {}, ["bridge.toml: [can] must be a table, got 1"]),
    "arming-timeout": (
        b"[output]\narming_timeout_ms = 100\n",
        [],
        {},
        ["[output] arming_timeout_ms: expected an integer 500..60000, got 100"],
    ),
    "motor-test": (
        b'[output]\nmotor_test = "yes"\n',
        [],
        {},
        ["[output] motor_test: expected true or false, got 'yes'"],
    ),
    "command-senders": (
        b"[mavlink]\ncommand_senders = [255, 255]\n",
        [],
        {},
        ["[mavlink] command_senders: expected a non-empty list of distinct integers 1..255"],
    ),
    "valid-range-order": (
        b"[mixer]\nvalid_range = [2200, 800]\n",
        [],
        {},
        ["[mixer] valid_range: expected two numbers [low, high] with low < high"],
    ),
    "zenoh-endpoint": (
        b"",
        ["--zenoh-connect", "tcp/nowhere"],
        {},
        ["command line: --zenoh-connect: expected endpoints of the form"],
    ),
}


def filled(text: str, gcs_url: str, tmp_path: Path) -> str:
    return text.replace("{gcs}", gcs_url).replace("{tmp}", str(tmp_path))


@pytest.mark.parametrize("case", list(BAD_CHECKS))
def test_check_refuses_before_opening_anything(
    case: str,
    tmp_path: Path,
    a_file: Path,
    gcs: socket.socket,
    can_port: int,
    observer: Observer,
) -> None:
    content, args, env, words = BAD_CHECKS[case]
    gcs_url = f"udpout:127.0.0.1:{gcs.getsockname()[1]}"
    config = tmp_path / "bridge.toml"
    config.write_bytes(filled(content.decode("latin-1"), gcs_url, tmp_path).encode("latin-1"))
    args = [filled(a, gcs_url, tmp_path) for a in args]
    if "--mavlink" not in args and b"url" not in content:
        args += ["--mavlink", gcs_url]
    result = esc_bridge(
        "run",
        "--check",
        "--config",
        str(config),
        *bus_flags(can_port),
        *args,
        env={k: filled(v, gcs_url, tmp_path) for k, v in env.items()},
    )
    assert result.returncode == 2, result.stderr
    assert result.stdout == ""
    assert "Traceback" not in result.stderr
    assert result.stderr.startswith("esc-bridge: ")
    for word in words:
        assert filled(word, gcs_url, tmp_path) in result.stderr
    assert_nothing_opened(gcs, observer)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a-file", "bridge.toml"]


def test_unreadable_permissions(tmp_path: Path) -> None:
    path = tmp_path / "bridge.toml"
    path.write_text("[output]\nrate_hz = 400\n")
    path.chmod(0)
    command = [ESC_BRIDGE, "run", "--check", "--config", str(path)]
    if os.geteuid() == 0:
        # Root reads anything; without these two capabilities it obeys the mode bits too.
        setpriv = shutil.which("setpriv")
        if setpriv is None:
            pytest.skip("root without setpriv: file permissions cannot be made to apply")
        command = [setpriv, "--bounding-set", "-dac_override,-dac_read_search", "--", *command]
    result = subprocess.run(command, capture_output=True, text=True, timeout=60)
    assert result.returncode == 2
    assert result.stderr == (
        f"esc-bridge: {path}: cannot read: Permission denied; expected a readable TOML config "
        "file\n"
    )


def test_check_prints_each_check_and_opens_nothing(
    tmp_path: Path, gcs: socket.socket, can_port: int, observer: Observer
) -> None:
    gcs_url = f"udpout:127.0.0.1:{gcs.getsockname()[1]}"
    config = tmp_path / "bridge.toml"
    config.write_text(
        '[mixer]\nname = "quad-x"\naxis_channels = { roll = 1, pitch = 2, thrust = 3, yaw = 4 }\n'
        "[output]\nmotor_test = true\n"
    )
    record = tmp_path / "rec" / "today"
    result = esc_bridge(
        "run",
        "--check",
        "--config",
        str(config),
        "--mavlink",
        gcs_url,
        "--record",
        str(record),
        *bus_flags(can_port),
    )
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    assert lines[:2] == [f"{config}: OK", "  mixer quad-x: 4 outputs"]
    assert lines[2].startswith("  bus load ")
    assert lines[3:9] == [
        f"  MAVLink: autopilot on udpout 127.0.0.1:{gcs.getsockname()[1]}; outputs: none",
        "  mixer inputs roll, pitch, yaw, thrust: all carried by servo_output_raw (roll, pitch, "
        "yaw, thrust by [mixer] axis_channels)",
        "  valid range [800, 2200] contains the input range [1000, 2000]",
        "  arming state older than 3000 ms counts as disarmed; motor test on, from system IDs 1, "
        "255",
        "  MAVLink ESC telemetry for 4 ESCs: autopilot link by its HEARTBEAT: ArduPilot "
        "ESC_TELEMETRY 2 Hz (112 B/s); PX4 ESC_STATUS 2 Hz, ESC_INFO 1 Hz (196 B/s); other "
        "ESC_STATUS 2 Hz, ESC_INFO 1 Hz, ESC_TELEMETRY 2 Hz (308 B/s)",
        lines[8],
    ]
    assert lines[8].startswith("  MAVLink dialect loads (") and lines[8].endswith(".py)")
    assert lines[9:] == [f"  recording into {record} (to be created in {tmp_path}, writable)"]
    assert_nothing_opened(gcs, observer)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bridge.toml"]


@pytest.mark.parametrize("path", EXAMPLES, ids=[p.name for p in EXAMPLES])
def test_check_passes_every_shipped_example(path: Path) -> None:
    result = esc_bridge("run", "--check", "--config", str(path))
    # Every check passes; then, as run would, --check refuses a SocketCAN interface this
    # machine does not have up (exit 1, after the lines of every other check).
    config = plan(build_config(read_config_file(path), str(path))).config
    refusal = None
    if config.can.interface == "socketcan":
        channel = config.can.channel
        refusal = assess(read_link(channel), channel, config.bitrate).refusal
    if refusal is None:
        assert result.returncode == 0, result.stderr
    else:
        assert result.returncode == 1
        assert result.stderr == f"esc-bridge: error: cannot start: {refusal}\n"
    lines = result.stdout.splitlines()
    assert lines[0] == f"{path}: OK"
    assert any(line.startswith("  MAVLink: autopilot on ") for line in lines)
    assert any(line.startswith("  valid range [800, 2200] contains") for line in lines)
    assert any(line.startswith("  MAVLink dialect loads") for line in lines)


def test_socketcan_interface_is_read_and_a_missing_one_named(tmp_path: Path) -> None:
    # No can7 here: --check says so after every other check's line, and refuses as run does,
    # in the same words and with the same exit status, naming the channel; --bitrate takes 1M.
    args = ["--can-channel", "can7", "--bitrate", "1M", "--mavlink", "udpout:127.0.0.1:9"]
    check = esc_bridge("run", "--check", "--no-zenoh", *args)
    assert check.returncode == 1
    lines = check.stdout.splitlines()
    assert lines[2].startswith("  bus load ") and " of 1000 kbit/s: " in lines[2]
    assert (
        lines[-1] == "  SocketCAN interface can7: not found on this machine; run refuses to start"
    )
    run = esc_bridge("run", "--no-zenoh", *args)
    assert run.returncode == 1
    assert run.stderr.startswith(
        "esc-bridge: error: cannot start: SocketCAN interface can7 does not exist; expected a CAN "
        "interface: "
    )
    assert check.stderr == run.stderr
    bad = esc_bridge("run", "--check", "--no-zenoh", *args[:2], "--bitrate", "1.5M")
    assert bad.returncode == 2
    assert "--bitrate: expected a bit rate such as 500000, 500k or 1M" in bad.stderr


# -- run and --check agree -------------------------------------------------------------------

# (config file, extra args, extra environment, good?) run by `run` and by `run --check` with
# the same flags; "{tmp}" is the test's directory, "{url}" the daemon's MAVLink URL.
AGREEMENT: dict[str, tuple[str, list[str], dict[str, str], bool]] = {
    "defaults": ("", [], {}, True),
    "geometry-with-axes": (
        '[mixer]\nname = "quad-x"\naxis_channels = { roll = 1, pitch = 2, thrust = 3, yaw = 4 }'
        "\nvalid_range = [900, 2100]\n",
        [],
        {},
        True,
    ),
    "hil-motor-test": (
        '[mavlink]\nsource = "hil_actuator_controls"\ncommand_senders = [255, 7]\n'
        "[output]\nmotor_test = true\narming_timeout_ms = 1000\n",
        [],
        {},
        True,
    ),
    "record-new-dir": ("", ["--record", "{tmp}/rec/new"], {}, True),
    "output-malformed": ('[mavlink]\noutputs = ["udp:10.0.0.1:14550"]\n', [], {}, False),
    "output-repeats-url": ('[mavlink]\noutputs = ["{url}"]\n', [], {}, False),
    "geometry-without-axes": ('[mixer]\nname = "hex-x"\n', [], {}, False),
    "valid-range": ("[mixer]\nvalid_range = [1000, 1900]\n", [], {}, False),
    "record-unwritable": ("", ["--record", "/proc/esc-bridge-record"], {}, False),
    "record-a-file": ("", ["--record", "{tmp}/bridge.toml"], {}, False),
    "dialect": ("", [], {CACHE_ENV: "{tmp}/bridge.toml/cache"}, False),
    "arming-timeout": ("[output]\narming_timeout_ms = 70000\n", [], {}, False),
    "not-utf8": ("[output]\n# caf\udce9\n", [], {}, False),
    # python-can would take it for a host name to look up, and fail to open the bus with it.
    "udp-multicast-channel": ("", ["--can-channel", "ckesc "], {}, False),
}


@pytest.mark.parametrize("case", list(AGREEMENT))
def test_run_and_check_agree(
    case: str,
    tmp_path: Path,
    start_daemon: Callable[..., Daemon],
    observer: Observer,
    mavlink_port: int,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    text, extra, env, good = AGREEMENT[case]

    def fill(value: str) -> str:
        return value.replace("{tmp}", str(tmp_path)).replace(
            "{url}", f"udpin:127.0.0.1:{mavlink_port}"
        )

    config = tmp_path / "bridge.toml"
    config.write_bytes(fill(text).encode("utf-8", "surrogateescape"))
    for name, value in env.items():
        monkeypatch.setenv(name, fill(value))  # the daemon's environment, and --check's
    daemon = start_daemon("--config", str(config), *map(fill, extra))
    check = esc_bridge(*daemon.args[1:], "--check")
    if good:
        assert check.returncode == 0, check.stderr
        assert check.stdout.startswith(f"{config}: OK\n")
        observer.wait_for(lambda msg: True, STARTUP_TIMEOUT_S)  # run sends (safe values)
        assert daemon.stop() == 0, daemon.output
        if extra[:1] == ["--record"]:
            recorded = sorted(p.suffix for p in Path(fill(extra[1])).iterdir())
            assert recorded == [".log", ".mcap", ".tlog"]
        return
    assert daemon.proc.wait(30) == 2
    daemon.stop()
    assert check.returncode == 2
    assert check.stdout == ""
    refusal = check.stderr.strip()
    assert refusal.startswith("esc-bridge: ")
    assert refusal in daemon.output.splitlines()  # the same words from run
    assert "Traceback" not in daemon.output + check.stderr
    time.sleep(QUIET_S)
    assert observer.frames == []
