"""The README, docs/ and the config/ and mixers/ READMEs hold what they show: links lead to
files and headings that exist, every ``esc-bridge`` command in a ``sh`` block parses with the
real command line, every ``sh`` block is valid shell, every TOML block parses (a configuration
through the bridge's own loader), and the files of docs/hardware.md are what systemd and the
Raspberry Pi firmware read."""

from __future__ import annotations

import argparse
import configparser
import contextlib
import io
import re
import shlex
import shutil
import subprocess
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from bridge.cli import build_parser
from bridge.config import build_config, documented_keys
from bridge.config_file import read_config_file

ROOT = Path(__file__).resolve().parent.parent
PAGES = [
    ROOT / "README.md",
    *sorted((ROOT / "docs").glob("*.md")),
    ROOT / "config" / "README.md",
    ROOT / "mixers" / "README.md",
]
HARDWARE = ROOT / "docs" / "hardware.md"

# The bridge's accepted bit rates (`[can] bitrate`), and the one the docs bring the bus up at.
BIT_RATE = 500_000


@dataclass(frozen=True)
class Block:
    page: Path
    line: int  # of the opening fence, 1-based
    lang: str
    text: str

    def where(self) -> str:
        return f"{self.page.relative_to(ROOT)}:{self.line}"


def _blocks(page: Path) -> list[Block]:
    """Every fenced block of a page, its content dedented as a list item's block is."""
    blocks: list[Block] = []
    lines = page.read_text(encoding="utf-8").split("\n")
    start: tuple[int, str, int] | None = None  # line, language, indent
    body: list[str] = []
    for number, line in enumerate(lines, 1):
        stripped = line.lstrip(" ")
        if start is None:
            if stripped.startswith("```"):
                start = (number, stripped[3:].strip(), len(line) - len(stripped))
                body = []
        elif stripped.startswith("```"):
            blocks.append(Block(page, start[0], start[1], "\n".join(body) + "\n"))
            start = None
        else:
            body.append(line[start[2] :] if line[: start[2]].strip() == "" else line)
    assert start is None, f"{page.relative_to(ROOT)}:{start[0]}: a code block is not closed"
    return blocks


def _blocks_of(lang: str) -> list[Block]:
    return [block for page in PAGES for block in _blocks(page) if block.lang == lang]


def _prose(page: Path) -> str:
    """The page without its fenced blocks (links in code are not links)."""
    return re.sub(r"^ *```.*?^ *```", "", page.read_text(encoding="utf-8"), flags=re.S | re.M)


# -- links ------------------------------------------------------------------------------------


def _slug(heading: str) -> str:
    """A heading's anchor as GitHub makes it: lower case, punctuation dropped, spaces to '-'."""
    text = heading.strip().lower().replace("`", "")
    return re.sub(r"[^\w\- ]", "", text).replace(" ", "-")


def _anchors(page: Path) -> set[str]:
    """Every heading's anchor; a repeated heading's gets -1, -2, ... as on GitHub."""
    anchors: set[str] = set()
    seen: Counter[str] = Counter()
    for heading in re.findall(r"^#{1,6} (.+)$", _prose(page), re.M):
        slug = _slug(heading)
        anchors.add(f"{slug}-{seen[slug]}" if seen[slug] else slug)
        seen[slug] += 1
    return anchors


def _links() -> Iterator[tuple[Path, str]]:
    for page in PAGES:
        for target in re.findall(r"\]\(([^)\s]+)\)", _prose(page)):
            if not re.match(r"[a-z]+:", target):  # http:, https:, mailto: are not checked here
                yield page, target


def test_every_relative_link_leads_to_a_file_and_heading_that_exist() -> None:
    links = list(_links())
    assert len(links) > 50, "the pages link to each other"
    broken = []
    for page, target in links:
        path_part, _, anchor = target.partition("#")
        path = (page.parent / path_part).resolve() if path_part else page
        name = path.relative_to(ROOT).as_posix() if path.is_relative_to(ROOT) else str(path)
        if not path.exists():
            broken.append(f"{page.relative_to(ROOT)}: {target}: no file {name}")
        elif anchor and path.suffix == ".md" and anchor not in _anchors(path):
            broken.append(f"{page.relative_to(ROOT)}: {target}: no heading #{anchor} in {name}")
    assert broken == []


