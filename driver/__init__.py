"""driver: the process that drives a run, Ray's own word for it. The command line
(``cli``, its options declared once in ``options``), the wiring of a run's system
(``system``), the local Ray (``local_ray``); one training run (``training``), many runs
under Ray Tune (``tuning``), and demonstration recording (``recording``).

The one composition root: the only package that imports both ``rollout`` (the actor side
and the service) and ``learners``.
"""
