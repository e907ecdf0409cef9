"""The player: the Academy loop of a Unity build, as a gRPC client of the trainer.

Sequence (protocol note §2): U1 handshake -> P1 (seed, num_areas); U2 empty -> P2 (the
first RESET); then each reply is answered with the agents' infos until Python sends
status 400, QUIT, or the connection breaks. One call in flight at a time, no deadline on
calls after the handshake: Python may think as long as it likes.

The player never outlives its trainer: it exits on 400 / QUIT / any RPC error, and a
watchdog thread ends it when its parent process is gone (also while a fault makes it hang).
"""

from __future__ import annotations

import logging
import os
import threading
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field

import grpc
import numpy as np

from unitysim import messages, wire, wire_input
from unitysim.envs import load
from unitysim.envs.base import AgentInfos, Behavior, Output, Parameters, SimEnv
from unitysim.faults import Faults
from unitysim.h2client import H2Channel
from unitysim.side_channels import SideChannels, encode_stats, frame

log = logging.getLogger("unitysim")

EXCHANGE = "/communicator_objects.UnityToExternalProto/Exchange"
CLIENTS = ("h2", "grpcio")  # the gRPC client: our own HTTP/2 one (default), or grpcio's
CLIENT_VARIABLE = "UNITYSIM_GRPC_CLIENT"
CRASH_EXIT_CODE = 3
OVERSIZE_BYTES = 4 * 1024 * 1024 + 64 * 1024
_OVERSIZE_CHANNEL = uuid.UUID("00000000-0000-0000-0000-00000000beef")


@dataclass(frozen=True)
class PlayerConfig:
    env_name: str
    port: int
    connect_timeout: float = 30.0
    faults: Faults = field(default_factory=Faults)
    watch_parent: bool = True
    client: str = "h2"
    no_graphics: bool = False  # -nographics: cameras send blank frames, as Unity's do


class Session:
    """One training session: the environment, its behaviors and the side channels."""

    def __init__(
        self, env_class: type[SimEnv], seed: int, num_areas: int, no_graphics: bool = False
    ) -> None:
        self.parameters = Parameters()
        self.side_channels = SideChannels(self.parameters)
        self.env = env_class(np.random.default_rng(seed), num_areas, self.parameters)
        self.behaviors: dict[str, Behavior] = {b.name: b for b in env_class.behaviors}
        self.announced: set[str] = set()
        self.seen: list[str] = []  # behaviors with a spec on the Python side, in order
        self.steps = 0
        # per behavior, the cameras a player without graphics renders nothing into
        self.blank = (
            {
                b.name: [i for i, sensor in enumerate(b.sensors) if sensor.rendered]
                for b in env_class.behaviors
            }
            if no_graphics
            else {}
        )

    def output(self, result: Output) -> bytes:
        announce = []
        for name, infos in result.items():
            for index in self.blank.get(name, ()):
                infos.obs[index] = np.zeros_like(infos.obs[index])
            if len(infos) and name not in self.announced:
                self.announced.add(name)
                self.seen.append(name)
                announce.append(self.behaviors[name])
        # Real Unity lists every subscribed behavior, empty or not.
        full = {name: result.get(name) or _empty(self.behaviors[name]) for name in self.seen}
        stats = encode_stats(self.env.drain_stats())
        return wire.encode_output(self.behaviors, full, announce, stats)


def _empty(behavior: Behavior) -> AgentInfos:
    return AgentInfos.build(
        np.zeros(0, np.int32), [np.zeros((0, *s.shape), np.float32) for s in behavior.sensors]
    )


