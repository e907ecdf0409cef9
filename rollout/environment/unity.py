"""One Unity instance, as a rollout worker owns it: leased port, loopback-only server,
player tied to its owner's life, side channels, and restarts after failures.

``UnityEnvironment`` (mlagents-envs, unmodified) is subclassed in two places only:
``_get_communicator`` returns :mod:`rollout.environment.communicator`'s server on a port from
:mod:`rollout.environment.ports`, and ``_close`` also kills the player's process group. The
player is launched through :mod:`rollout.environment.launch_guard`, so it dies with its owner even
after a SIGKILL. The same code drives real builds, unitysim builds
(``unitysim:3DBall``) and the editor (``build=None``, port 5004).
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import os
import re
import shlex
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

from mlagents_envs.base_env import ActionTuple, BehaviorSpec, DecisionSteps, TerminalSteps
from mlagents_envs.communicator_objects.agent_action_pb2 import AgentActionProto
from mlagents_envs.communicator_objects.command_pb2 import STEP
from mlagents_envs.communicator_objects.observation_pb2 import PNG
from mlagents_envs.communicator_objects.unity_input_pb2 import UnityInputProto
from mlagents_envs.communicator_objects.unity_rl_input_pb2 import UnityRLInputProto
from mlagents_envs.communicator_objects.unity_rl_output_pb2 import UnityRLOutputProto
from mlagents_envs.environment import UnityEnvironment
from mlagents_envs.exception import (
    UnityCommunicationException,
    UnityCommunicatorStoppedException,
    UnityEnvironmentException,
    UnityTimeOutException,
    UnityWorkerInUseException,
)
from mlagents_envs.rpc_communicator import RpcCommunicator
from mlagents_envs.side_channel.engine_configuration_channel import (
    EngineConfigurationChannel,
)
from mlagents_envs.side_channel.environment_parameters_channel import (
    EnvironmentParametersChannel,
)
from mlagents_envs.side_channel.stats_side_channel import StatsSideChannel

from batches.parameters import Constant, Gaussian, Uniform, Value, Values, reseeded
from rollout.environment.builds import UnityError, resolve_build
from rollout.environment.communicator import LoopbackCommunicator
from rollout.environment.ports import PortAllocator
from rollout.environment.restarts import RestartBudget, RestartPolicy, RestartRefused
from unitysim.launcher import write_executable

log = logging.getLogger(__name__)

EDITOR_PORT = UnityEnvironment.DEFAULT_EDITOR_PORT
_PROJECT_ROOT = Path(__file__).resolve().parents[2]  # where rollout/ and unitysim/ live

#: Failures a restart can cure: the player died (also after an oversized message), hung,
#: sent status != 200 or NaNs.
RECOVERABLE = (
    UnityCommunicatorStoppedException,  # status != 200
    UnityEnvironmentException,
    UnityTimeOutException,
    UnityCommunicationException,
    UnityWorkerInUseException,
    RuntimeError,
)


class UnityStartError(UnityError):
    """A launch that never connected: fatal at a run's start, a failed start in a restart."""


class UnityStartTimeout(UnityStartError):
    """A launch still running that did not connect within ``timeout_wait``: a slow machine
    (a loaded cluster node) as much as a broken build, so even a run's first launch is
    tried again under the restart policy, as mlagents-learn does."""


@dataclass(frozen=True)
class EngineSettings:
    """Engine configuration sent at start; mlagents-learn's defaults for training."""

    width: int = 84
    height: int = 84
    quality_level: int = 5
    time_scale: float = 20.0
    target_frame_rate: int = -1
    capture_frame_rate: int = 60


@dataclass(frozen=True)
class UnityConfig:
    build: str | None  # path to a build, "unitysim:<Env>", or None for the editor
    seed: int = 0
    num_areas: int = 1
    timeout_wait: int = 60
    no_graphics: bool = False  # Unity's -nographics (mlagents-learn's default: off)
    no_graphics_monitor: bool = False  # worker 0 with graphics, the others without
    engine: EngineSettings = field(default_factory=EngineSettings)
    env_params: Values = field(default_factory=dict)  # the first lesson's, seeded per worker
    additional_args: tuple[str, ...] = ()
    log_folder: str | None = None
    restarts: RestartPolicy = field(default_factory=RestartPolicy)


def _guard_launcher(executable: str) -> str:
    """A launcher that execs ``executable`` through rollout.environment.launch_guard; returns the
    ``file_name`` to give UnityEnvironment."""
    directory = Path(tempfile.gettempdir()) / f"unity-rollout-{os.getuid()}" / "guarded"
    directory.mkdir(parents=True, exist_ok=True)
    name = Path(executable).name.replace(".x86_64", "").replace(".x86", "")
    digest = hashlib.sha256(executable.encode()).hexdigest()[:12]  # stable across processes
    path = directory / f"{name}-{digest}.x86_64"
    text = (
        "#!/bin/sh\n"
        "# Ties the Unity player to its owner's life (see rollout/environment/launch_guard.py).\n"
        f'export PYTHONPATH={shlex.quote(str(_PROJECT_ROOT))}"${{PYTHONPATH:+:$PYTHONPATH}}"\n'
        f"exec {shlex.quote(sys.executable)} -m rollout.environment.launch_guard "
        f'{shlex.quote(executable)} "$@"\n'
    )
    write_executable(path, text)
    return str(path.with_suffix(""))


