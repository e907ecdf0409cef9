"""driver: the process that drives a run, Ray's own word for it. The command line
(``cli``, its options declared once in ``options``), the train loop (``train``), its
summaries, checkpoints and learner keeper, start-up timing and the local Ray.

The one composition root: the only package that imports both ``rollout`` (the actor side
and the service) and ``learners``.
"""
