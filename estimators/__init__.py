"""lidarcam estimators: measurement extraction, solvers, data I/O, simulator, CLI."""

__version__ = "0.2.0"