PLAYER_SEED_STRIDE = 7919  # sampler seeds of a restarted player, away from other workers'


def send_parameter(channel: EnvironmentParametersChannel, key: str, value: Value) -> None:
    """One parameter over Unity's side channel, as mlagents-learn's samplers ``apply``."""
    if isinstance(value, Constant):
        channel.set_float_parameter(key, value.value)
    elif isinstance(value, Uniform):
        channel.set_uniform_sampler_parameters(key, value.min_value, value.max_value, value.seed)
    elif isinstance(value, Gaussian):
        channel.set_gaussian_sampler_parameters(key, value.mean, value.st_dev, value.seed)
    else:
        channel.set_multirangeuniform_sampler_parameters(
            key, [list(pair) for pair in value.intervals], value.seed
        )


# --- the mlagents subclasses ------------------------------------------------------------


class GuardedUnityEnvironment(UnityEnvironment):
    def __init__(
        self,
        executable: str | None,
        port: int,
        on_bound: Callable[[int], None],
        **kwargs: object,
    ) -> None:
        self._on_bound = on_bound
        # per behavior, the names of its sensors Unity sends as PNG (read off the first
        # agent info that carries them): their values are exactly k/255
        self.png_sensors: dict[str, frozenset[str]] = {}
        file_name = _guard_launcher(executable) if executable else None
        super().__init__(file_name=file_name, base_port=port, worker_id=0, **kwargs)

    def _update_state(self, output: UnityRLOutputProto) -> None:
        for behavior, infos in output.agentInfos.items():
            if behavior not in self.png_sensors and infos.value and behavior in self._env_specs:
                sensors = self._env_specs[behavior].observation_specs
                observations = infos.value[0].observations
                self.png_sensors[behavior] = frozenset(
                    spec.name
                    for spec, proto in zip(sensors, observations, strict=False)
                    if proto.compression_type == PNG
                )
        super()._update_state(output)

    def _get_communicator(  # type: ignore[override]
        self, worker_id: int, base_port: int, timeout_wait: int
    ) -> RpcCommunicator:
        return LoopbackCommunicator(base_port + worker_id, timeout_wait, self._on_bound)

    def abort(self) -> None:
        """Close without waiting for the player to exit on its own (it failed)."""
        self._close(timeout=0)

    def _close(self, timeout: int | None = None) -> None:
        process = self._process
        super()._close(timeout)
        if process is not None:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(process.pid, signal.SIGKILL)  # the player's whole session
            with contextlib.suppress(subprocess.TimeoutExpired):
                process.wait(5)

    @property
    def player_pid(self) -> int | None:
        return self._process.pid if self._process is not None else None

    def _generate_step_input(self, vector_action: dict[str, ActionTuple]) -> UnityInputProto:
        """mlagents' step input, the same message built with one constructor call per agent
        instead of six ``extend`` calls (tested equal to the original)."""
        rl_in = UnityRLInputProto()
        for behavior, actions in vector_action.items():
            n_agents = len(self._env_state[behavior][0])
            if n_agents == 0:
                continue
            continuous = actions.continuous.tolist()
            discrete = actions.discrete.tolist()
            rl_in.agent_actions[behavior].value.extend(
                AgentActionProto(
                    vector_actions_deprecated=c + d, continuous_actions=c, discrete_actions=d
                )
                for c, d in zip(continuous[:n_agents], discrete[:n_agents], strict=True)
            )
            rl_in.command = STEP
        rl_in.side_channel = bytes(self._side_channel_manager.generate_side_channel_messages())
        return self._wrap_unity_input(rl_in)


# --- the restartable instance ------------------------------------------------------------


