"""Run the stateful file-safety property (``tests/file_safety_machine.py``) on a large budget and count.

    python benchmarks/fuzz_files.py --examples 2000 [--steps 12]

Each example is a fresh folder and a random sequence of the user's things, crafted markers and locks, and real dm2
commands into it (with ``--force`` or not, failing, interrupted or intruded on at a random write); after every
step every byte the user had is checked. Writes ``benchmarks/results/<date>-fuzz-files.json``: examples and dm2
commands run, and the first failure found (hypothesis shrinks it to its shortest sequence), if any.
"""

from __future__ import annotations

import argparse
import datetime
import json
import sys
import time
import traceback
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

from file_safety_machine import FileSafety  # noqa: E402
from hypothesis import HealthCheck, settings  # noqa: E402
from hypothesis.stateful import run_state_machine_as_test  # noqa: E402


class Counted(FileSafety):
    examples = 0
    commands = 0

    def __init__(self) -> None:
        super().__init__()
        Counted.examples += 1

    def teardown(self) -> None:
        Counted.commands += self.runs
        super().teardown()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--examples", type=int, default=2000)
    ap.add_argument("--steps", type=int, default=12)
    args = ap.parse_args()
    t0 = time.perf_counter()
    failure = None
    try:
        run_state_machine_as_test(Counted, settings=settings(
            max_examples=args.examples, stateful_step_count=args.steps, deadline=None, database=None,
            suppress_health_check=list(HealthCheck)))
    except Exception:  # the property failed: keep the shrunk sequence
        failure = traceback.format_exc()[-4000:]
    result = {"examples": Counted.examples, "dm2_commands": Counted.commands, "steps_per_example": args.steps,
              "failed": failure is not None, "failure": failure, "seconds": round(time.perf_counter() - t0, 1),
              "command": "python benchmarks/fuzz_files.py " + " ".join(sys.argv[1:])}
    out = ROOT / "benchmarks" / "results" / f"{datetime.date.today().isoformat()}-fuzz-files.json"
    out.write_text(json.dumps(result, indent=1))
    print(json.dumps({k: v for k, v in result.items() if k != "failure"}), failure or "")
    sys.exit(1 if failure else 0)


if __name__ == "__main__":
    main()
