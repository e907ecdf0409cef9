"""The service between the workers and the learner: workers kept collecting, demand, back-pressure,
supervision of failures, elastic membership, metrics."""
