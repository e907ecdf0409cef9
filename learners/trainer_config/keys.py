"""The keys of ML-Agents' trainer config that ``learners.trainer_config.parse`` checks: each key's
value check (a one-line :class:`ConfigError` at the dotted key), and the keys ML-Agents has and we
do not implement, with the value that asks for what we do anyway."""

from __future__ import annotations

import difflib
import math
import os
import re
from collections.abc import Callable, Iterable, Mapping
from typing import Any

from learners.trainer_config.settings import (
    BehavioralCloningSettings,
    MemorySettings,
    NetworkSettings,
    RewardSignalSettings,
    SelfPlaySettings,
)

SCHEDULES = ("linear", "constant")
# ML-Agents' image encoders (learners.networks.encoders builds them; torch-free names here)
VIS_ENCODE_TYPES = ("simple", "nature_cnn", "resnet", "match3", "fully_connected")


class ConfigError(ValueError):
    """A trainer config we cannot run; the message is one line starting with the key path."""


def show(value: object) -> str:
    """``repr`` cut short, so a misplaced section still makes a one-line message."""
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def unknown_key(path: str, key: object, known: Iterable[str]) -> ConfigError:
    """An unknown key, with the closest known one when there is a likely match."""
    names = sorted(known)
    close = difflib.get_close_matches(str(key), names, n=1, cutoff=0.6)
    hint = f"did you mean {close[0]!r}?" if close else f"expected one of {', '.join(names)}"
    return ConfigError(
        f"{path}.{key}: unknown key; {hint}" if path else f"{key}: unknown key; {hint}"
    )


def section(path: str, value: object) -> Mapping[str, Any]:
    """A section: a mapping with string keys; ``null`` (an empty YAML section) is empty."""
    if value is None:
        return {}
    if not isinstance(value, Mapping):
        raise ConfigError(f"{path}: expected a mapping, got {show(value)}")
    for key in value:
        if not isinstance(key, str):
            raise ConfigError(f"{path}.{key}: keys must be strings")
    return value


# ---- value checks: each returns the parsed value or raises ConfigError at `path` ----------

_FLOAT_TEXT = re.compile(r"[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?")
Check = Callable[[str, object], Any]


def parse_number(path: str, value: object, what: str) -> float:
    """A finite number: ints, floats and the strings PyYAML leaves for ``3.0e-4``."""
    text_ok = isinstance(value, str) and _FLOAT_TEXT.fullmatch(value.strip()) is not None
    if isinstance(value, bool) or not (isinstance(value, int | float) or text_ok):
        raise ConfigError(f"{path}: expected {what}, got {show(value)}")
    number = float(value)  # type: ignore[arg-type]
    if not math.isfinite(number):
        raise ConfigError(f"{path}: expected {what}, got {show(value)}")
    return number


def float_in(
    low: float | None = None, high: float | None = None, *, open_low: bool = False
) -> Check:
    """A float check with an optional range (``open_low``: low itself excluded)."""
    if low is None:
        what = "a number"
    elif low == 0 and high is None:
        what = "a positive number" if open_low else "a number >= 0"
    else:
        what = f"a number in {'(' if open_low else '['}{low:g}, {high:g}]"

    def check(path: str, value: object) -> float:
        number = parse_number(path, value, what)
        if low is not None and (number < low or (open_low and number == low)):
            raise ConfigError(f"{path}: expected {what}, got {show(value)}")
        if high is not None and number > high:
            raise ConfigError(f"{path}: expected {what}, got {show(value)}")
        return number

    return check


def int_from(low: int = 1) -> Check:
    """An integer >= ``low``; ``5.0e5`` is accepted as 500000, ``1.5`` is not."""
    what = {1: "a positive integer", 0: "an integer >= 0"}.get(low, f"an integer >= {low}")

    def check(path: str, value: object) -> int:
        number = parse_number(path, value, what)
        if number != int(number) or number < low:
            raise ConfigError(f"{path}: expected {what}, got {show(value)}")
        return int(number)

    return check


def _bool(path: str, value: object) -> bool:
    if not isinstance(value, bool):
        raise ConfigError(f"{path}: expected true or false, got {show(value)}")
    return value


