"""The project's experiment scripts (benchmarks, reports), run from the repository root as
``python -m experiments.<name>``; their shared helpers are in ``experiments.common``."""