class Player:
    def __init__(self, config: PlayerConfig) -> None:
        self.config = config
        self.env_class = load(config.env_name)  # fail fast on an unknown name
        self.faults = config.faults

    def run(self) -> int:
        """Play one session; the return value is the process exit code."""
        if self.config.watch_parent:
            _start_parent_watchdog()
        if self.config.client not in CLIENTS:
            raise ValueError(f"unknown gRPC client {self.config.client!r}; choose from {CLIENTS}")
        if self.config.client == "grpcio":
            target = f"localhost:{self.config.port}"
            options = [("grpc.enable_http_proxy", 0), ("grpc.max_receive_message_length", -1)]
            with grpc.insecure_channel(target, options=options) as channel:
                exchange: Callable[..., bytes] = channel.unary_unary(
                    EXCHANGE,
                    request_serializer=wire.to_bytes,  # steps are sent as encoded bytes
                    response_deserializer=None,  # and replies read from their bytes
                )
                return self._guarded(exchange)
        with H2Channel("localhost", self.config.port, EXCHANGE) as h2:

            def h2_exchange(
                message: messages.UnityMessageProto | bytes,
                wait_for_ready: bool = False,
                timeout: float | None = None,
            ) -> bytes:
                return h2.call(wire.to_bytes(message), timeout, wait_for_ready)

            return self._guarded(h2_exchange)

    def _guarded(self, exchange: Callable[..., bytes]) -> int:
        """Play; an RPC error ends the session (exit 1 if our message was too large)."""
        try:
            return self._play(exchange)
        except grpc.RpcError as error:
            code = error.code() if hasattr(error, "code") else None
            if code == grpc.StatusCode.RESOURCE_EXHAUSTED:
                log.error("message rejected as too large, disconnecting: %s", error)
                return 1
            log.info("connection to the trainer ended (%s): quitting", code)
            return 0

    def _play(self, exchange: Callable[..., bytes]) -> int:
        version = self.faults.communication_version or messages.COMMUNICATION_VERSION
        log.info("connecting to localhost:%d as %s", self.config.port, self.config.env_name)
        try:
            reply = exchange(
                messages.handshake_output(version),
                wait_for_ready=True,
                timeout=self.config.connect_timeout,
            )
        except grpc.RpcError as error:
            log.error(
                "no trainer answered on localhost:%d within %.0f s (%s)",
                self.config.port,
                self.config.connect_timeout,
                error.code() if hasattr(error, "code") else error,
            )
            return 1
        init = wire_input.read_input(reply, {})
        if init.status != 200:
            log.info("trainer refused the handshake (status %d)", init.status)
            return 0
        log.info(
            "handshake: python communication %s, seed %s, num_areas %s",
            init.communication_version,
            init.seed,
            init.num_areas,
        )
        session = Session(
            self.env_class, init.seed or 0, init.num_areas or 1, self.config.no_graphics
        )
        reply = exchange(messages.status_message(200))  # U2: the first real input comes back
        while True:
            request = wire_input.read_input(reply, session.behaviors)
            if request.status != 200:
                log.info("trainer closed the session (status %d)", request.status)
                return 0
            if request.command == messages.QUIT:
                log.info("QUIT received")
                return 0
            if request.side_channel:
                session.side_channels.receive(request.side_channel)
            if request.command == messages.RESET:
                log.info("RESET")
                session.steps = 0
                result = session.env.reset()
            else:
                session.steps += 1
                self._before_step(session.steps)
                result = session.env.step(request.actions)
            message, status = self._corrupt(session.output(result), session)
            if self.faults.delay_ms:
                time.sleep(self.faults.delay_ms / 1000.0)
            reply = exchange(message)
            if status != 200:
                log.error("sent status %d: quitting", status)
                return 1

    def _before_step(self, step: int) -> None:
        if self.faults.due(self.faults.crash_after, step):
            log.error("fault: crashing at step %d", step)
            logging.shutdown()
            os._exit(CRASH_EXIT_CODE)
        if self.faults.due(self.faults.hang_after, step):
            log.error("fault: hanging at step %d", step)
            while True:  # the parent watchdog ends the process once the trainer is gone
                time.sleep(1.0)

    def _corrupt(self, encoded: bytes, session: Session) -> tuple[bytes, int]:
        """Apply the faults due at this step; returns the bytes to send and their status."""
        faults, step = self.faults, session.steps
        due = (faults.status_after, faults.nan_after, faults.oversize_after, faults.silent_after)
        if not any(faults.due(after, step) for after in due):
            return encoded, 200
        message = messages.UnityMessageProto.FromString(encoded)
        if faults.due(faults.status_after, step):
            log.error("fault: sending status %d at step %d", faults.status_code, step)
            message.header.status = faults.status_code
        if faults.due(faults.nan_after, step):
            for listed in message.unity_output.rl_output.agentInfos.values():
                for info in listed.value:
                    for observation in info.observations:
                        if observation.HasField("float_data"):
                            data = observation.float_data.data
                            data[:] = [float("nan")] * len(data)
        if faults.due(faults.silent_after, step):
            for listed in message.unity_output.rl_output.agentInfos.values():
                del listed.value[:]
        if faults.due(faults.oversize_after, step):
            log.error("fault: sending an oversized message at step %d", step)
            padding = frame(_OVERSIZE_CHANNEL, b"\0" * OVERSIZE_BYTES)
            message.unity_output.rl_output.side_channel += padding
        return message.SerializeToString(), message.header.status


def _start_parent_watchdog(period: float = 0.5) -> None:
    """Exit as soon as the process that launched us is gone (we are then re-parented)."""
    parent = os.getppid()

    def watch() -> None:
        while True:
            time.sleep(period)
            if os.getppid() != parent:
                log.error("trainer process %d is gone: quitting", parent)
                logging.shutdown()
                os._exit(0)

    threading.Thread(target=watch, name="parent-watchdog", daemon=True).start()
