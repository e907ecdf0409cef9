"""The benchmarks, grouped by the question they answer: ``speed`` (how fast collection,
scaling, the learner and start-up are), ``learning`` (how a run learns, against
mlagents-learn too), ``equality`` (the same computation as mlagents-learn's own code),
``costs`` (what faults and memory cost) and ``device`` (the GPU machine's checks).

Run from the repository root as modules, ``.venv/bin/python -m benchmarks.speed.bench_scale``;
``benchmarks/README.md`` lists them. Nothing here is imported by the product. This file
and every sub-package's ``__init__`` import nothing: mlagents-learn's own Python (the
anchor's venv) imports this package to run the equality checks' ML-Agents side.
"""
