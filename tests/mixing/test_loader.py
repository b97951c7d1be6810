"""bridge.mixing.loader: bundled mixers and files; every invalid definition refused with its
file and entry."""

from __future__ import annotations

from pathlib import Path

import pytest
from _mixing import inputs, mix, one_output, write

from bridge.errors import ConfigError
from bridge.mixing.loader import bundled_mixer_names, load_mixer
from bridge.mixing.mixer import Mixer

# --------------------------------------------------------------------------------------------
# Bundled mixers


def test_bundled_names() -> None:
    assert bundled_mixer_names() == sorted(
        [
            "coax-x8",
            "hex-x",
            "octo-x",
            "passthrough-12",
            "passthrough-16",
            "passthrough-4",
            "passthrough-6",
            "passthrough-8",
            "quad-x",
        ]
    )


@pytest.mark.parametrize("name", bundled_mixer_names())
def test_every_bundled_mixer_loads_and_mixes(name: str) -> None:
    definition = load_mixer(name)
    assert definition.name == name  # the info key matches the file name
    assert definition.description
    mixer = Mixer(definition)
    vector = inputs([1500.0] * 32, roll=0.0, pitch=0.0, yaw=0.0, thrust=0.5)
    for armed in (False, True):
        out = mix(mixer, vector, armed)
        assert len(out) == mixer.n_outputs == len(definition.outputs)
        assert out == pytest.approx([0.5] * mixer.n_outputs)


@pytest.mark.parametrize("n", [4, 6, 8, 12, 16])
def test_passthrough_maps_channel_n_to_output_n(n: int) -> None:
    mixer = Mixer(load_mixer(f"passthrough-{n}"))
    assert mixer.n_outputs == n
    for k in range(n):
        for pwm_us, expected in ((1000.0, 0.0), (1500.0, 0.5), (2000.0, 1.0)):
            channels = [1250.0] * n
            channels[k] = pwm_us
            out = mix(mixer, inputs(channels))
            assert out[k] == pytest.approx(expected)
            assert all(v == pytest.approx(0.25) for i, v in enumerate(out) if i != k)


def test_passthrough_clamps_out_of_range_pulses() -> None:
    mixer = Mixer(load_mixer("passthrough-4"))
    assert mix(mixer, inputs([900.0, 2100.0, 0.0, 65535.0])) == [0.0, 1.0, 0.0, 1.0]


def test_out_of_range_channel_counts_as_its_end_in_a_sum(tmp_path: Path) -> None:
    # Clamped per input, so a glitching channel cannot push its partner's share around.
    mixer = one_output(tmp_path, "source = { ch1 = 0.5, ch2 = 0.5 }")
    assert mix(mixer, inputs([2500.0, 1000.0])) == pytest.approx([0.5])
    assert mix(mixer, inputs([500.0, 2000.0])) == pytest.approx([0.5])


def test_passthrough_ignores_channels_it_does_not_use() -> None:
    mixer = Mixer(load_mixer("passthrough-4"))
    vector = inputs([1500.0] * 4)  # ch5..ch32 and the axes are NaN
    assert mix(mixer, vector) == [0.5] * 4


def test_input_range_override_for_normalized_sources() -> None:
    unit = load_mixer("passthrough-4").with_input_range(0.0, 1.0)
    assert mix(Mixer(unit), inputs([0.0, 0.25, 1.0, 0.5])) == [0.0, 0.25, 1.0, 0.5]
    signed = load_mixer("passthrough-4", input_range=(-1.0, 1.0))
    assert mix(Mixer(signed), inputs([-1.0, 0.0, 1.0, 0.5])) == [0.0, 0.5, 1.0, 0.75]


def test_input_range_override_leaves_axis_only_outputs_alone() -> None:
    definition = load_mixer("quad-x")
    assert definition.with_input_range(0.0, 1.0) == definition


def test_input_range_override_is_validated() -> None:
    with pytest.raises(ConfigError, match=r"passthrough-4\.toml: input range override: .*< high"):
        load_mixer("passthrough-4").with_input_range(2000.0, 1000.0)


def test_unknown_bundled_name() -> None:
    with pytest.raises(ConfigError, match="unknown mixer 'quad-y'; bundled: coax-x8"):
        load_mixer("quad-y")


