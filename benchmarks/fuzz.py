"""Fuzz every reader of dm2 with mutated inputs and count how each input ends.

    python benchmarks/fuzz.py --budget 10000 [--family tum --family ply] [--out results.json] [--timeout 10]

Inputs, mutations and the oracle are ``tests/fuzzing.py`` (shared with the in-suite budget,
``tests/test_fuzz.py``): per family, seeds written with dm2's own writers (plus small real files from
``../shared/data`` when present), mutated deterministically by input index. Each input runs in a worker
process through what ``dm2 info`` and ``dm2 convert`` run; a worker killed by a signal (a native crash), one
that runs past ``--timeout`` seconds or exceeds its memory limit is counted as a failure of that kind and
replaced, so one bad input never ends the run. Writes per family: inputs tried, clean errors, clean reads,
failures by kind with examples (input index, so that ``tests/fuzzing.make_input`` regenerates the reproducer).
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import platform
import resource
import shutil
import signal
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

import fuzzing  # noqa: E402  (tests/fuzzing.py, shared with the test suite)

DATA = ROOT.parent / "shared" / "data"
#: address-space headroom of a worker beyond what it holds after imports (memory blow-ups fail as "memory")
MEMORY_HEADROOM = 2 << 30


def _worker(conn, family: str, base_seed: int, work: str, real: bool) -> None:
    import warnings

    warnings.simplefilter("ignore")
    import logging

    logging.disable(logging.WARNING)  # readers warn on odd-but-readable input; the counts are what matters
    extra = fuzzing.real_seeds(family, DATA) if real else []
    fuzzing.seeds(family, extra)  # build the seeds before limiting memory
    with open("/proc/self/statm") as fh:
        vm = int(fh.read().split()[0]) * os.sysconf("SC_PAGE_SIZE")
    resource.setrlimit(resource.RLIMIT_AS, (vm + MEMORY_HEADROOM, resource.RLIM_INFINITY))
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 1)
    os.dup2(devnull, 2)  # C libraries print to the terminal
    conn.send("ready")
    while True:
        index = conn.recv()
        if index is None:
            return
        files, entry, topic = fuzzing.make_input(family, index, base_seed, extra)
        outcome = fuzzing.check(family, files, entry, topic, Path(work) / "case")
        conn.send((outcome.kind, outcome.detail))


class Pool1:
    """One worker process, replaced when it dies or hangs."""

    def __init__(self, family: str, base_seed: int, work: Path, real: bool) -> None:
        self.args = (family, base_seed, str(work), real)
        self.proc = None
        self.conn = None

    def start(self) -> None:
        parent, child = mp.Pipe()
        self.proc = mp.get_context("fork").Process(target=_worker, args=(child, *self.args), daemon=True)
        self.proc.start()
        self.conn = parent
        if not parent.poll(300) or parent.recv() != "ready":
            raise RuntimeError("fuzz worker did not start")

    def kill(self) -> None:
        if self.proc is not None and self.proc.is_alive():
            self.proc.kill()
        if self.proc is not None:
            self.proc.join(5)
        self.proc = None

    def run(self, index: int, timeout: float) -> fuzzing.Outcome:
        if self.proc is None or not self.proc.is_alive():
            self.start()
        self.conn.send(index)
        if self.conn.poll(timeout):
            try:
                kind, detail = self.conn.recv()
                return fuzzing.Outcome(kind, detail)
            except EOFError:
                pass
        alive = self.proc.is_alive()
        if not alive:
            self.proc.join(5)
        code = self.proc.exitcode
        self.kill()
        if alive:
            return fuzzing.Outcome("timeout", f"> {timeout:g} s")
        return fuzzing.Outcome(_signal_kind(code), f"exit code {code}")

    def close(self) -> None:
        if self.proc is not None and self.proc.is_alive():
            self.conn.send(None)
            self.proc.join(10)
        self.kill()


def _signal_kind(code) -> str:
    if isinstance(code, int) and code < 0:
        try:
            return f"signal:{signal.Signals(-code).name}"
        except ValueError:
            return f"signal:{-code}"
    return f"died:{code}"


def run_family(family: str, budget: int, base_seed: int, timeout: float, real: bool, wall: float | None) -> dict:
    stats = {"family": family, "inputs": 0, "clean_errors": 0, "clean_reads": 0, "failures": {}, "examples": []}
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix=f"dm2-fuzz-{family}-") as work:
        pool = Pool1(family, base_seed, Path(work), real)
        try:
            for index in range(budget):
                if wall is not None and time.perf_counter() - t0 > wall:
                    stats["stopped"] = f"wall-time limit {wall:g} s"
                    break
                outcome = pool.run(index, timeout)
                if outcome.kind == "timeout" or outcome.kind.startswith(("signal:", "died:")):
                    # a killed worker may have left its temporary files; start the next input clean
                    for p in Path(work).iterdir():
                        shutil.rmtree(p, ignore_errors=True) if p.is_dir() else p.unlink(missing_ok=True)
                fuzzing.record(stats, index, outcome)
        finally:
            pool.close()
    stats["seconds"] = round(time.perf_counter() - t0, 1)
    return stats


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--budget", type=int, default=10_000, help="inputs per family")
    parser.add_argument("--family", action="append", choices=sorted(fuzzing.FAMILIES), help="(repeatable)")
    parser.add_argument("--seed", type=int, default=0, help="base seed of the mutations")
    parser.add_argument("--timeout", type=float, default=fuzzing.SLOW_S, help="seconds per input")
    parser.add_argument("--wall", type=float, default=None, help="seconds per family at most")
    parser.add_argument("--no-real", action="store_true", help="generated seeds only (no ../shared/data)")
    parser.add_argument("--out", type=Path, default=None, help="results JSON (default: print only)")
    args = parser.parse_args(argv)
    families = args.family or list(fuzzing.FAMILIES)
    results = []
    for family in families:
        stats = run_family(family, args.budget, args.seed, args.timeout, not args.no_real, args.wall)
        results.append(stats)
        fails = sum(stats["failures"].values())
        print(f"{family:18s} {stats['inputs']:6d} inputs  {stats['clean_errors']:6d} clean errors  "
              f"{stats['clean_reads']:6d} clean reads  {fails:4d} failures {stats['failures'] or ''}  "
              f"({stats['seconds']} s)", flush=True)
    doc = {
        "command": "python benchmarks/fuzz.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        "budget_per_family": args.budget, "seed": args.seed, "timeout_s": args.timeout,
        "real_seeds": not args.no_real and DATA.is_dir(), "python": platform.python_version(),
        "families": results,
        "total": {"inputs": sum(r["inputs"] for r in results),
                  "failures": sum(sum(r["failures"].values()) for r in results)},
    }
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(doc, indent=1) + "\n")
    return 1 if doc["total"]["failures"] else 0


if __name__ == "__main__":
    sys.exit(main())
