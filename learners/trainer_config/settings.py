"""A trainer config, resolved: the frozen settings of each behavior and of the run.

Plain data with no parsing (``learners.trainer_config.parse`` reads the YAML into these) and no
torch, so the policy factory that workers unpickle, the learner and the driver all share them.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from types import MappingProxyType
from typing import Any

from batches.contracts import base_name
from batches.parameters import Curriculum


@dataclass(frozen=True)
class MemorySettings:
    """ML-Agents ``network_settings.memory``: an LSTM after the trunk, trained on
    sequences of ``sequence_length`` steps."""

    memory_size: int = 128  # the LSTM's cell and hidden state together: memory_size // 2 units
    sequence_length: int = 64


@dataclass(frozen=True)
class NetworkSettings:
    """ML-Agents ``network_settings``: hidden units and layers of the shared trunk."""

    hidden_units: int = 128
    num_layers: int = 2
    normalize: bool = False  # running mean/variance normalization of vector observations
    # "hyper": goal signals (ObservationType.GOAL_SIGNAL) condition the other features
    # multiplicatively (one set of trunk weights per goal dimension, what ML-Agents'
    # hypernetwork achieves); "none": goal signals are ordinary inputs.
    goal_conditioning_type: str = "hyper"
    # ML-Agents' image encoder (learners.networks.encoders): simple, nature_cnn, resnet, match3 or
    # fully_connected; each ends in a dense layer to hidden_units.
    vis_encode_type: str = "simple"
    # act with the Gaussian's mean and the likeliest discrete actions (ML-Agents' key; the
    # CLI's --deterministic sets it for every behavior); it changes no weight
    deterministic: bool = False
    memory: MemorySettings | None = None  # the policy and the critic each get an LSTM
    # Not config keys: set by the learner's policy factory for SAC behaviors.
    tanh_squash: bool = False  # continuous actions are tanh(Gaussian sample)
    conditional_sigma: bool = False  # log-std from a head on the trunk, not a parameter


@dataclass(frozen=True)
class Hyperparameters:
    """``hyperparameters:`` of every trainer type; fields a trainer does not use keep defaults."""

    batch_size: int = 1024
    buffer_size: int = 10240
    learning_rate: float = 3.0e-4
    learning_rate_schedule: str = "linear"  # "linear" | "constant"
    # PPO and IMPALA
    beta: float = 5.0e-3  # entropy coefficient
    epsilon: float = 0.2  # PPO clip (policy ratio and value change)
    beta_schedule: str | None = None  # None: as learning_rate_schedule (ML-Agents' rule)
    epsilon_schedule: str | None = None
    lambd: float = 0.95  # GAE lambda
    num_epoch: int = 3
    # SAC
    buffer_init_steps: int = 0
    tau: float = 0.005
    steps_per_update: float = 1.0
    init_entcoef: float = 1.0
    reward_signal_steps_per_update: float | None = None  # None: steps_per_update
    # our extensions, not ML-Agents keys:
    # PPO, POCA: steps acted by weights more than this many updates old are dropped (None:
    # every step trains, as in mlagents-learn; docs/benchmarks-log.md, "policy lag")
    max_policy_lag: int | None = None
    vtrace_rho_clip: float = 1.0  # IMPALA V-trace rho-bar
    vtrace_c_clip: float = 1.0  # IMPALA V-trace c-bar


@dataclass(frozen=True)
class SelfPlaySettings:
    """ML-Agents' ``self_play`` section (its defaults): ``learners/algorithms/self_play.py``."""

    save_steps: int = 20_000  # trainer steps between snapshots of the learning policy
    team_change: int = 100_000  # trainer steps between learning teams (ML: 5 x save_steps)
    swap_steps: int = 2_000  # ghost steps between opponents
    window: int = 10  # snapshots kept to play against
    play_against_latest_model_ratio: float = 0.5
    initial_elo: float = 1200.0