def _choice(*allowed: str) -> Check:
    def check(path: str, value: object) -> str:
        if value not in allowed:
            raise ConfigError(f"{path}: expected one of {', '.join(allowed)}, got {show(value)}")
        return str(value)

    return check


POSITIVE_INT, POSITIVE = int_from(1), float_in(0, open_low=True)

# hyperparameters every trainer type takes (learners.trainer_config.trainer_types adds each one's
# own)
SHARED: dict[str, Check] = {
    "batch_size": POSITIVE_INT,
    "buffer_size": POSITIVE_INT,
    "learning_rate": POSITIVE,
    "learning_rate_schedule": _choice(*SCHEDULES),
}
ON_POLICY: dict[str, Check] = {
    "beta": float_in(0),
    "beta_schedule": _choice(*SCHEDULES),
    "epsilon": POSITIVE,
    "epsilon_schedule": _choice(*SCHEDULES),
    "lambd": float_in(0, 1),
    "num_epoch": POSITIVE_INT,
}
# ML-Agents keys we do not implement, each with the value that asks for what we do anyway
# (not reported; ALWAYS: reported whatever the value)
ALWAYS = object()


def _memory(path: str, value: object) -> MemorySettings | None:
    """``memory``: ``memory_size`` (even: an LSTM's cell and hidden state halves) and
    ``sequence_length``, ML-Agents' defaults 128 and 64; ``null``: none."""
    if value is None:
        return None
    given = checked(path, value, {"memory_size": POSITIVE_INT, "sequence_length": POSITIVE_INT})
    if given.get("memory_size", 2) % 2:
        raise ConfigError(
            f"{path}.memory_size: expected an even number, got {given['memory_size']}"
        )
    return MemorySettings(**given)


NETWORK: dict[str, Check] = {
    "hidden_units": POSITIVE_INT,
    "num_layers": POSITIVE_INT,
    "normalize": _bool,
    "goal_conditioning_type": _choice("hyper", "none"),
    "vis_encode_type": _choice(*VIS_ENCODE_TYPES),
    "deterministic": _bool,
    "memory": _memory,
}


def _optional_path(path: str, value: object) -> str | None:
    if value is not None and (not isinstance(value, str) or not value.strip()):
        raise ConfigError(f"{path}: expected a checkpoint's path, got {show(value)}")
    return value


def checked(path: str, value: object, checks: Mapping[str, Check]) -> dict[str, Any]:
    """A section's keys, each through its check; an unknown one is the error."""
    given = {}
    for key, item in section(path, value).items():
        if key not in checks:
            raise unknown_key(path, key, checks)
        given[key] = checks[key](f"{path}.{key}", item)
    return given


def _self_play(path: str, value: object) -> SelfPlaySettings:
    """ML-Agents' ``self_play`` section; ``team_change`` defaults to 5 x ``save_steps``."""
    checks: dict[str, Check] = {
        "save_steps": POSITIVE_INT,
        "team_change": POSITIVE_INT,
        "swap_steps": POSITIVE_INT,
        "window": POSITIVE_INT,
        "play_against_latest_model_ratio": float_in(0, 1),
        "initial_elo": float_in(),
    }
    given = checked(path, value, checks)
    if "team_change" not in given:
        given["team_change"] = 5 * given.get("save_steps", SelfPlaySettings.save_steps)
    return SelfPlaySettings(**given)


def _behavioral_cloning(path: str, value: object) -> BehavioralCloningSettings:
    """ML-Agents' ``behavioral_cloning`` section; ``demo_path`` made absolute (the learner
    reads it in a process of its own; the driver reads the file where the run is
    planned)."""
    checks: dict[str, Check] = {
        "demo_path": _demo_path,
        "strength": float_in(0),
        "steps": int_from(0),
        "samples_per_update": int_from(0),
        "num_epoch": optional(POSITIVE_INT),
        "batch_size": optional(POSITIVE_INT),
    }
    given = checked(path, value, checks)
    if "demo_path" not in given:
        raise ConfigError(f"{path}.demo_path: required (a .demo file or a folder of them)")
    return BehavioralCloningSettings(**given)


