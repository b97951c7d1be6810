"""Helpers shared by the tests of bridge.mixing: input vectors, mixing, mixer files."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

from bridge.mixing.definition import INPUT_NAMES
from bridge.mixing.loader import load_mixer
from bridge.mixing.mixer import Mixer

NAN = math.nan
GEOMETRY_MIXERS = ("quad-x", "hex-x", "octo-x", "coax-x8")
S3_2 = math.sqrt(3.0) / 2.0


def inputs(
    channels: Sequence[float] = (),
    roll: float = NAN,
    pitch: float = NAN,
    yaw: float = NAN,
    thrust: float = NAN,
) -> list[float]:
    """A 36-entry input vector: the given channels from ch1 on, NaN for the rest."""
    vector = [*channels, *[NAN] * (32 - len(channels)), roll, pitch, yaw, thrust]
    assert len(vector) == len(INPUT_NAMES)
    return vector


def axes(
    roll: float = 0.0, pitch: float = 0.0, yaw: float = 0.0, thrust: float = 0.5
) -> list[float]:
    return inputs(roll=roll, pitch=pitch, yaw=yaw, thrust=thrust)


def mix(mixer: Mixer, vector: Sequence[float], armed: bool = False) -> list[float]:
    result = mixer.mix(vector, armed)
    assert result is not None
    return result


def write(tmp_path: Path, text: str, name: str = "frame.toml") -> str:
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return str(path)


def one_output(tmp_path: Path, keys: str) -> Mixer:
    """A mixer with a single direct output 'm1' whose keys are ``keys``."""
    text = f'[info]\ndescription = "test"\n\n[[outputs]]\nname = "m1"\n{keys}\n'
    return Mixer(load_mixer(write(tmp_path, text)))
