"""ML-Agents trainer-config YAML (``behaviors:``, ``default_settings:`` ...) for our learners.

As in ``mlagents-learn``, a behavior's settings are merged over ``default_settings``, over
the defaults of its trainer type, section by section. Everything is checked at load time,
so a typo fails with one line naming the dotted key (and the key probably meant).

- Errors (:class:`ConfigError`): unknown keys, bad types or ranges, another trainer's
  hyperparameter.
- Reported (``RunConfig.unsupported``, one ``logging.warning``): what a trainer type lacks
  (``memory`` or an intrinsic signal under POCA or IMPALA) and an extrinsic signal's
  ``network_settings`` (no network reads it); training goes on without them. Values that ask for
  what we do anyway (``memory: null`` ...) are not reported. All five of ML-Agents'
  ``vis_encode_type`` values are implemented (``learners.networks.encoders``). Environment
  parameters (numbers, samplers, curricula) are read by
  ``learners.trainer_config.environment_parameters``.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from types import MappingProxyType
from typing import Any

import yaml

from batches.contracts import base_name
from batches.parameters import Curriculum
from learners.host.devices import DeviceError, check_device
from learners.trainer_config.environment_parameters import parse_environment_parameters
from learners.trainer_config.keys import (
    ALWAYS,
    ENGINE,
    ENGINE_UNSUPPORTED,
    EXTRINSIC,
    INTRINSIC,
    NETWORK,
    REWARD_UNSUPPORTED,
    RUN_KEYS,
    RUN_SETTINGS,
    RUN_UNSUPPORTED,
    SECTIONS,
    TOP,
    TOP_UNSUPPORTED,
    ConfigError,
    intrinsic_signal,
    section,
    show,
    unknown_key,
)
from learners.trainer_config.settings import RewardSignalSettings, RunConfig, TrainerSettings
from learners.trainer_config.trainer_types import TRAINERS

logger = logging.getLogger(__name__)
DEFAULTS = "<defaults>"  # the source of a run without a config file

CONFIG_DIR = Path(__file__).resolve().parents[2] / "config"  # the repository's config/


def defaults(trainer_type: str = "ppo") -> TrainerSettings:
    """ML-Agents' defaults for ``trainer_type``."""
    if trainer_type not in TRAINERS:
        raise ConfigError(f"trainer_type: {_trainer_type_problem(trainer_type)}")
    return TRAINERS[trainer_type].settings()


def _all_hyper_keys() -> set[str]:
    return {k for t in TRAINERS.values() for k in (*t.hyperparameters, *t.unsupported)}


def _trainer_type_problem(value: object) -> str:
    return f"expected one of {', '.join(TRAINERS)}, got {show(value)}"


def _ignored_value(value: object, neutral: object) -> bool:
    """Whether an unsupported key's value is what we do anyway (so nothing to report)."""
    return neutral is not ALWAYS and value == neutral


# ---- layers: one trainer-settings mapping, checked and parsed but not merged --------------


@dataclass
class _Layer:
    """What one ``default_settings`` or behavior section sets, parsed, by section."""

    trainer_type: str | None = None
    hyper: dict[str, Any] = field(default_factory=dict)
    network: dict[str, Any] = field(default_factory=dict)
    extrinsic: dict[str, Any] = field(default_factory=dict)
    intrinsic: dict[str, RewardSignalSettings] = field(default_factory=dict)
    signals: set[str] | None = None  # the reward signals it names (None: no reward_signals)
    top: dict[str, Any] = field(default_factory=dict)


