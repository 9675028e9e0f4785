"""Compare every metric of two results files of one benchmark set (timings and memory left out).

    python benchmarks/compare_sets.py benchmarks/results/A.json benchmarks/results/B.json

Prints the cases, the metrics compared and every one whose relative difference exceeds 1e-7."""

import json
import sys


def main(before: str, after: str, tolerance: float = 1e-7) -> int:
    a, b = (json.load(open(p)) for p in (before, after))
    A = {(c["dataset"], c["method"]): c for c in a["cases"]}
    B = {(c["dataset"], c["method"]): c for c in b["cases"]}
    if A.keys() != B.keys():
        print("the sets hold different cases:", sorted(A.keys() ^ B.keys()))
        return 1
    count, differ = 0, []
    for key, case in A.items():
        for metric, va in (case.get("metrics") or {}).items():
            vb = B[key]["metrics"].get(metric)
            count += 1
            if va is None or vb is None:
                if va != vb:
                    differ.append((key, metric, va, vb))
            elif abs(va - vb) > tolerance * max(1.0, abs(va)):
                differ.append((key, metric, va, vb))
    print(f"{len(A)} cases, {count} metrics; {len(differ)} differ by more than {tolerance:g} (relative)")
    for key, metric, va, vb in differ:
        print(f"  {key[0]} / {key[1]} / {metric}: {va!r} -> {vb!r}")
    return 0


if __name__ == "__main__":
    sys.exit(main(*sys.argv[1:3]))