class UnityInstance:
    """A Unity instance that restarts itself on a fresh port after a recoverable failure."""

    def __init__(self, config: UnityConfig, allocator: PortAllocator | None = None) -> None:
        self.config = config
        self.allocator = allocator or PortAllocator()
        self.executable = resolve_build(config.build)  # bad paths fail here, at once
        self.budget = RestartBudget(config.restarts)
        self.port: int | None = None
        self.env: GuardedUnityEnvironment | None = None
        self._stats = StatsSideChannel()
        self._parameters = EnvironmentParametersChannel()
        self.parameters: Values = dict(config.env_params)  # sent to every player started

    @property
    def restarts(self) -> int:
        return self.budget.restarts

    # --- lifecycle ----------------------------------------------------------------------

    def start(self) -> None:
        config = self.config
        port = self.allocator.lease() if self.executable else self.allocator.lease_port(EDITOR_PORT)
        engine = EngineConfigurationChannel()
        engine.set_configuration_parameters(**vars(config.engine))
        if config.log_folder:  # mlagents passes -logFile <folder>/Player-0.log
            Path(config.log_folder).mkdir(parents=True, exist_ok=True)
        # a restarted player draws a new stream; the channel holds these until the handshake
        params = self._parameters = EnvironmentParametersChannel()
        for key, value in self.parameters.items():
            send_parameter(params, key, reseeded(value, PLAYER_SEED_STRIDE * self.restarts))
        try:
            self.env = GuardedUnityEnvironment(
                self.executable,
                port,
                self.allocator.confirm,
                seed=config.seed + self.restarts,
                no_graphics=config.no_graphics,
                timeout_wait=config.timeout_wait,
                additional_args=list(config.additional_args),
                side_channels=[engine, params, self._stats],
                log_folder=config.log_folder,
                num_areas=config.num_areas,
            )
        except UnityEnvironmentException as error:
            self.allocator.release(port)
            first = str(error).splitlines()[0]
            if "not compatible" in first:
                raise UnityError(f"{config.build}: {first}") from None
            exited = re.search(r"return code (-?\d+)", first)
            what = f"the player exited with code {exited.group(1)}" if exited else first
            detail = f"{what} before it connected{self._log()}"
            raise UnityStartError(f"{config.build}: {detail}") from None
        except UnityTimeOutException:
            self.allocator.release(port)
            raise UnityStartTimeout(
                f"{config.build}: did not connect within timeout_wait ({config.timeout_wait} s)"
                f"{self._log()}"
            ) from None
        except BaseException:
            self.allocator.release(port)
            raise
        self.port = port
        log.info("Unity %s on port %d (pid %s)", config.build, port, self.env.player_pid)

    def _log(self) -> str:
        """Where the player's own log is, when it wrote one (a build that died first did not)."""
        folder = self.config.log_folder
        if not folder or not self.executable:
            return ""
        path = Path(folder) / "Player-0.log"
        return f"; its log: {path}" if path.is_file() else "; it wrote no log"

    def close(self, failed: bool = False) -> None:
        """``failed``: the player crashed or hangs, so it gets no grace period to exit."""
        env, port = self.env, self.port
        self.env, self.port = None, None
        try:
            if env is not None:
                with contextlib.suppress(Exception):
                    env.abort() if failed else env.close()
        finally:
            if port is not None:
                self.allocator.release(port)

    def restart(self, reason: str) -> None:
        """Close, back off, and start again on a fresh port, as the restart policy allows;
        a launch that fails counts as one more failed start."""
        self.close(failed=True)
        while True:
            try:
                delay = self.budget.admit(str(self.config.build), reason)
            except RestartRefused as refused:
                raise UnityError(str(refused)) from None
            log.warning("restarting Unity (%s) in %.1f s: %s", self.config.build, delay, reason)
            time.sleep(delay)
            try:
                self.start()
                return
            except UnityStartError as error:
                reason = str(error)
            except UnityError:
                raise
            except RECOVERABLE as error:
                reason = f"{type(error).__name__}: {str(error).splitlines()[0]}"

    def healthy_step(self) -> None:
        """Call after a successful exchange: the backoff starts over."""
        self.budget.healthy()

    def __enter__(self) -> UnityInstance:
        self.start()
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    # --- the environment ------------------------------------------------------------------

    def _require(self) -> GuardedUnityEnvironment:
        if self.env is None:
            raise UnityError("the Unity instance is not running: call start() first")
        return self.env

    @property
    def behavior_specs(self) -> Mapping[str, BehaviorSpec]:
        return self._require().behavior_specs

    @property
    def player_pid(self) -> int | None:
        return self._require().player_pid

    def reset(self) -> None:
        self._require().reset()

    def set_parameters(self, values: Values) -> None:
        """New environment parameters (a lesson changed): the build reads them at its next
        episode resets; kept for any player started later."""
        self.parameters.update(values)
        for key, value in values.items():
            send_parameter(self._parameters, key, value)

    def step(self) -> None:
        self._require().step()

    def get_steps(self, behavior: str) -> tuple[DecisionSteps, TerminalSteps]:
        return self._require().get_steps(behavior)

    def png_sensors(self, behavior: str) -> frozenset[str] | None:
        """The behavior's sensors that arrive as PNG (None: no agent of it seen yet). Their
        values are multiples of 1/255, so they travel to the learner as uint8, losslessly."""
        return self._require().png_sensors.get(behavior)

    def set_actions(self, behavior: str, actions: ActionTuple) -> None:
        self._require().set_actions(behavior, actions)

    def drain_stats(self) -> dict[str, list[tuple[float, int]]]:
        """Stats Unity sent since the last call (``StatsRecorder``), for the metrics."""
        return {
            key: [(value, int(method.value)) for value, method in entries]
            for key, entries in self._stats.get_and_reset_stats().items()
        }
