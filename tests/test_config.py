"""Configuration: validation messages, precedence, documentation and the shipped examples."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import pytest
from conftest import documented_keys

from bridge.cli import build_parser as _parser
from bridge.cli.run import run_config
from bridge.config import build_config, with_esc_count
from bridge.config_file import read_config_file
from bridge.daemon import preflight
from bridge.errors import ConfigError

ROOT = Path(__file__).resolve().parent.parent
EXAMPLES = sorted((ROOT / "config").glob("*.toml"))


def test_every_key_is_documented_with_its_default() -> None:
    readme = (ROOT / "config" / "README.md").read_text(encoding="utf-8")
    for section, key, default, _ in documented_keys():
        row = re.search(rf"^\| `{key}` \|.*$", readme, re.MULTILINE)
        assert row is not None, f"[{section}] {key} is not documented in config/README.md"
        shown = f'"{default}"' if isinstance(default, str) else repr(default)  # as TOML writes it
        assert f"`{shown}`" in row.group(0), f"[{section}] {key}: default {shown} missing"
        assert f"## [{section}]" in readme


@pytest.mark.parametrize("path", EXAMPLES, ids=[p.name for p in EXAMPLES])
def test_shipped_examples_are_valid(path: Path) -> None:
    config = build_config(read_config_file(path), str(path))
    checked = preflight.plan(config)
    assert checked.config.escs.ids  # filled in
    assert "bus load" in checked.load_text


@pytest.mark.parametrize(
    ("raw", "message"),
    [
        ({"outptu": {}}, r"unknown section \[outptu\]; expected one of \[mavlink\]"),
        ({"output": {"rate": 4}}, r"\[output\] unknown key 'rate'; expected one of protocol"),
        ({"output": {"rate_hz": 0}}, r"\[output\] rate_hz: expected an integer 1..1000, got 0"),
        ({"output": {"rate_hz": "400"}}, r"rate_hz: expected an integer 1..1000, got '400'"),
        ({"output": {"protocol": "dshot"}}, r"protocol: expected one of 'ckesc', 'ft'"),
        ({"output": {"input_timeout_ms": 5}}, r"input_timeout_ms: expected an integer 20..1000"),
        ({"output": {"require_armed": 1}}, r"require_armed: expected true or false, got 1"),
        ({"can": {"bitrate": 123}}, r"\[can\] bitrate: expected a bit rate such as 500000, 500k"),
        ({"can": {"bitrate": "300k"}}, r"bitrate: expected a bit rate .*, 50000, got '300k'"),
        ({"escs": {"ids": [1, 1]}}, r"ids: expected a list of distinct integers 1..125"),
        ({"escs": {"ids": [0]}}, r"ids: expected a list of integers 1..125, got \[0\]"),
        ({"mavlink": {"signing_key": "abc"}}, r"signing_key: expected 64 hex digits"),
        ({"mixer": {"input_range": [1, 1]}}, r"input_range: expected two different numbers"),
        (
            {"output": {"protocol": "ft", "rate_hz": 5}},
            r"rate_hz: 5 Hz refreshes each FT ESC every 200 ms; the ESC drops a command after "
            r"450 ms, so expected at least 9 Hz",
        ),
        ({"mavlink": []}, r"\[mavlink\] must be a table"),
        (
            {"output": {"arming_timeout_ms": 499}},
            r"\[output\] arming_timeout_ms: expected an integer 500..60000, got 499",
        ),
        ({"output": {"arming_timeout_ms": 60_001}}, r"arming_timeout_ms: expected an integer"),
        ({"output": {"arming_timeout_ms": 3000.0}}, r"arming_timeout_ms: expected an integer"),
        ({"output": {"motor_test": 1}}, r"\[output\] motor_test: expected true or false, got 1"),
        (
            {"mavlink": {"command_senders": [255, 255]}},
            r"command_senders: expected a non-empty list of distinct integers 1..255",
        ),
        (
            {"mavlink": {"command_senders": [0]}},
            r"command_senders: expected a non-empty list of integers 1..255, got \[0\]",
        ),
        ({"mavlink": {"command_senders": []}}, r"command_senders: expected a non-empty list"),
        ({"mavlink": {"command_senders": 255}}, r"command_senders: expected a non-empty list"),
        (
            {"mixer": {"valid_range": [2200, 800]}},
            r"\[mixer\] valid_range: expected two numbers \[low, high\] with low < high",
        ),
        ({"mixer": {"valid_range": [800]}}, r"valid_range: expected two numbers"),
        ({"mixer": {"valid_range": [800, "2200"]}}, r"valid_range: expected two numbers"),
        ({"mixer": {"valid_range": [False, True]}}, r"valid_range: expected two numbers"),
        ({"mixer": {"input_range": [True, False]}}, r"input_range: expected two different"),
    ],
)
def test_bad_values_name_file_key_and_expectation(raw: dict[str, Any], message: str) -> None:
    with pytest.raises(ConfigError, match=message) as caught:
        build_config(raw, "vehicle.toml")
    assert str(caught.value).startswith("vehicle.toml: ")


def test_esc_lists_must_match_the_mixer() -> None:
    config = build_config({"escs": {"ids": [1, 2, 3]}}, "v.toml")
    with pytest.raises(ConfigError, match=r"ids has 3 entries but mixer 'passthrough-4' has 4"):
        with_esc_count(config, 4)
    filled = with_esc_count(build_config({}, "v.toml"), 4)
    assert filled.escs.ids == (1, 2, 3, 4)
    assert filled.escs.keys("ckesc").ckesc_channels == (1, 2, 3, 4)


def test_ckesc_frame_must_carry_the_channels() -> None:
    with pytest.raises(ConfigError, match=r"'14b' carries channels 1..4.* \[1, 2, 3, 5\]"):
        build_config({"escs": {"ckesc_command": "14b", "ckesc_channels": [1, 2, 3, 5]}}, "v")
    # The default channels, 1..N, once the mixer says N.
    config = build_config({"escs": {"ckesc_command": "14b"}}, "v.toml")
    with pytest.raises(ConfigError, match=r"^v.toml: \[escs\] ckesc_command '14b' carries"):
        with_esc_count(config, 6)


def test_only_the_selected_family_checks_its_keys() -> None:
    keys = {"ckesc_command": "14b", "ckesc_channels": [1, 2, 3, 5, 6]}
    with pytest.raises(ConfigError, match=r"ckesc_channels has 5 entries but ids has 4"):
        build_config({"escs": {"ids": [1, 2, 3, 4], **keys}}, "v.toml")
    # FT on the bus: the CKESC keys are checked for form only, and not sized to the mixer.
    ft = build_config({"output": {"protocol": "ft"}, "escs": {"ids": [1, 2, 3, 4], **keys}}, "v")
    assert with_esc_count(ft, 4).escs.keys("ckesc").ckesc_channels == (1, 2, 3, 5, 6)


def test_dronecan_keys_are_checked() -> None:
    with pytest.raises(ConfigError, match=r"dronecan_node_id: expected an integer 1..125"):
        build_config({"escs": {"dronecan_node_id": 0}}, "v.toml")
    with pytest.raises(ConfigError, match=r"ids \[1, 2, 3, 21\]: a DroneCAN RawCommand carries"):
        preflight.plan(
            build_config({"output": {"protocol": "dronecan"}, "escs": {"ids": [1, 2, 3, 21]}}, "v")
        )
    with pytest.raises(ConfigError, match=r"dronecan_reversible names ESCs \[7\]"):
        build_config(
            {
                "output": {"protocol": "dronecan"},
                "escs": {"ids": [1, 2, 3, 4], "dronecan_reversible": [7]},
            },
            "v.toml",
        )
    # Another family selected: the DroneCAN keys are checked for form only.
    build_config({"escs": {"ids": [1, 2, 3, 4], "dronecan_reversible": [7]}}, "v.toml")


def test_command_line_overrides_file(tmp_path: Path) -> None:
    path = tmp_path / "v.toml"
    path.write_text("[output]\nrate_hz = 200\n[can]\noptions = { port = 1, hop_limit = 0 }\n")
    args = _parser().parse_args(
        ["run", "--config", str(path), "--rate", "300", "--can-option", "port=2"]
    )
    config = run_config(args)
    assert config.rate_hz == 300
    assert dict(config.can.options or {}) == {"port": 2, "hop_limit": 0}
    assert config.source == str(path)


def test_bad_flag_is_named_as_the_flag() -> None:
    args = _parser().parse_args(["run", "--rate", "5000"])
    with pytest.raises(ConfigError, match=r"^command line: --rate: expected an integer 1..1000"):
        run_config(args)


def test_missing_and_malformed_files(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"no such config file"):
        read_config_file(tmp_path / "absent.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[output\nrate_hz = 1\n")
    with pytest.raises(ConfigError, match=r"bad.toml: not valid TOML"):
        read_config_file(bad)


def test_new_keys_defaults_and_values() -> None:
    defaults = build_config({}, "v.toml")
    assert defaults.output.arming_timeout_ms == 3000
    assert defaults.output.motor_test is False
    assert defaults.mavlink.command_senders is None
    assert defaults.mixer.valid_range is None
    config = build_config(
        {
            "output": {"arming_timeout_ms": 500, "motor_test": True},
            "mavlink": {"command_senders": [7, 255, 42]},
            "mixer": {"valid_range": [-2, 2.5]},
        },
        "v.toml",
    )
    assert config.output.arming_timeout_ms == 500
    assert config.output.motor_test is True
    assert config.mavlink.command_senders == (7, 255, 42)
    assert config.mixer.valid_range == (-2, 2.5)


def test_command_sender_ids() -> None:
    # By default a ground station (255) and the autopilot itself may send motor commands.
    assert build_config({}, "v").command_sender_ids == frozenset({1, 255})
    other_autopilot = build_config({"mavlink": {"autopilot_system_id": 3}}, "v")
    assert other_autopilot.command_sender_ids == frozenset({3, 255})
    given = build_config({"mavlink": {"command_senders": [200, 7]}}, "v")
    assert given.command_sender_ids == frozenset({7, 200})