def test_the_slug_is_githubs() -> None:
    assert _slug("Recording a flight: `--record DIR`") == "recording-a-flight---record-dir"
    assert _slug("Plotting it: `esc-bridge plot RECORDING_DIR`") == (
        "plotting-it-esc-bridge-plot-recording_dir"
    )
    assert _slug("Installing ESCs, step by step") == "installing-escs-step-by-step"


# -- sh blocks --------------------------------------------------------------------------------

SH_BLOCKS = _blocks_of("sh")
# Tokens that end one simple command and start the next, and redirections (their next token is
# a file name, not an argument).
_SEPARATORS = {"&&", "||", ";", "|", "&", "(", ")"}
_REDIRECTS = {">", ">>", "<", "2>", "&>"}


def _commands(script: str) -> Iterator[list[str]]:
    """The simple commands of a shell script, each as its words (no quoting, no comments)."""
    for line in script.replace("\\\n", " ").split("\n"):
        lexer = shlex.shlex(line, posix=True, punctuation_chars=True)
        lexer.whitespace_split = True
        words: list[str] = []
        skip_next = False
        for token in lexer:
            if skip_next:
                skip_next = False
            elif token in _SEPARATORS:
                if words:
                    yield words
                words = []
            elif token in _REDIRECTS or token.endswith(">"):
                skip_next = True
            else:
                words.append(token)
        if words:
            yield words


def _bridge_argv(words: list[str]) -> list[str] | None:
    """The arguments of an ``esc-bridge`` command (after sudo and VAR=value), else None."""
    while words and (words[0] == "sudo" or re.fullmatch(r"[A-Z_][A-Z0-9_]*=\S*", words[0])):
        words = words[1:]
    if words and Path(words[0]).name == "esc-bridge":
        return words[1:]
    return None


BRIDGE_COMMANDS = [
    (block, argv)
    for block in SH_BLOCKS
    for words in _commands(block.text)
    if (argv := _bridge_argv(words)) is not None
]


def _problem(argv: list[str]) -> str | None:
    """Why ``esc-bridge ARGV`` would not parse, or use an option by another name; else None."""
    errors = io.StringIO()
    try:
        with contextlib.redirect_stderr(errors), contextlib.redirect_stdout(io.StringIO()):
            build_parser().parse_args(argv)
    except SystemExit as exc:  # argparse's way out: 0 after --help, 2 for a bad argument
        if exc.code != 0:
            return errors.getvalue().strip()
    parser = build_parser()  # the subcommand's own parser: argparse also takes a flag's prefix
    for word in argv:
        choices = [
            action.choices
            for action in parser._actions
            if isinstance(action, argparse._SubParsersAction)
        ]
        if choices and isinstance(choices[0], dict) and word in choices[0]:
            parser = choices[0][word]
    known = {option for action in parser._actions for option in action.option_strings}
    for word in argv:
        flag = word.split("=", 1)[0]
        if flag.startswith("--") and flag not in known:
            return f"{flag} is not an option of `{parser.prog}` (only the start of one?)"
    return None


def test_the_pages_show_commands() -> None:
    assert len(SH_BLOCKS) >= 25
    assert len(BRIDGE_COMMANDS) >= 30
    shown = {argv[0] for _, argv in BRIDGE_COMMANDS if argv and not argv[0].startswith("-")}
    assert shown >= {"run", "decode", "monitor", "sim", "demo", "esc", "plot", "mavlink-dialect"}


def test_ci_runs_the_readmes_two_first_commands_test_line_verbatim() -> None:
    """The README starts with the set-up-and-demo command and the set-up-and-test command, and
    .ci/run runs the second one as written (so what CI installs is what a new user installs)."""
    readme = [b for b in _blocks(ROOT / "README.md") if b.lang == "sh"]
    demo, tests = readme[0].text.strip(), readme[1].text.strip()
    assert demo.endswith("esc-bridge demo") and "\n" not in demo, demo
    assert tests.endswith("-m pytest") and "\n" not in tests, tests
    ci_lines = (ROOT / ".ci" / "run").read_text(encoding="utf-8").splitlines()
    assert tests in ci_lines, f".ci/run does not run the README's test command: {tests}"


