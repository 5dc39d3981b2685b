"""One table of the accuracy checks of several test runs (make test-portable).

Reads the JSON lines the `accuracy` test fixture appends to ORCHARD_ACCURACY_LOG (one line per check:
test, quantity, value, limit, kind, switches) and prints, per check, the limit, the value of the default
run and the worst value over all runs (with the switches of that run). A check whose worst value comes
within 20 % of its limit is fragile. Exit status 1 if any check failed or is fragile.

    python scripts/accuracy_table.py build/accuracy.jsonl
"""

from __future__ import annotations

import json
import sys
from collections import defaultdict
from pathlib import Path

FRAGILE_FRACTION = 0.2


def used(rec: dict) -> float:
    """How close to its limit, to pick each check's worst run (1 = at the limit, larger = failed): value / limit
    for an upper limit, 2 - value / limit for a lower one (20 % above the limit: 0.8)."""
    v, lim = rec["value"], rec["limit"]
    if rec["kind"] == "max":
        return v / lim if lim else float("inf")
    return 1.0 + (1.0 - v / lim) if lim else float("inf")


def main(path: str) -> int:
    rows: dict[tuple[str, str], list[dict]] = defaultdict(list)
    for line in Path(path).read_text().splitlines():
        if line.strip():
            rec = json.loads(line)
            rows[rec["test"], rec["quantity"]].append(rec)
    runs = sorted({r["switches"] for recs in rows.values() for r in recs})
    print(f"accuracy checks over {len(runs)} runs: {', '.join(runs)}\n")
    print("| test | quantity | limit | value (default) | worst (run) | worst / limit |")
    print("|---|---|---|---|---|---|")
    bad = 0
    for (test, quantity), recs in sorted(rows.items()):
        worst = max(recs, key=used)
        default = [r for r in recs if r["switches"] == "default"]
        sign = "<=" if worst["kind"] == "max" else ">="
        flag = ""
        if not all(r["ok"] for r in recs):
            flag, bad = " FAILED", bad + 1
        elif any(r["fragile"] for r in recs):  # marked by the fixture (test/conftest.py), one rule
            flag, bad = " FRAGILE", bad + 1
        name = test.split("::", 1)[-1]
        print(f"| {name} | {quantity} | {sign} {worst['limit']:.4g} | "
              f"{default[0]['value']:.4g} | " if default else f"| {name} | {quantity} | {sign} {worst['limit']:.4g} | - | ",
              end="")
        print(f"{worst['value']:.4g} ({worst['switches']}) | {worst['value'] / worst['limit']:.2f}{flag} |")
    print(f"\n{len(rows)} checks; {bad} failed or fragile (within {100 * FRAGILE_FRACTION:.0f} % of the limit)")
    return 1 if bad else 0


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit(__doc__)
    sys.exit(main(sys.argv[1]))