def _demo_path(path: str, value: object) -> str:
    if not isinstance(value, str) or not value.strip():
        raise ConfigError(f"{path}: expected a .demo file or a folder of them, got {show(value)}")
    return os.path.abspath(os.path.expanduser(value))


def optional(check: Check) -> Check:
    """``check``, or None where the value is null."""
    return lambda path, value: None if value is None else check(path, value)


INTRINSIC = ("curiosity", "gail", "rnd")  # reward signals besides extrinsic (TrainerType.signals)
INTRINSIC_RATE = {"curiosity": 3.0e-4, "gail": 3.0e-4, "rnd": 1.0e-4}  # ML-Agents' defaults


def intrinsic_signal(path: str, kind: str, value: object) -> RewardSignalSettings:
    """A curiosity, gail or rnd section: ``gamma``, ``strength``, ``learning_rate``,
    ``encoding_size`` and the signal's own ``network_settings`` (ML-Agents' defaults);
    gail's ``demo_path`` (required), ``use_actions`` and ``use_vail``."""
    checks: dict[str, Check] = {
        "gamma": float_in(0, 1, open_low=True),
        "strength": float_in(0),
        "learning_rate": POSITIVE,
        "encoding_size": optional(POSITIVE_INT),
    }
    if kind == "gail":
        checks |= {"demo_path": _demo_path, "use_actions": _bool, "use_vail": _bool}
    given: dict[str, Any] = {"learning_rate": INTRINSIC_RATE[kind]}
    for key, item in section(path, value).items():
        if key == "network_settings":
            network = {}
            for name, setting in section(f"{path}.{key}", item).items():
                if name == "memory":  # ML-Agents ignores it here, with a warning
                    if setting is not None:
                        raise ConfigError(
                            f"{path}.{key}.memory: a reward signal's networks have no "
                            "memory (ML-Agents ignores it); remove it"
                        )
                elif name in NETWORK:
                    network[name] = NETWORK[name](f"{path}.{key}.{name}", setting)
                else:
                    raise unknown_key(f"{path}.{key}", name, NETWORK)
            given[key] = NetworkSettings(**network)
        elif key in checks:
            given[key] = checks[key](f"{path}.{key}", item)
        else:
            raise unknown_key(path, key, {*checks, "network_settings"})
    if kind == "gail" and "demo_path" not in given:
        raise ConfigError(f"{path}.demo_path: required (a .demo file or a folder of them)")
    return RewardSignalSettings(kind, **given)


TOP: dict[str, Check] = {
    "init_path": _optional_path,  # a checkpoint to start this behavior from
    "self_play": _self_play,
    "behavioral_cloning": _behavioral_cloning,
    "max_steps": POSITIVE_INT,
    "time_horizon": POSITIVE_INT,
    "summary_freq": POSITIVE_INT,
    "checkpoint_interval": POSITIVE_INT,
    "keep_checkpoints": POSITIVE_INT,
    "even_checkpoints": _bool,  # checkpoint_interval: max_steps / keep_checkpoints
    "threaded": _bool,  # workers collect through this behavior's updates (driver/system.py)
}
TOP_UNSUPPORTED: dict[str, object] = {}
SECTIONS = ("trainer_type", "hyperparameters", "network_settings", "reward_signals")
EXTRINSIC: dict[str, Check] = {"gamma": float_in(0, 1, open_low=True), "strength": float_in(0)}
REWARD_UNSUPPORTED: tuple[str, ...] = ()
ENGINE: dict[str, Check] = {
    "time_scale": POSITIVE,
    "width": POSITIVE_INT,
    "height": POSITIVE_INT,
    "quality_level": int_from(0),
    "target_frame_rate": int_from(-1),
    "capture_frame_rate": int_from(0),
    "no_graphics": _bool,
    "no_graphics_monitor": _bool,
}
ENGINE_UNSUPPORTED: tuple[str, ...] = ()
RUN_UNSUPPORTED: tuple[str, ...] = ()
# the run's own settings, as mlagents-learn reads them: the driver's options take and check
# them (driver/options.py), so they pass through here unread
RUN_SETTINGS = ("env_settings", "checkpoint_settings", "debug")
RUN_KEYS = (
    "behaviors",
    "default_settings",
    "engine_settings",
    "environment_parameters",
    "torch_settings",
)