@pytest.mark.parametrize(
    ("block", "argv"),
    BRIDGE_COMMANDS,
    ids=[f"{b.where()}:{' '.join(a[:2])}" for b, a in BRIDGE_COMMANDS],
)
def test_every_bridge_command_shown_parses(block: Block, argv: list[str]) -> None:
    assert _problem(argv) is None, f"{block.where()}: esc-bridge {' '.join(argv)}"


def test_the_repository_files_the_commands_name_exist() -> None:
    named = {
        word
        for block in SH_BLOCKS
        for words in _commands(block.text)
        for word in words
        if re.match(r"(config|mixers|autopilot|bench|tests)/", word)
    }
    assert "config/quad-ckesc.toml" in named
    assert [name for name in sorted(named) if not (ROOT / name).exists()] == []


def test_a_wrong_command_is_caught() -> None:
    (words,) = _commands("sudo .venv/bin/esc-bridge esc spin --motor 1 --bitrat 500000  # typo\n")
    argv = _bridge_argv(words)
    assert argv == ["esc", "spin", "--motor", "1", "--bitrat", "500000"]
    argv += ["--throttle", "10", "--seconds", "3"]
    assert _problem(argv) == (
        "--bitrat is not an option of `esc-bridge esc spin` (only the start of one?)"
    )
    assert "unrecognized arguments: --nope" in str(_problem(["run", "--nope"]))
    assert "invalid choice: 'fly'" in str(_problem(["fly"]))
    assert _problem(["esc", "spin", "--bitrate", "500000", "--motor", "1"]) is not None
    assert _problem(["--help"]) is None


@pytest.mark.parametrize("block", SH_BLOCKS, ids=[b.where() for b in SH_BLOCKS])
def test_every_sh_block_is_valid_shell(block: Block) -> None:
    result = subprocess.run(
        ["bash", "-n"], input=block.text, capture_output=True, text=True, check=False
    )
    assert result.returncode == 0, f"{block.where()}: {result.stderr}"


# -- TOML blocks ------------------------------------------------------------------------------

TOML_BLOCKS = _blocks_of("toml")
SECTIONS = {section for section, _, _, _ in documented_keys()}


@pytest.mark.parametrize("block", TOML_BLOCKS, ids=[b.where() for b in TOML_BLOCKS])
def test_every_toml_block_parses_and_a_configuration_loads(block: Block, tmp_path: Path) -> None:
    path = tmp_path / "block.toml"
    path.write_text(block.text, encoding="utf-8")
    raw = read_config_file(path)
    assert raw, f"{block.where()}: an empty block"
    if set(raw) <= SECTIONS:  # sections of the bridge's configuration: the rest are defaults
        build_config(raw, block.where())


def test_there_are_configuration_blocks() -> None:
    assert len(TOML_BLOCKS) >= 2


# -- docs/hardware.md: the files systemd and the firmware read --------------------------------

# systemd.network(5) of systemd 252 (Debian 12, Raspberry Pi OS Bookworm): the keys the page may
# use in each section.
NETWORK_KEYS = {
    "Match": {"Name", "Kind", "Driver", "Path", "Type"},
    "CAN": {"BitRate", "SamplePoint", "RestartSec", "Termination", "TripleSampling"},
    "Link": {"RequiredForOnline", "ActivationPolicy"},
}
HARDWARE_BLOCKS = _blocks(HARDWARE)


def _ini(block: Block) -> configparser.ConfigParser:
    parser = configparser.ConfigParser(interpolation=None, delimiters=("=",))
    parser.optionxform = str  # type: ignore[assignment,method-assign]  # keys keep their case
    parser.read_string(block.text, source=block.where())
    return parser


def _si(value: str) -> float:
    """systemd's number with an SI prefix of base 1000: 500K, 1M."""
    number = re.fullmatch(r"(\d+(?:\.\d+)?)([KMG]?)", value)
    assert number is not None, f"not a number with K/M/G: {value!r}"
    return float(number.group(1)) * {"": 1, "K": 1e3, "M": 1e6, "G": 1e9}[number.group(2)]


def test_the_network_file_has_systemds_sections_and_keys() -> None:
    (network,) = [b for b in HARDWARE_BLOCKS if b.lang == "ini" and b.text.startswith("[Match]")]
    ini = _ini(network)
    assert set(ini.sections()) <= set(NETWORK_KEYS), ini.sections()
    for section in ini.sections():
        assert set(ini[section]) <= NETWORK_KEYS[section], (section, set(ini[section]))
    assert ini["Match"]["Name"] == "can0"
    assert _si(ini["CAN"]["BitRate"]) == BIT_RATE
    assert re.fullmatch(r"\d+(ms|s|us)", ini["CAN"]["RestartSec"])
    assert ini["Link"]["RequiredForOnline"] in ("no", "false", "0")


