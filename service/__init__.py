"""netpose service package: estimator core, filter, configuration, daemon wiring and CLI."""

__version__ = "0.1.0"
