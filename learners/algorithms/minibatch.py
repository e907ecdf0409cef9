"""PPO's minibatch step, captured once and replayed as a CUDA graph on a GPU.

On a GPU an eager minibatch step is bound by Python and kernel launches, not by the GPU:
about 300 kernels per step (measured on an H100, ``docs/benchmarks.md``: the 3DBall MLP's
step 3.5 ms eager against 0.36 ms replayed, nature_cnn on 84x84x3 5.0 ms against 1.3 ms).
A graph replays those kernels with one launch, so everything the step reads lives at
addresses that stay put between replays:

- the steps come from ``Steps`` over the trajectory store's columns at their full
  capacity, and a minibatch is the rows named in a fixed index tensor;
- advantages and value targets are copied into buffers of that capacity;
- epsilon, beta and the learning rate are 0-dim tensors (the optimizer is Adam with
  ``capturable=True`` and a tensor learning rate), written before the replays;
- the loss entries are summed on the device and read once per update.

The same function runs eagerly on the CPU (and for a GPU's first steps, which set up
Adam's state and the libraries' handles), so the CPU tests cover everything but the
capture. A capture that fails is logged once and the step stays eager.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

import torch

from learners.host.devices import Compute

log = logging.getLogger(__name__)

REPORTED = (
    "loss_objective",
    "objective_size",  # |loss_objective| of each minibatch: what ML-Agents reports
    "loss_critic",
    "loss_entropy",
    "entropy",
    "clip_fraction",
    "kl_approx",
)
KEPT = ("lr", "capturable", "fused", "foreach")  # an optimizer's own kind, not its state's
EAGER_STEPS = 3  # before a capture: Adam's state, cuDNN's and cuBLAS's handles


def adam(params: Any, lr: float, compute: Compute) -> torch.optim.Adam:
    """Fused Adam; on a GPU with a tensor learning rate, so that a graph can replay it."""
    if compute.torch_device.type == "cuda":
        rate = torch.tensor(lr, device=compute.torch_device)
        return torch.optim.Adam(params, lr=rate, fused=True, capturable=True)
    return torch.optim.Adam(params, lr=lr, fused=True)


def set_learning_rate(optimizer: torch.optim.Optimizer, lr: float) -> None:
    """Write a new learning rate, in place where it is a tensor (a graph reads it there)."""
    for group in optimizer.param_groups:
        _set_group_learning_rate(group, lr)


def _set_group_learning_rate(group: dict[str, Any], lr: float) -> None:
    if isinstance(group["lr"], torch.Tensor):
        group["lr"].fill_(lr)
    else:
        group["lr"] = lr


def plain_learning_rates(state: dict[str, Any]) -> dict[str, Any]:
    """An optimizer's state_dict with float learning rates: a checkpoint loads on any device."""
    groups = [
        {**g, "lr": float(g["lr"]) if isinstance(g["lr"], torch.Tensor) else g["lr"]}
        for g in state["param_groups"]
    ]
    return {**state, "param_groups": groups}


def load_optimizer(optimizer: torch.optim.Optimizer, state: dict[str, Any]) -> None:
    """Load a checkpoint's optimizer state, keeping this optimizer's own kind (a tensor
    learning rate, capturable, fused): the checkpoint may come from another device."""
    own = [{k: g[k] for k in KEPT if k in g} for g in optimizer.param_groups]
    optimizer.load_state_dict(state)
    for group, kept in zip(optimizer.param_groups, own, strict=True):
        saved = float(group["lr"])
        group.update(kept)
        _set_group_learning_rate(group, saved)


class MinibatchStep:
    """``step(rows)``: one gradient step on ``inputs[rows]``; graphed once warm on CUDA.

    ``loss(index, scalars)`` computes the loss entries of the minibatch at ``index`` with
    ``scalars`` (epsilon, beta) as tensors; it must read only tensors that outlive the
    graph (``start`` drops the graph when their addresses moved)."""

    def __init__(
        self,
        loss: Callable[[torch.Tensor, torch.Tensor], dict[str, torch.Tensor]],
        optimizer: torch.optim.Optimizer,
        batch_size: int,
        compute: Compute,
        reported: tuple[str, ...] = REPORTED,
    ) -> None:
        self.loss = loss
        self.optimizer = optimizer
        self.compute = compute
        self.reported = reported
        device = compute.torch_device
        self.params = [p for group in optimizer.param_groups for p in group["params"]]
        self.index = torch.zeros(batch_size, dtype=torch.int64, device=device)
        self.scalars = torch.zeros(2, device=device)  # epsilon, beta
        self.sums = torch.zeros(len(reported), device=device)
        self.steps = 0  # in the current update
        self.graphable = device.type == "cuda"
        self._graph: torch.cuda.CUDAGraph | None = None
        self._eager_steps = 0
        self._inputs: tuple[int, ...] = ()

    def start(self, inputs: tuple[int, ...], epsilon: float, beta: float) -> None:
        """A new update: ``inputs`` names the addresses the loss reads (the graph is
        dropped when they moved), epsilon and beta are this update's."""
        if inputs != self._inputs:
            self._graph = None
            self._eager_steps = 0
            self._inputs = inputs
        self.scalars[0], self.scalars[1] = epsilon, beta
        self.sums.zero_()
        self.steps = 0

    def drop_graph(self) -> None:
        """The optimizer's state was replaced (a checkpoint loaded): capture anew."""
        self._graph, self._eager_steps = None, 0

    def __call__(self, rows: torch.Tensor) -> None:
        self.index.copy_(rows, non_blocking=True)
        self.steps += 1
        if self._graph is not None:
            self._graph.replay()
        elif not self.graphable or self._eager_steps < EAGER_STEPS:
            self._run_eager()
        else:
            self._capture()
            if self._graph is not None:
                self._graph.replay()
            else:
                self._run_eager()

    def means(self) -> dict[str, float]:
        """Each reported entry's mean over this update's steps (one read of the device)."""
        values = (self.sums / max(self.steps, 1)).tolist()
        return dict(zip(self.reported, values, strict=True))

    # --- internals ----------------------------------------------------------------------

    def _body(self) -> None:
        for param in self.params:
            param.grad = None
        losses = self.loss(self.index, self.scalars)
        sum(v for k, v in losses.items() if k.startswith("loss_")).backward()
        self.optimizer.step()
        with torch.no_grad():
            self.sums += torch.stack([losses[k].detach().float() for k in self.reported])

    def _run_eager(self) -> None:
        if not self.graphable:
            self._body()
            return
        # on a side stream, as before a capture (the AccumulateGrad ops' streams)
        side = torch.cuda.Stream(self.compute.torch_device)
        side.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(side):
            self._body()
        torch.cuda.current_stream().wait_stream(side)
        self._eager_steps += 1

    def _capture(self) -> None:
        graph = torch.cuda.CUDAGraph()
        for param in self.params:
            param.grad = None
        try:
            with torch.cuda.graph(graph, capture_error_mode="thread_local"):
                self._body()
        except RuntimeError as error:
            log.warning("minibatch step stays eager: CUDA graph capture failed: %s", error)
            self.graphable = False
            return
        self._graph = graph
