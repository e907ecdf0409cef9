"""The same computation as mlagents-learn 1.1.0's own code: one update of each trainer
(PPO, its branches and masks, memory, intrinsic signals, POCA), the trajectories and
groupmates a worker cuts, ``.demo`` files both ways; and mlagents-learn's own acting
normalizer. ``common`` holds what the checks share (running both sides, comparing
weights). Files run by mlagents-learn's own Python (the anchor's venv) import nothing of
ours but this package; ``mlagents_hooks``, ``mlagents_update_log`` and
``demo_mlagents_side`` even run as plain files there."""