def test_missing_file(tmp_path: Path) -> None:
    missing = tmp_path / "absent.toml"
    with pytest.raises(ConfigError, match=r"absent\.toml: cannot read mixer"):
        load_mixer(str(missing))


def test_rotor_positions_are_kept_with_their_outputs() -> None:
    definition = load_mixer("quad-x")
    assert [o.name for o in definition.outputs] == [
        "front_right",
        "rear_left",
        "front_left",
        "rear_right",
    ]
    assert [r.direction for r in definition.rotors] == ["CCW", "CCW", "CW", "CW"]
    x, y, _ = definition.rotors[0].position_m
    assert x > 0.0 and y > 0.0  # motor 1 front right, in metres FRD


# --------------------------------------------------------------------------------------------
# Invalid definitions: each refused with the file and the entry named

PASSTHROUGH_HEAD = '[info]\ndescription = "bad"\n\n'
OUT1 = '[[outputs]]\nname = "m1"\nsource = "ch1"\n\n[[outputs]]\nname = "m2"\nsource = "ch2"\n\n'
QUAD_HEAD = '[info]\ndescription = "bad"\n[rotor_default]\ndirection = "CW"\n'


def rotors_text(*entries: str) -> str:
    return QUAD_HEAD + "".join(f"\n[[rotors]]\n{e}\n" for e in entries)


GOOD_QUAD = (
    'name = "a"\nposition = [1.0, 1.0, 0.0]\ndirection = "CCW"',
    'name = "b"\nposition = [-1.0, -1.0, 0.0]\ndirection = "CCW"',
    'name = "c"\nposition = [1.0, -1.0, 0.0]',
    'name = "d"\nposition = [-1.0, 1.0, 0.0]',
)

