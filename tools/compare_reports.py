"""Compare two JSON reports (report.json, model.json) of runs that should agree: every key and string equal,
every number equal within a relative tolerance; the run's date and the program's version aside.

    python tools/compare_reports.py A/report.json B/report.json [--rel 1e-9] [--ignore date_utc,version]

Exit 0 when they agree (it prints how many numbers it compared and the largest relative difference);
exit 1 with each difference's JSON path otherwise. Keys only B has are listed as additions and do not fail
(a new record field is an addition, not a change); keys only A has fail.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import dataclass, field


@dataclass
class Comparison:
    rel: float
    ignore: frozenset[str]
    numbers: int = 0
    largest_rel: float = 0.0
    differences: list[str] = field(default_factory=list)
    additions: list[str] = field(default_factory=list)

    def walk(self, a: object, b: object, path: str) -> None:
        if isinstance(a, dict) and isinstance(b, dict):
            for key in a:
                if key in self.ignore:
                    continue
                if key not in b:
                    self.differences.append(f"{path}.{key}: only in the first")
                else:
                    self.walk(a[key], b[key], f"{path}.{key}")
            self.additions += [f"{path}.{key}" for key in b if key not in a and key not in self.ignore]
        elif isinstance(a, list) and isinstance(b, list):
            if len(a) != len(b):
                self.differences.append(f"{path}: {len(a)} items against {len(b)}")
            for i, (x, y) in enumerate(zip(a, b, strict=False)):
                self.walk(x, y, f"{path}[{i}]")
        elif _number(a) and _number(b):
            self.numbers += 1
            if a == b or (isinstance(a, float) and math.isnan(a) and math.isnan(b)):
                return
            rel = abs(a - b) / max(abs(a), abs(b))
            self.largest_rel = max(self.largest_rel, rel)
            if rel > self.rel:
                self.differences.append(f"{path}: {a!r} against {b!r} (relative {rel:.2e})")
        elif a != b:
            self.differences.append(f"{path}: {a!r} against {b!r}")


def _number(x: object) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("first")
    ap.add_argument("second")
    ap.add_argument("--rel", type=float, default=1e-9, help="relative tolerance of numbers (default 1e-9)")
    ap.add_argument("--ignore", default="date_utc,version", help="keys left out (default date_utc,version)")
    args = ap.parse_args(argv)
    with open(args.first) as fa, open(args.second) as fb:
        a, b = json.load(fa), json.load(fb)
    cmp = Comparison(args.rel, frozenset(k for k in args.ignore.split(",") if k))
    cmp.walk(a, b, "$")
    for line in cmp.additions:
        print(f"added: {line}")
    for line in cmp.differences:
        print(f"differs: {line}")
    print(
        f"{cmp.numbers} numbers compared, largest relative difference {cmp.largest_rel:.2e}; "
        f"{len(cmp.differences)} differences, {len(cmp.additions)} additions"
    )
    return 1 if cmp.differences else 0


if __name__ == "__main__":
    sys.exit(main())
