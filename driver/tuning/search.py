"""What ``unity-rollout tune`` searches: a YAML file naming trainer-config keys by their
dotted path in ML-Agents' trainer YAML, each with the values to try::

    behaviors.3DBall.hyperparameters.learning_rate: {loguniform: [1.0e-4, 1.0e-2]}
    behaviors.3DBall.hyperparameters.beta: {choice: [1.0e-3, 5.0e-3, 1.0e-2]}
    behaviors.3DBall.hyperparameters.num_epoch: {randint: [3, 8]}   # 3 to 7
    default_settings.hyperparameters.epsilon: {uniform: [0.1, 0.3]}
    behaviors.3DBall.network_settings.hidden_units: {grid: [64, 128]}  # every value, each trial

Every key is checked against the trainer config before Ray starts, with the values at the
ends of its range, so a typo or a value out of range is one line before anything runs.
Under PBT a trial takes another's checkpoint, so keys that change the network (or the
trainer type) cannot be searched there."""

from __future__ import annotations

import copy
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from driver.declaration import TrainingError
from learners.trainer_config.parse import ConfigError, parse_config

DOMAINS = ("choice", "uniform", "loguniform", "randint", "grid")
NUMERIC = ("uniform", "loguniform", "randint")


@dataclass(frozen=True)
class Dimension:
    """One searched key: its dotted path, its domain and the domain's arguments."""

    key: str
    domain: str
    values: tuple[Any, ...]

    def ends(self) -> tuple[Any, ...]:
        """The values that bound what a trial may get: each checked against the config."""
        if self.domain == "randint":
            return (self.values[0], self.values[1] - 1)
        return self.values

    def tune_domain(self) -> Any:
        from ray import tune

        if self.domain == "grid":
            return tune.grid_search(list(self.values))
        if self.domain == "choice":
            return tune.choice(list(self.values))
        low, high = self.values
        return {"uniform": tune.uniform, "loguniform": tune.loguniform, "randint": tune.randint}[
            self.domain
        ](low, high)


@dataclass(frozen=True)
class Search:
    source: str
    dimensions: tuple[Dimension, ...]

    def space(self) -> dict[str, Any]:
        """Tune's ``param_space``: each trial's config maps these keys to its values."""
        return {d.key: d.tune_domain() for d in self.dimensions}

    def mutations(self) -> dict[str, Any]:
        """PBT's ``hyperparam_mutations``: explore resamples or perturbs within the same."""
        return {d.key: d.tune_domain() for d in self.dimensions if d.domain != "grid"}

    def check_for_pbt(self) -> None:
        for d in self.dimensions:
            if ".network_settings." in f".{d.key}." or d.key.endswith("trainer_type"):
                raise TrainingError(
                    f"{self.source}: {d.key}: a PBT trial takes another's checkpoint, which "
                    "holds its network and trainer type; search this key with --scheduler "
                    "asha or fifo"
                )
            if d.domain == "grid":
                raise TrainingError(
                    f"{self.source}: {d.key}: grid under PBT: use choice (PBT explores "
                    "by resampling), or --scheduler asha or fifo"
                )


def load_search(path: str | Path) -> Search:
    """The search file, its shape checked; ``TrainingError`` names the file and key."""
    source = str(path)
    try:
        data = yaml.safe_load(Path(path).read_text(encoding="utf-8"))
    except OSError as error:
        raise TrainingError(f"--search: cannot read {source} ({error.strerror})") from None
    except yaml.YAMLError as error:
        first = str(error).splitlines()[0]
        raise TrainingError(f"--search: {source}: invalid YAML ({first})") from None
    if not isinstance(data, Mapping) or not data:
        raise TrainingError(
            f"--search: {source}: a mapping of trainer-config keys to values to try, e.g. "
            "behaviors.3DBall.hyperparameters.learning_rate: {loguniform: [1.0e-4, 1.0e-2]}"
        )
    return Search(source, tuple(_dimension(source, str(k), v) for k, v in data.items()))


def _dimension(source: str, key: str, raw: Any) -> Dimension:
    where = f"{source}: {key}"
    if not isinstance(raw, Mapping):  # a fixed value: one choice
        return Dimension(key, "choice", (raw,))
    if len(raw) != 1 or next(iter(raw)) not in DOMAINS:
        raise TrainingError(f"{where}: one of {', '.join(DOMAINS)} with its values, got {raw!r}")
    domain, values = next(iter(raw.items()))
    if not isinstance(values, list) or not values:
        raise TrainingError(f"{where}: {domain} takes a list of values, got {values!r}")
    if domain in NUMERIC:
        if len(values) != 2 or not all(_number(v) for v in values) or values[0] >= values[1]:
            raise TrainingError(f"{where}: {domain} takes [low, high], low < high: {values!r}")
        if domain == "loguniform" and values[0] <= 0:
            raise TrainingError(f"{where}: loguniform needs low > 0, got {values[0]!r}")
        if domain == "randint" and not all(isinstance(v, int) for v in values):
            raise TrainingError(f"{where}: randint takes integers [low, high), got {values!r}")
    return Dimension(key, domain, tuple(values))


def _number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def with_values(data: Any, values: Mapping[str, Any]) -> dict[str, Any]:
    """The trainer config's data with each dotted key set (sections made as needed)."""
    out = copy.deepcopy(dict(data or {}))
    for key, value in values.items():
        node, *parents, leaf = (out, *key.split("."))
        for part in parents:
            child = node.get(part)
            if child is None:
                child = node[part] = {}
            if not isinstance(child, dict):
                raise TrainingError(f"{key}: {part} holds {child!r}, not a section of keys")
            node = child
        node[leaf] = value
    return out


def check_search(search: Search, data: Any, config_source: str) -> None:
    """Every key at every end of its range makes a valid trainer config, and names a
    behavior the config has (a new one would train with the defaults, unseen)."""
    named = set((data or {}).get("behaviors") or {})
    for d in search.dimensions:
        parts = d.key.split(".")
        if parts[0] == "behaviors" and len(parts) > 1 and parts[1] not in named:
            raise TrainingError(
                f"--search {search.source}: {d.key}: the trainer config ({config_source}) has "
                f"no behavior {parts[1]!r} (it has {', '.join(sorted(named)) or 'none'}); "
                "default_settings.<section>.<key> sets a key for every behavior"
            )
        for value in d.ends():
            try:
                parse_config(with_values(data, {d.key: value}), config_source)
            except (ConfigError, TrainingError) as error:
                problem = f"--search {search.source}: {d.key} = {value!r}: {error}"
                raise TrainingError(problem) from None