INVALID = {
    "unknown input": (
        PASSTHROUGH_HEAD + OUT1 + '[[outputs]]\nname = "m3"\nsource = "ch33"\n',
        "output 3 ('m3'): source: unknown input 'ch33'",
    ),
    "unknown input in weights": (
        PASSTHROUGH_HEAD + '[[outputs]]\nname = "m1"\nsource = { rol = 1.0 }\n',
        "output 1 ('m1'): source: unknown input 'rol'",
    ),
    "weights as an array": (
        PASSTHROUGH_HEAD + '[[outputs]]\nname = "m1"\nsource = [1.0, 0.5]\n',
        "output 1 ('m1'): source must be an input name",
    ),
    "weight not a number": (
        PASSTHROUGH_HEAD + '[[outputs]]\nname = "m1"\nsource = { ch1 = "1" }\n',
        "output 1 ('m1'): source weight of 'ch1' must be a number",
    ),
    "empty weights": (
        PASSTHROUGH_HEAD + '[[outputs]]\nname = "m1"\nsource = {}\n',
        "output 1 ('m1'): source names no input",
    ),
    "min above max": (
        PASSTHROUGH_HEAD
        + OUT1
        + '[[outputs]]\nname = "m3"\nsource = "ch3"\nmin = 0.8\nmax = 0.2\n',
        "output 3 ('m3'): min 0.8 > max 0.2",
    ),
    "max beyond 1": (
        PASSTHROUGH_HEAD + '[[outputs]]\nname = "m1"\nsource = "ch1"\nmax = 1.5\n',
        "output 1 ('m1'): max 1.5 outside -1..1",
    ),
    "range without stop": (
        PASSTHROUGH_HEAD + '[[outputs]]\nname = "m1"\nsource = "ch1"\nmin = 0.1\n',
        "output 1 ('m1'): [min 0.1, max 1] must contain 0",
    ),
    "idle outside range": (
        PASSTHROUGH_HEAD + '[[outputs]]\nname = "m1"\nsource = "ch1"\nidle = -0.1\n',
        "output 1 ('m1'): idle -0.1 outside [min 0, max 1]",
    ),
    "input range reversed": (
        PASSTHROUGH_HEAD + '[[outputs]]\nname = "m1"\nsource = "ch1"\ninput_range = [2000, 1000]\n',
        "output 1 ('m1'): input_range low 2000 must be < high 1000",
    ),
    "input range beyond limits": (
        PASSTHROUGH_HEAD + '[[outputs]]\nname = "m1"\nsource = "ch1"\ninput_range = [0, 70000]\n',
        "output 1 ('m1'): input_range [0, 70000] outside -1..65535",
    ),
    "input range shape": (
        PASSTHROUGH_HEAD + '[[outputs]]\nname = "m1"\nsource = "ch1"\ninput_range = [1000]\n',
        "output 1 ('m1'): input_range must be an array of 2 numbers",
    ),
    "deadband too large": (
        PASSTHROUGH_HEAD + '[[outputs]]\nname = "m1"\nsource = "ch1"\ndeadband = 1.0\n',
        "output 1 ('m1'): deadband 1 outside 0 <= deadband < 1",
    ),
    "negative slew": (
        PASSTHROUGH_HEAD + '[[outputs]]\nname = "m1"\nsource = "ch1"\nslew_down = -1\n',
        "output 1 ('m1'): slew_down -1 must be >= 0",
    ),
    "offset too large": (
        PASSTHROUGH_HEAD + '[[outputs]]\nname = "m1"\nsource = "ch1"\noffset = 2.0\n',
        "output 1 ('m1'): offset 2 outside -1..1",
    ),
    "bool for a number": (
        PASSTHROUGH_HEAD + '[[outputs]]\nname = "m1"\nsource = "ch1"\nmax = true\n',
        "output 1 ('m1'): max must be a number, got True",
    ),
    "string for a bool": (
        PASSTHROUGH_HEAD + '[[outputs]]\nname = "m1"\nsource = "ch1"\nreversed = "yes"\n',
        "output 1 ('m1'): reversed must be true or false",
    ),
    "unknown output key": (
        PASSTHROUGH_HEAD + OUT1 + '[[outputs]]\nname = "m3"\nsource = "ch3"\nrevresed = true\n',
        "output 3 ('m3'): unknown key 'revresed' in an output",
    ),
    "unknown default key": (
        PASSTHROUGH_HEAD + "[output_default]\nidel = 0.1\n\n" + OUT1,
        "output_default: unknown key 'idel'",
    ),
    "unknown top-level key": (
        PASSTHROUGH_HEAD + OUT1 + "[mixer]\nx = 1\n",
        "top level: unknown key 'mixer'",
    ),
    "duplicate key": (
        PASSTHROUGH_HEAD + OUT1 + '[[outputs]]\nname = "m3"\nsource = "ch3"\nsource = "ch4"\n',
        "invalid TOML: Cannot overwrite a value (at line 15, column 15): 'source = \"ch4\"'",
    ),
    "duplicate weight": (
        PASSTHROUGH_HEAD + '[[outputs]]\nname = "m1"\nsource = { ch1 = 1.0, ch1 = 0.5 }\n',
        "invalid TOML: Duplicate inline table key 'ch1'",
    ),
    "duplicate output name": (
        PASSTHROUGH_HEAD + OUT1 + '[[outputs]]\nname = "m1"\nsource = "ch3"\n',
        "output 3 ('m1'): name already used by output 1",
    ),
    "missing name": (
        PASSTHROUGH_HEAD + OUT1 + '[[outputs]]\nsource = "ch3"\n',
        "output 3: missing key 'name'",
    ),
    "missing source": (
        PASSTHROUGH_HEAD + '[[outputs]]\nname = "m1"\n',
        "output 1 ('m1'): missing key 'source'",
    ),
    "outputs not an array": (
        "outputs = 3\n" + PASSTHROUGH_HEAD,
        "outputs: outputs must be an array of tables",
    ),
    "too many outputs": (
        PASSTHROUGH_HEAD
        + "".join(f'[[outputs]]\nname = "m{i}"\nsource = "ch1"\n' for i in range(1, 34)),
        "33 outputs; a mixer has 1..32",
    ),
    "no outputs": (PASSTHROUGH_HEAD, "defines no outputs"),
    "missing description": ('[info]\nkey = "x"\n' + OUT1, "info: description must be"),
    "missing info": (OUT1, "info: [info] must be a table"),
    "bad key": ('[info]\nkey = "my frame"\ndescription = "d"\n' + OUT1, "info: key 'my frame'"),
    "syntax error": (PASSTHROUGH_HEAD + "[[outputs]\n", "invalid TOML"),
    "rotor direction": (
        rotors_text(*GOOD_QUAD[:3], 'name = "d"\nposition = [-1.0, 1.0, 0.0]\ndirection = "cw"'),
        "rotor 4 ('d'): direction must be 'CW' or 'CCW', got 'cw'",
    ),
    "rotor position shape": (
        rotors_text(*GOOD_QUAD[:3], 'name = "d"\nposition = [-1.0, 1.0]'),
        "rotor 4 ('d'): position must be an array of 3 numbers",
    ),
    "rotor missing position": (
        rotors_text(*GOOD_QUAD[:3], 'name = "d"'),
        "rotor 4 ('d'): missing key 'position'",
    ),
    "rotor missing direction": (
        '[info]\ndescription = "bad"\n[[rotors]]\nname = "a"\nposition = [1.0, 1.0, 0.0]\n',
        "rotor 1 ('a'): missing key 'direction'",
    ),
    "rotor zero axis": (
        rotors_text(*GOOD_QUAD[:3], GOOD_QUAD[3] + "\naxis = [0.0, 0.0, 0.0]"),
        "rotor 4 ('d'): axis must not be the zero vector",
    ),
    "rotor ct": (
        rotors_text(GOOD_QUAD[0] + "\nCt = 0.0", *GOOD_QUAD[1:]),
        "rotor 1 ('a'): Ct 0 must be > 0",
    ),
    "rotor negative cm": (
        rotors_text(GOOD_QUAD[0] + "\nCm = -0.05", *GOOD_QUAD[1:]),
        "rotor 1 ('a'): Cm -0.05 must be >= 0",
    ),
    "rotor reversed": (
        rotors_text(GOOD_QUAD[0] + "\nreversed = true", *GOOD_QUAD[1:]),
        "rotor 1 ('a'): unknown key 'reversed' in a rotor",
    ),
    "rotor idle above max": (
        rotors_text(*GOOD_QUAD[:2], GOOD_QUAD[2] + "\nidle = 0.5\nmax = 0.3", GOOD_QUAD[3]),
        "rotor 3 ('c'): idle 0.5 outside [min 0, max 0.3]",
    ),
    "rotor default unknown key": (
        rotors_text(*GOOD_QUAD).replace(
            "[rotor_default]\n", "[rotor_default]\nposition = [0, 0, 0]\n"
        ),
        "rotor_default: unknown key 'position'",
    ),
    "geometry cannot yaw": (
        rotors_text(*(r.replace('direction = "CCW"', 'direction = "CW"') for r in GOOD_QUAD)),
        "rotors: the rotors cannot produce roll, pitch, yaw and thrust independently",
    ),
    "geometry cannot roll": (
        rotors_text(
            'name = "a"\nposition = [1.0, 0.0, 0.0]\ndirection = "CCW"',
            'name = "b"\nposition = [-1.0, 0.0, 0.0]',
        ),
        "rotors: no rotor produces roll torque",
    ),
    "rotor and output share a name": (
        rotors_text(*GOOD_QUAD) + '\n[[outputs]]\nname = "a"\nsource = "ch5"\n',
        "output 5 ('a'): name already used by output 1",
    ),
}


