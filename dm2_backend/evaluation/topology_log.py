"""The place recognition's log as a run-folder document (``topology.json``).

``Topology.log[0]`` is the plugin's summary; every other entry with frames ``i`` and ``j`` is a loop-closure
candidate with its scores and ``reason``; ``dropped: true`` marks a closure that the final robust solve
dropped. Each candidate gets a ``status``:

- ``accepted``: in the final topology (``accepted`` and not dropped);
- ``dropped``: accepted, then dropped by the final robust solve;
- ``verified``: passed the gates but was never accepted (e.g. no second closure confirmed it);
- ``rejected``: failed the gates (``reason`` says which).

Plugins that log no ``verified`` flag (``descriptor``) count a candidate as verified when it was accepted.
"""

from __future__ import annotations

import re
from collections import Counter

import numpy as np

from dm2_backend.kernel.prepared import Topology

DROPPED = "dropped by the final robust solve"
STATUSES = ("accepted", "dropped", "verified", "rejected")
_STATUS_REASON = {"accepted": "accepted", "dropped": DROPPED, "verified": "verified, not accepted"}
_NUMBER = re.compile(r"[-+]?\d+(?:\.\d+)?(?:e[-+]?\d+)?")


def reason_kind(part: str) -> str:
    """One reason with its numbers replaced by ``#``, so equal causes count together."""
    return _NUMBER.sub("#", part.strip())


def candidates(log: list[dict]) -> list[dict]:
    """Copies of the candidate entries of a topology log, each with its ``status``."""
    out = []
    for e in log[1:]:
        if not (isinstance(e, dict) and "i" in e and "j" in e):
            continue
        c = dict(e)
        verified = bool(c.get("verified", c.get("accepted", False)))
        if c.get("dropped"):
            c["status"] = "dropped"
        elif c.get("accepted"):
            c["status"] = "accepted"
        else:
            c["status"] = "verified" if verified else "rejected"
        out.append(c)
    return out


def document(topology: Topology) -> dict:
    """``topology.json``: the plugin's summary, counts, a histogram of reasons (rejections by cause, numbers
    masked; the others by status), the edge kinds, and every candidate with its scores, reason and status."""
    log = topology.log or [{}]
    cands = candidates(log)
    status = Counter(c["status"] for c in cands)
    reasons: Counter = Counter()
    for c in cands:
        reason = str(c.get("reason", "")) if c["status"] == "rejected" else _STATUS_REASON[c["status"]]
        reasons.update(reason_kind(p) for p in reason.split(";") if p.strip())
    summary = log[0] if log and "i" not in log[0] else {}
    return {
        "plugin": summary.get("plugin"),
        "summary": summary,
        "counts": {
            "candidates": len(cands),
            "verified": sum(status[s] for s in ("accepted", "dropped", "verified")),
            "accepted": status["accepted"],
            "dropped": status["dropped"],
            "rejected": status["rejected"],
            "verified_not_accepted": status["verified"],
        },
        "reasons": dict(reasons.most_common()),
        "edges": dict(Counter(topology.edge_kind)),
        "candidates": cands,
    }


def pairs_by_status(doc: dict) -> dict[str, np.ndarray]:
    """``status -> (M,2)`` frame pairs of a :func:`document`'s candidates; accepted closures across a corridor
    (with a free ``axis``) under ``"across"`` rather than ``"accepted"``."""
    def kind(c: dict) -> str:
        return "across" if c["status"] == "accepted" and c.get("axis") is not None else c["status"]

    return {s: np.array([(c["i"], c["j"]) for c in doc["candidates"] if kind(c) == s], dtype=int).reshape(-1, 2)
            for s in (*STATUSES, "across")}