@dataclass(frozen=True)
class RewardSignalSettings:
    """One of ``reward_signals`` besides ``extrinsic`` (``learners/reward_signals/intrinsic.py``),
    with ML-Agents' defaults; each has its own value head and gamma."""

    kind: str  # "curiosity" | "rnd" | "gail"
    gamma: float = 0.99
    strength: float = 1.0
    # the signal's own networks (ML-Agents' NetworkSettings defaults), not the policy's
    network_settings: NetworkSettings = field(default_factory=NetworkSettings)
    learning_rate: float = 3.0e-4  # rnd: 1e-4
    encoding_size: int | None = None  # read as ML-Agents 1.1.0 reads it: not used
    # gail only
    demo_path: str | None = None  # the expert's .demo file or folder, made absolute
    use_actions: bool = False  # the discriminator sees actions (and episode ends) too
    use_vail: bool = False  # a variational information bottleneck in the discriminator


@dataclass(frozen=True)
class BehavioralCloningSettings:
    """ML-Agents' ``behavioral_cloning`` section (its defaults):
    ``learners/reward_signals/cloning.py``."""

    demo_path: str  # a .demo file or a folder of them, made absolute when the config is read
    strength: float = 1.0  # the cloning learning rate is learning_rate x strength
    steps: int = 0  # steps over which that rate decays linearly to 0 (0: it stays)
    samples_per_update: int = 0  # demonstration steps per update (0: all of them)
    num_epoch: int | None = None  # None: 3, as ML-Agents' cloning module defaults it
    batch_size: int | None = None  # None: hyperparameters.batch_size


@dataclass(frozen=True)
class TrainerSettings:
    """The settings of one behavior, resolved (nothing left to merge)."""

    trainer_type: str = "ppo"  # "ppo" | "sac" | "impala"
    hyperparameters: Hyperparameters = field(default_factory=Hyperparameters)
    network_settings: NetworkSettings = field(default_factory=NetworkSettings)
    gamma: float = 0.99  # reward_signals.extrinsic.gamma
    reward_strength: float = 1.0  # reward_signals.extrinsic.strength (0: no extrinsic signal)
    max_steps: int = 500_000
    time_horizon: int = 64
    summary_freq: int = 50_000
    checkpoint_interval: int = 500_000
    keep_checkpoints: int = 5
    even_checkpoints: bool = False  # checkpoint_interval is max_steps / keep_checkpoints
    # on-policy: workers go on collecting through this behavior's updates, up to one
    # buffer_size ahead, with the weights the update replaces (ML-Agents' trainer thread)
    threaded: bool = False
    init_path: str | None = None  # a checkpoint (file or folder) this behavior starts from
    self_play: SelfPlaySettings | None = None  # None: no self-play
    behavioral_cloning: BehavioralCloningSettings | None = None
    reward_signals: tuple[RewardSignalSettings, ...] = ()  # besides extrinsic (PPO)


@dataclass(frozen=True)
class RunConfig:
    """A whole config file: per-behavior settings plus the run-level sections we use."""

    behaviors: Mapping[str, TrainerSettings]
    default: TrainerSettings  # default_settings over the built-in defaults
    engine: Mapping[str, float | int | bool]  # only the engine_settings keys given
    environment_parameters: Mapping[str, Curriculum]  # each parameter's lessons
    unsupported: tuple[str, ...]  # dotted paths of known keys we do not implement
    source: str = "<config>"
    torch_device: str | None = None  # torch_settings.device (None: --device, else auto)
    default_given: bool = False  # default_settings: in the file, for behaviors it does not name
    # env_settings, checkpoint_settings and debug as the file gives them, for the driver
    run_settings: Mapping[str, Any] = field(default_factory=dict)

    def deterministic(self) -> RunConfig:
        """Every behavior acting deterministically (the CLI's --deterministic)."""

        def acting(settings: TrainerSettings) -> TrainerSettings:
            network = replace(settings.network_settings, deterministic=True)
            return replace(settings, network_settings=network)

        behaviors = {name: acting(settings) for name, settings in self.behaviors.items()}
        return replace(self, behaviors=MappingProxyType(behaviors), default=acting(self.default))

    def for_behavior(self, behavior: str) -> TrainerSettings:
        """Settings for ``behavior`` (``?team=`` ignored); ``default`` if not listed."""
        return self.behaviors.get(base_name(behavior), self.default)