@pytest.mark.parametrize("case", sorted(INVALID))
def test_invalid_definition_is_refused_with_file_and_entry(tmp_path: Path, case: str) -> None:
    text, expected = INVALID[case]
    path = write(tmp_path, text, name="broken.toml")
    with pytest.raises(ConfigError) as caught:
        load_mixer(path)
    message = str(caught.value)
    assert message.startswith(f"{path}: "), message
    assert expected in message, message


def test_invalid_utf8_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "latin1.toml"
    path.write_bytes(b'[info]\ndescription = "caf\xe9"\n')
    with pytest.raises(ConfigError, match=r"latin1\.toml: not UTF-8"):
        load_mixer(str(path))


def test_valid_mixed_file_numbers_rotors_first(tmp_path: Path) -> None:
    text = rotors_text(*GOOD_QUAD) + '\n[[outputs]]\nname = "gimbal"\nsource = "ch5"\n'
    definition = load_mixer(write(tmp_path, text))
    assert [o.name for o in definition.outputs] == ["a", "b", "c", "d", "gimbal"]
    out = mix(Mixer(definition), inputs([1000.0] * 4 + [1750.0], 0.0, 0.0, 0.0, 0.5))
    assert out == pytest.approx([0.5, 0.5, 0.5, 0.5, 0.75])
