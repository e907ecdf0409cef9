"""Where the learner computes: its device and whether it uses mixed precision.

The choice comes from ``--device`` or the trainer config's ``torch_settings.device``
(ML-Agents' key): ``auto`` (a GPU when Ray gives the learner one), ``cpu``, ``cuda`` or
``cuda:N``. The driver only decides whether the learner actor asks Ray for a GPU
(``learner_device``), without torch; the learner's process resolves the device
(``Compute.of``). Workers always act on CPU, and the learner publishes CPU weights.

Batches go to the device once per update (pinned first, so the copy is asynchronous); with
``mixed_precision`` the hidden layers (image encoders, trunks, POCA's group critic) run in bfloat16
autocast, which needs no loss scaling, and the heads, losses and optimizer in float32
(``learners.networks.mixed_precision``). Where bfloat16 has no arithmetic of its own (a CPU without
AVX-512 or AMX, a GPU before Ampere) it is emulated and slower than float32, so the learner computes
in float32 there and its ``note`` says why (the driver prints it).
"""

from __future__ import annotations

import contextlib
import math
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import torch
    from tensordict import TensorDictBase

DEVICES = "auto, cpu, cuda or cuda:N"
_DEVICE = re.compile(r"auto|cpu|cuda(:\d+)?")


class DeviceError(ValueError):
    """A device that cannot be had; its message is one line naming what to change."""


def check_device(value: object, what: str = "--device") -> str:
    """``value`` if it names a device we accept, else a one-line ``DeviceError``."""
    if not isinstance(value, str) or not _DEVICE.fullmatch(value):
        raise DeviceError(f"{what}: {value!r} is not a device; use {DEVICES}")
    return value


def learner_device(device: str, cluster_gpus: float) -> str:
    """The device the learner actor gets: ``cpu``, or a GPU one, for which it asks Ray for
    a GPU. ``cuda``/``cuda:N`` on a cluster without a GPU is an error (raised in the
    driver, before any worker starts); ``auto`` takes a GPU when the cluster has one."""
    check_device(device)
    if device.startswith("cuda") and cluster_gpus < 1:
        raise DeviceError(
            f"--device {device}: the Ray cluster has no GPU (ray.cluster_resources() "
            "lists none); use --device cpu or auto, or add a GPU node"
        )
    return "cpu" if device == "auto" and cluster_gpus < 1 else device


@dataclass(frozen=True)
class Compute:
    """The learner's device (a torch device string) and mixed precision; ``note``: why it
    departs from what the run asked (one line), else None."""

    device: str = "cpu"
    mixed_precision: bool = False
    note: str | None = None

    @classmethod
    def of(cls, device: str = "auto", mixed_precision: bool = False) -> Compute:
        """Resolve ``device`` in the learner's process (under Ray: among the GPUs Ray gave
        it, which it numbers from 0)."""
        import torch

        check_device(device)
        if device == "auto":
            device = "cuda" if torch.cuda.is_available() else "cpu"
        if device.startswith("cuda"):
            # float32 matrix products in TF32, as cuDNN's convolutions already are by default
            torch.set_float32_matmul_precision("high")
            count = torch.cuda.device_count()
            index = int(device.partition(":")[2] or 0)
            if index >= count:
                raise DeviceError(
                    f"--device {device}: this process sees {count} CUDA device(s); use "
                    "cpu, auto or a cuda:N below that"
                )
        if mixed_precision and (why := bfloat16_slow(torch.device(device))) is not None:
            note = (
                f"--mixed-precision: {why}, where bfloat16 runs slower than float32; the "
                "learner computes in float32"
            )
            return cls(device, False, note)
        return cls(device, mixed_precision)

    @property
    def torch_device(self) -> torch.device:
        import torch

        return torch.device(self.device)

    def place(self, network: torch.nn.Module) -> None:
        """Move a network to the device, its hidden layers under this mixed precision; on
        a GPU its convolutions' weights go channels-last, as the encoders' inputs do there
        (cuDNN's fast kernels are NHWC: with NCHW they transposed every tensor, 17% of an
        H100's time in a nature_cnn update)."""
        import torch

        from learners.networks.mixed_precision import set_autocast

        network.to(self.torch_device)
        set_autocast(network, self.autocast)
        if self.torch_device.type == "cuda":
            network.to(memory_format=torch.channels_last)

    def to_device(self, batch: TensorDictBase) -> TensorDictBase:
        """One copy of an update's batch to the device; pinned, so it is asynchronous."""
        if self.device == "cpu":
            return batch
        return batch.pin_memory().to(self.device, non_blocking=True)

    def autocast(self) -> Any:
        """bfloat16 autocast on the device when mixed precision is on, else a no-op (not a
        disabled autocast: entering one costs microseconds, several times a minibatch)."""
        import torch

        if not self.mixed_precision:
            return contextlib.nullcontext()
        return torch.autocast(self.torch_device.type, dtype=torch.bfloat16)


