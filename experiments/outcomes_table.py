"""Protocol A's outcomes per goal direction of a run, summed over its seeds: how many
episodes were correct, pushed the disk the wrong way, or never moved it (the failure
kinds of docs/arm.md).  Reads ``<run>/<method>/eval.json``; trains nothing.

    .venv/bin/python experiments/outcomes_table.py runs/arm_levers/arm/fingertip_offsets \\
        --methods lazy scripted
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path


def outcomes(run_dir: Path, method: str) -> dict[float, dict[str, int]]:
    """``goal -> {correct, wrong, not_pushed}`` summed over the run's seeds."""
    table: dict[float, dict[str, int]] = {}
    for seed in json.loads((run_dir / method / "eval.json").read_text())["per_seed"]:
        for row in seed["protocol_a"]["per_goal"]:
            cell = table.setdefault(round(row["goal"], 4), dict.fromkeys(("correct", "wrong", "not_pushed"), 0))
            for kind in cell:
                cell[kind] += int(row[kind])
    return table


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("run_dir", type=Path)
    ap.add_argument("--methods", nargs="+", default=["lazy"])
    args = ap.parse_args()
    for method in args.methods:
        table = outcomes(args.run_dir, method)
        total = {k: sum(c[k] for c in table.values()) for k in ("correct", "wrong", "not_pushed")}
        print(f"\n{method} ({args.run_dir}): episodes correct / wrong direction / not pushed")
        print("| goal (deg) | correct | wrong | not pushed |\n|---|---|---|---|")
        for goal, c in sorted(table.items()):
            print(f"| {math.degrees(goal):.1f} | {c['correct']} | {c['wrong']} | {c['not_pushed']} |")
        print(f"| all | {total['correct']} | {total['wrong']} | {total['not_pushed']} |")


if __name__ == "__main__":
    main()
