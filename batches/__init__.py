"""The batch vocabulary both sides speak: segment keys (``keys``), specs from ML-Agents'
``BehaviorSpec`` (``specs``) and the packed :class:`~batches.segment.Segment` a worker
hands the learner. ``rollout`` builds segments, ``learners`` trains on them; neither
imports the other, and nothing here imports either.
"""
