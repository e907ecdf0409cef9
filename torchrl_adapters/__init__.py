"""torchrl over the rollout service, for users with their own loss and loop:
``UnityCollector`` yields TensorDict batches under torchrl's key names from Ray workers
acting with the user's ``TensorDictModule`` (docs/torchrl.md)."""

from torchrl_adapters.collector import UnityCollector

__all__ = ["UnityCollector"]
