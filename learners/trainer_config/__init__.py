"""ML-Agents' trainer-config YAML: its parsing, its keys and their checks, environment parameters,
resolved settings and the registry of trainer types."""
