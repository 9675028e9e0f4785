"""The stateful file-safety property (:mod:`file_safety_machine`) on a bounded budget; ``benchmarks/fuzz_files.py``
runs it longer."""

from __future__ import annotations

from file_safety_machine import FileSafety
from hypothesis import HealthCheck, settings

TestFileSafety = FileSafety.TestCase
TestFileSafety.settings = settings(max_examples=30, stateful_step_count=10, deadline=None, derandomize=True,
                                   suppress_health_check=list(HealthCheck))