def _parse_layer(path: str, raw: object, inherited_type: str, unsupported: list[str]) -> _Layer:
    """Check one trainer-settings section against ``trainer_type`` (its own or inherited)."""
    data = section(path, raw)
    layer = _Layer()
    known = {*SECTIONS, *TOP, *TOP_UNSUPPORTED}
    for key in data:
        if key not in known:
            raise unknown_key(path, key, known)
    if "trainer_type" in data:
        value = data["trainer_type"]
        if value not in TRAINERS:
            raise ConfigError(f"{path}.trainer_type: {_trainer_type_problem(value)}")
        layer.trainer_type = value
    trainer_type = layer.trainer_type or inherited_type
    for key, check in TOP.items():
        if key in data:
            layer.top[key] = check(f"{path}.{key}", data[key])
    for key, neutral in TOP_UNSUPPORTED.items():
        if key in data and not _ignored_value(data[key], neutral):
            unsupported.append(f"{path}.{key}")

    hyper_path = f"{path}.hyperparameters"
    kind = TRAINERS[trainer_type]
    checks, extra = kind.hyperparameters, kind.unsupported
    for key, value in section(hyper_path, data.get("hyperparameters")).items():
        if key in checks:
            layer.hyper[key] = checks[key](f"{hyper_path}.{key}", value)
        elif key in extra:
            if not _ignored_value(value, extra[key]):
                unsupported.append(f"{hyper_path}.{key}")
        elif key in _all_hyper_keys():
            owners = [n for n, t in TRAINERS.items() if key in (*t.hyperparameters, *t.unsupported)]
            only = ", ".join(owners)
            raise ConfigError(
                f"{hyper_path}.{key}: not a {trainer_type} hyperparameter ({only} only)"
            )
        else:
            raise unknown_key(hyper_path, key, {*checks, *extra})

    net_path = f"{path}.network_settings"
    for key, value in section(net_path, data.get("network_settings")).items():
        if key not in NETWORK:
            raise unknown_key(net_path, key, NETWORK)
        parsed = NETWORK[key](f"{net_path}.{key}", value)
        if key == "memory" and parsed is not None and kind.recurrent is None:
            unsupported.append(f"{net_path}.{key}")
        else:
            layer.network[key] = parsed

    reward_path = f"{path}.reward_signals"
    if "reward_signals" in data:
        layer.signals = set(section(reward_path, data["reward_signals"]))
    for key, value in section(reward_path, data.get("reward_signals")).items():
        if key in INTRINSIC:
            signal = intrinsic_signal(f"{reward_path}.{key}", key, value)
            if kind.signals:
                layer.intrinsic[key] = signal
            else:
                unsupported.append(f"{reward_path}.{key}")
        elif key in REWARD_UNSUPPORTED:
            unsupported.append(f"{reward_path}.{key}")
        elif key == "extrinsic":
            signal_path = f"{reward_path}.extrinsic"
            for name, item in section(signal_path, value).items():
                if name in EXTRINSIC:
                    layer.extrinsic[name] = EXTRINSIC[name](f"{signal_path}.{name}", item)
                elif name == "network_settings":
                    unsupported.append(f"{signal_path}.{name}")
                else:
                    raise unknown_key(signal_path, name, {*EXTRINSIC, "network_settings"})
        else:
            raise unknown_key(reward_path, key, {"extrinsic", *INTRINSIC, *REWARD_UNSUPPORTED})
    return layer


def _resolve(path: str, trainer_type: str, layers: list[_Layer]) -> TrainerSettings:
    """Merge ``layers`` (later wins, key by key) over ``defaults(trainer_type)``.

    A layer's hyperparameters that ``trainer_type`` does not use (``default_settings`` for
    PPO under a SAC behavior) are skipped: the layer was checked against its own type.
    Reward signals merge as ML-Agents merges them: the first layer's (the extrinsic one
    when it names none), and those the later ones add; without the extrinsic signal among
    them, the environment's reward is not trained on.
    """
    base = defaults(trainer_type)
    hyper: dict[str, Any] = {}
    network: dict[str, Any] = {}
    extrinsic: dict[str, Any] = {}
    intrinsic: dict[str, RewardSignalSettings] = {}
    top: dict[str, Any] = {}
    for layer in layers:
        intrinsic.update(layer.intrinsic)
        hyper.update(
            (k, v) for k, v in layer.hyper.items() if k in TRAINERS[trainer_type].hyperparameters
        )
        network.update(layer.network)
        extrinsic.update(layer.extrinsic)
        top.update(layer.top)
    signals = set(layers[0].signals if layers[0].signals is not None else {"extrinsic"})
    for layer in layers[1:]:
        signals |= layer.signals or set()
    settings = replace(
        base,
        hyperparameters=replace(base.hyperparameters, **hyper),
        network_settings=replace(base.network_settings, **network),
        gamma=extrinsic.get("gamma", base.gamma),
        reward_strength=extrinsic.get("strength", base.reward_strength)
        if "extrinsic" in signals
        else 0.0,
        reward_signals=tuple(v for k, v in intrinsic.items() if k in signals),
        **top,
    )
    if settings.even_checkpoints:  # as ML-Agents' TrainerSettings computes it
        interval = max(1, int(settings.max_steps / settings.keep_checkpoints))
        settings = replace(settings, checkpoint_interval=interval)
    h = settings.hyperparameters
    if trainer_type != "sac" and h.batch_size > h.buffer_size:
        raise ConfigError(
            f"{path}.hyperparameters.batch_size: {h.batch_size} is larger than "
            f"buffer_size {h.buffer_size}"
        )
    return settings


# ---- whole files --------------------------------------------------------------------------


def _engine(raw: object, unsupported: list[str]) -> dict[str, float | int | bool]:
    engine: dict[str, float | int | bool] = {}
    for key, value in section("engine_settings", raw).items():
        if key in ENGINE:
            engine[key] = ENGINE[key](f"engine_settings.{key}", value)
        elif key in ENGINE_UNSUPPORTED:
            unsupported.append(f"engine_settings.{key}")
        else:
            raise unknown_key("engine_settings", key, {*ENGINE, *ENGINE_UNSUPPORTED})
    return engine


