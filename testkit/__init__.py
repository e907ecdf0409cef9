"""testkit: the test doubles and tooling that only the tests and benchmarks use (synthetic
segments, workers without Unity, fault injection). Not installed with the product; tests
and benchmarks import it from the repository root."""
