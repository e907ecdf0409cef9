"""ONNX export of trained policies in the ML-Agents layout, for Unity's inference engine.

Owns the exported graph: inputs ``obs_0..obs_{n-1}`` (one per sensor, in spec order, batch
axis dynamic, images NCHW as current ML-Agents writes them) and ``action_masks`` (discrete only,
float, 1 = allowed), and the outputs Unity's ``SentisModelParamLoader`` reads: the float
constants ``version_number`` (3) and ``memory_size``, the action-size constants, the
stochastic actions sampled inside the graph (as ML-Agents does) and their deterministic
twins. Continuous actions leave the graph as the collector sends them to Unity
(``clamp(a, -3, 3) / 3``, as ML-Agents exports them), so the file acts as the policy did
in training; squashed (SAC) policies emit ``tanh`` of the sample and ``tanh(mean)`` as deterministic
action, with the state-dependent log-std of ``conditional_sigma`` networks.
Also owns ``export_checkpoint`` (one ``.onnx`` per behavior) behind ``unity-rollout export``.
Not owned: the networks (``learners.networks.policies``), the checkpoint format
(``learners.host.checkpoint``). A policy with memory takes ``recurrent_in`` ``[batch, 1,
memory_size]`` last and gives ``recurrent_out`` last, as ML-Agents' exporter names them.
See docs/export.md.
"""

from __future__ import annotations

import copy
import warnings
from pathlib import Path

import onnx
import torch
from torch import nn

from learners.host import checkpoint
from learners.networks.policies import ActorCritic

__all__ = ["MODEL_EXPORT_VERSION", "OPSET", "export_checkpoint", "export_onnx", "onnx_names"]

MODEL_EXPORT_VERSION = 3  # ML-Agents' ModelApiVersion.MLAgents2_0 (obs_{i} inputs)
OPSET = 9  # ML-Agents' SerializationSettings.onnx_opset
_MASK_PENALTY = 1e8  # masked logits: logit * 0 - 1e8, as ML-Agents masks (no -inf, no Where)


class _ExportedPolicy(nn.Module):
    """The acting path of an :class:`ActorCritic`, with ML-Agents' inputs and outputs."""

    def __init__(self, network: ActorCritic) -> None:
        super().__init__()
        self.network = network
        continuous, branches = network.continuous, network.branches
        # Unity reads these constants as float tensors (SentisModelInfo casts Tensor<float>).
        self.register_buffer("version_number", torch.tensor([float(MODEL_EXPORT_VERSION)]))
        self.register_buffer("memory_size", torch.tensor([float(network.memory_size)]))
        self.register_buffer("continuous_shape", torch.tensor([float(continuous)]))
        self.register_buffer("discrete_shape", torch.tensor([[float(b) for b in branches]]))

    def forward(self, *inputs: torch.Tensor) -> tuple[torch.Tensor, ...]:
        net = self.network
        count = len(net.sensor_names)
        hidden = net.features(dict(zip(net.sensor_names, inputs[:count], strict=True)))
        memory_out = None
        if net.lstm is not None:  # recurrent_in [batch, 1, memory_size], last
            memory = inputs[-1].reshape(inputs[-1].shape[0], -1)
            hidden, memory_out = net.recur(net.lstm, hidden, memory)
        outputs = [self.version_number.clone(), self.memory_size.clone()]
        if net.mean is not None:
            mean, log_std = net.mean_log_std(hidden)
            sample = mean + torch.randn_like(mean) * torch.exp(log_std)
            if net.settings.tanh_squash:  # SAC policies: the action is tanh of the Gaussian
                sample, mean = torch.tanh(sample), torch.tanh(mean)
            outputs += [
                net.unity_action(sample),
                self.continuous_shape.clone(),
                net.unity_action(mean),
            ]
        if net.logits is not None:
            allowed = inputs[count]
            logits = net.logits(hidden) * allowed - _MASK_PENALTY * (1.0 - allowed)
            sampled, deterministic, offset = [], [], 0
            for size in net.branches:
                branch = logits[:, offset : offset + size]
                offset += size
                sampled.append(torch.multinomial(torch.softmax(branch, dim=1), 1))
                deterministic.append(torch.argmax(branch, dim=1, keepdim=True))
            outputs += [
                torch.cat(sampled, dim=1),
                self.discrete_shape.clone(),
                torch.cat(deterministic, dim=1),
            ]
        if memory_out is not None:
            outputs.append(memory_out.unsqueeze(1))
        return tuple(outputs)