def _unit() -> Block:
    (unit,) = [b for b in HARDWARE_BLOCKS if b.lang == "ini" and b.text.startswith("[Unit]")]
    return unit


def test_the_can_unit_brings_can0_up_as_the_page_does_by_hand() -> None:
    ini = _ini(_unit())
    assert ini["Service"]["Type"] == "oneshot"
    program, *arguments = shlex.split(ini["Service"]["ExecStart"])
    by_hand = [
        words[1:] if words[0] == "sudo" else words
        for b in HARDWARE_BLOCKS
        if b.lang == "sh"
        for words in _commands(b.text)
    ]
    assert [Path(program).name, *arguments] in by_hand  # the page's `ip link set can0 up ...`
    device = "sys-subsystem-net-devices-can0.device"
    assert ini["Unit"]["BindsTo"] == ini["Unit"]["After"] == ini["Install"]["WantedBy"] == device


def test_the_can_unit_passes_systemd_analyze_verify(tmp_path: Path) -> None:
    unit = tmp_path / "can0.service"
    unit.write_text(_unit().text, encoding="utf-8")
    analyze = shutil.which("systemd-analyze")
    if analyze is None:  # no systemd here: the INI checks above are all that can be made
        return
    result = subprocess.run(
        [analyze, "verify", str(unit)], capture_output=True, text=True, check=False
    )
    output = result.stdout + result.stderr
    assert result.returncode == 0, output
    assert unit.name not in output  # an unknown key or a bad value is only a warning


# `ip link set DEVICE type can` options, from iproute2 6.1's `ip link help can`.
IP_LINK_CAN_OPTIONS = {"bitrate", "sample-point", "restart-ms", "listen-only", "termination"}


def test_the_ip_link_commands_use_options_iproute2_knows() -> None:
    commands = [
        words[words.index("link") :]
        for block in _blocks_of("sh")
        for words in _commands(block.text)
        if "ip" in words and "type" in words and "can" in words
    ]
    assert len(commands) >= 3
    used = set()
    for words in commands:
        assert words[:3] == ["link", "set", "can0"], words
        options = words[words.index("can") + 1 :]
        used |= set(options[::2])
        assert all(value.replace(".", "").isdigit() for value in options[1::2]), words
    assert used <= IP_LINK_CAN_OPTIONS, used - IP_LINK_CAN_OPTIONS
    ip = shutil.which("ip")
    if ip is not None:  # and this machine's iproute2 still knows them
        usage = subprocess.run(
            [ip, "link", "help", "can"], capture_output=True, text=True, check=False
        )
        for option in used:
            assert f"[ {option} " in usage.stdout + usage.stderr, option


def test_one_bit_rate_on_the_hardware_page() -> None:
    text = HARDWARE.read_text(encoding="utf-8")
    rates = {int(rate) for rate in re.findall(r"\bbitrate (\d+)", text)}
    rates |= {int(_si(rate)) for rate in re.findall(r"^BitRate=(\S+)$", text, re.M)}
    assert rates == {BIT_RATE}


def test_the_mcp2515_overlays_name_a_crystal_and_a_gpio() -> None:
    text = HARDWARE.read_text(encoding="utf-8")
    overlays = re.findall(r"dtoverlay=mcp2515-can([01]),([^`\s]+)", text)
    assert len(overlays) >= 5
    for channel, parameters in overlays:
        values = dict(item.split("=", 1) for item in parameters.split(","))
        assert set(values) == {"oscillator", "interrupt"}, (channel, parameters)
        assert int(values["oscillator"]) in (8_000_000, 12_000_000, 16_000_000, 20_000_000)
        assert 0 <= int(values["interrupt"]) <= 27  # a BCM GPIO on the 40-pin header
    for block in HARDWARE_BLOCKS:
        if block.lang == "text":  # config.txt lines: key=value, no section, no spaces
            for line in block.text.strip().split("\n"):
                assert re.fullmatch(r"(dtparam|dtoverlay|enable_uart)=\S+", line), line