def _torch_device(raw: object) -> str | None:
    """``torch_settings.device`` (its only key in ML-Agents): auto, cpu, cuda or cuda:N."""
    settings = section("torch_settings", raw)
    for key in settings:
        if key != "device":
            raise unknown_key("torch_settings", key, {"device"})
    device = settings.get("device")
    if device is None:
        return None
    try:
        return check_device(device, "torch_settings.device")
    except DeviceError as error:
        raise ConfigError(str(error)) from None


def _check_lesson_behaviors(
    parameters: Mapping[str, Curriculum], behaviors: Mapping[str, TrainerSettings], source: str
) -> None:
    """A lesson that waits on a behavior the file does not configure may never end (the
    build may still have it, trained with defaults): said once, as the run starts."""
    for key, lessons in parameters.items():
        for lesson in lessons:
            criteria = lesson.completion_criteria
            if criteria is not None and behaviors and criteria.behavior not in behaviors:
                logger.warning(
                    "%s: environment_parameters.%s lesson %s waits on behavior %s, which "
                    "the file does not configure",
                    source,
                    key,
                    lesson.name,
                    criteria.behavior,
                )


def parse_config(data: object, source: str = "<config>") -> RunConfig:
    """Check and resolve an already-loaded trainer config (the YAML's top-level mapping)."""
    if not isinstance(data, Mapping):
        raise ConfigError(f"{source}: top level must be a mapping, got {type(data).__name__}")
    known = {*RUN_KEYS, *RUN_SETTINGS, *RUN_UNSUPPORTED}
    for key in data:
        if key not in known:
            raise unknown_key("", key, known)
    unsupported = [key for key in RUN_UNSUPPORTED if key in data]

    # default_settings' unsupported keys are reported once, not per behavior inheriting them
    default_layer = _parse_layer(
        "default_settings", data.get("default_settings"), "ppo", unsupported
    )
    default_type = default_layer.trainer_type or "ppo"
    default = _resolve("default_settings", default_type, [default_layer])

    behaviors: dict[str, TrainerSettings] = {}
    for name, raw in section("behaviors", data.get("behaviors")).items():
        path = f"behaviors.{name}"
        key = base_name(name)
        if not key or key in behaviors:
            raise ConfigError(f"{path}: {'empty' if not key else 'duplicate'} behavior name")
        layer = _parse_layer(path, raw, default_type, unsupported)
        trainer_type = layer.trainer_type or default_type
        # ML-Agents merges a behavior over default_settings only when the file has them
        given = [default_layer, layer] if data.get("default_settings") is not None else [layer]
        behaviors[key] = _resolve(path, trainer_type, given)

    engine = _engine(data.get("engine_settings"), unsupported)
    parameters = parse_environment_parameters(data.get("environment_parameters"))
    _check_lesson_behaviors(parameters, behaviors, source)
    torch_device = _torch_device(data.get("torch_settings"))
    reported = tuple(dict.fromkeys(unsupported))
    if reported:
        logger.warning("%s: not supported, ignored: %s", source, ", ".join(reported))
    return RunConfig(
        behaviors=MappingProxyType(behaviors),
        default=default,
        engine=MappingProxyType(engine),
        environment_parameters=parameters,
        unsupported=reported,
        source=source,
        torch_device=torch_device,
        default_given=data.get("default_settings") is not None,
        run_settings=MappingProxyType({k: data[k] for k in RUN_SETTINGS if k in data}),
    )


def load_config(path: str | Path) -> RunConfig:
    """Read and check a trainer-config YAML file; every problem is one ``ConfigError`` line."""
    return parse_config(read_config_data(path), str(path))


def read_config_data(path: str | Path) -> Any:
    """A trainer-config YAML file's data, unchecked; ``ConfigError`` when it does not read."""
    source = str(path)
    try:
        text = Path(path).read_text(encoding="utf-8")
    except OSError as error:
        raise ConfigError(f"{source}: cannot read ({error.strerror or error})") from error
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as error:
        mark = getattr(error, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark else ""
        problem = getattr(error, "problem", None) or str(error).splitlines()[0]
        raise ConfigError(f"{source}: invalid YAML: {where}{problem}") from error
    return data


def config_for_env(name: str) -> Path | None:
    """The shipped config of an environment (``3DBall``), if ``config/`` has one."""
    if not re.fullmatch(r"[A-Za-z0-9_][A-Za-z0-9_.-]*", name):
        return None
    path = CONFIG_DIR / f"{name}.yaml"
    return path if path.is_file() else None