def bfloat16_slow(device: torch.device) -> str | None:
    """Why bfloat16 would run slower than float32 on ``device`` (None: it would not). On a
    2-core AVX2 EPYC a 512 x 2 network's update took 13 times as long under bfloat16
    autocast as in float32 (2026-11-30): oneDNN emulates bfloat16 there."""
    import torch

    if device.type == "cuda":
        if torch.cuda.is_bf16_supported(including_emulation=False):
            return None
        return f"{torch.cuda.get_device_name(device)} has no bfloat16 arithmetic"
    try:
        native = bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())
    except (AttributeError, RuntimeError):  # torch no longer tells: assume it is fine
        return None
    if native:
        return None
    found = torch.backends.cpu.get_cpu_capability()
    return f"this CPU has no bfloat16 instructions (torch finds {found})"


def to_cpu(tree: Any) -> Any:
    """Tensors of a nested state (dicts, lists, tuples) on the CPU: checkpoints and the
    driver, which has no GPU, read them."""
    import torch

    if isinstance(tree, torch.Tensor):
        return tree.cpu()
    if isinstance(tree, dict):
        return {key: to_cpu(value) for key, value in tree.items()}
    if isinstance(tree, list | tuple):
        return type(tree)(to_cpu(value) for value in tree)
    return tree


def usable_cores(cgroup: Path = Path("/sys/fs/cgroup")) -> int:
    """The cores this process may keep busy: its CPU affinity, within the container's CPU
    quota (cgroup v2 ``cpu.max``, or v1 ``cpu.cfs_quota_us`` over its period), as
    mlagents-learn's ``cpu_utils`` counts them. A pod limited to 2 CPUs on a 64-core node
    sees 64 cores in its affinity."""
    cores = len(os.sched_getaffinity(0))
    for quota_file, period_file in (
        (cgroup / "cpu.max", None),
        (cgroup / "cpu/cpu.cfs_quota_us", cgroup / "cpu/cpu.cfs_period_us"),
    ):
        try:
            fields = quota_file.read_text().split()
            if period_file is not None:
                fields.append(period_file.read_text().strip())
            quota, period = int(fields[0]), int(fields[1])
        except (OSError, ValueError, IndexError):  # no such file, or "max": no quota
            continue
        if quota > 0 and period > 0:
            return max(1, min(cores, math.ceil(quota / period)))
    return cores


def free_memory(device: torch.device) -> int | None:
    """Bytes this process can still take on ``device``: a GPU's free memory, or the host's
    available memory within the container's limit (cgroup v2 or v1); None if unknown."""
    import torch

    if device.type == "cuda":
        return int(torch.cuda.mem_get_info(device)[0])
    free: list[int] = []
    try:
        meminfo = Path("/proc/meminfo").read_text()
        free.append(int(re.search(r"MemAvailable:\s+(\d+) kB", meminfo)[1]) * 1024)  # type: ignore[index]
    except (OSError, TypeError):
        pass
    for limit, usage in _CGROUP_FILES:
        try:
            cap, used = Path(limit).read_text().strip(), Path(usage).read_text().strip()
        except OSError:
            continue
        if cap.isdigit() and used.isdigit() and int(cap) < 2**60:
            free.append(max(int(cap) - int(used), 0))
    return min(free) if free else None


_CGROUP_FILES = (
    ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory.current"),
    ("/sys/fs/cgroup/memory/memory.limit_in_bytes", "/sys/fs/cgroup/memory/memory.usage_in_bytes"),
)