def onnx_names(network: ActorCritic) -> tuple[list[str], list[str]]:
    """(input names, output names) of the exported graph, in order."""
    inputs = [f"obs_{i}" for i in range(len(network.sensor_names))]
    outputs = ["version_number", "memory_size"]
    if network.continuous:
        outputs += [
            "continuous_actions",
            "continuous_action_output_shape",
            "deterministic_continuous_actions",
        ]
    if network.branches:
        inputs.append("action_masks")
        outputs += [
            "discrete_actions",
            "discrete_action_output_shape",
            "deterministic_discrete_actions",
        ]
    if network.memory_size:
        inputs.append("recurrent_in")
        outputs.append("recurrent_out")
    return inputs, outputs


def export_onnx(network: ActorCritic, path: str | Path) -> Path:
    """Write one behavior's policy to ``path`` (an ONNX file Unity loads as a model asset)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    wrapper = _ExportedPolicy(copy.deepcopy(network).cpu()).eval()
    input_names, output_names = onnx_names(network)
    dummy: list[torch.Tensor] = [
        torch.zeros(1, *spec.shape) for spec in network.spec.observation_specs
    ]
    if network.branches:
        dummy.append(torch.ones(1, sum(network.branches)))
    if network.memory_size:
        dummy.append(torch.zeros(1, 1, network.memory_size))
    batched = ("action_masks", "recurrent_in", "recurrent_out")
    dynamic_axes = {  # the batch axis of every input, every action output and the memory
        name: {0: "batch"}
        for name in input_names + output_names
        if name.startswith("obs_") or name in batched or name.endswith("_actions")
    }
    with torch.no_grad(), warnings.catch_warnings():
        # The TorchScript exporter is deprecated upstream but is the one that writes the
        # opset-9 graph ML-Agents does (and needs no onnxscript).
        warnings.simplefilter("ignore", DeprecationWarning)
        # an LSTM's: its state comes in as recurrent_in, and any batch size runs (tested)
        warnings.simplefilter("ignore", torch.jit.TracerWarning)
        warnings.filterwarnings("ignore", "Exporting a model to ONNX with a batch_size")
        torch.onnx.export(
            wrapper,
            tuple(dummy),
            str(path),
            input_names=input_names,
            output_names=output_names,
            dynamic_axes=dynamic_axes,
            opset_version=OPSET,
            do_constant_folding=True,
            dynamo=False,
        )
    onnx.checker.check_model(onnx.load(str(path)))
    return path


def export_checkpoint(source: str | Path, out_dir: str | Path | None = None) -> list[Path]:
    """Export every behavior of a checkpoint (a ``.pt`` file, or a run directory: each
    behavior's newest).

    Files are named after the behavior with ``?`` replaced by ``_`` (``3DBall_team=0.onnx``).
    ``out_dir`` defaults to ``<run dir>/exported`` for a run or a checkpoint inside a run's
    ``checkpoints/``, else to the checkpoint's own directory.
    """
    source = Path(source)
    state = checkpoint.load(source)
    if out_dir is None:
        run = next((p.parent for p in (source, *source.parents) if p.name == "checkpoints"), None)
        if run is None and source.is_dir():
            run = source
        out_dir = run / "exported" if run is not None else source.parent
    out_dir = Path(out_dir)
    return [
        export_onnx(network, out_dir / f"{behavior.replace('?', '_')}.onnx")
        for behavior, network in checkpoint.networks(state).items()
    ]
