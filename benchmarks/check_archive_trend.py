"""Score `online-id trend` on a simulated archive: every bench's condition and onset against what the trend found.

    online-id archive simulate ARCHIVE && online-id archive identify ARCHIVE --out RESULTS
    online-id trend RESULTS --out TREND
    .venv/bin/python benchmarks/check_archive_trend.py ARCHIVE/truth.json TREND/trend.json

A bench with wear or a sudden fault must have an alert and its resonance's onset within 7 days of the
truth; a healthy bench no trend at all. Exits 1 when one does not.
"""

from __future__ import annotations

import datetime as dt
import json
import sys


def main(truth_path: str, trend_path: str) -> int:
    truth = {b["bench"]: b for b in json.load(open(truth_path))["benches"]}
    found = {b["bench"]: b for b in json.load(open(trend_path))["benches"]}
    ok = True
    print("| bench | truth | onset (truth) | found | onset (found) | days off | drift %/month of f0 [95 %] |")
    print("|---|---|---|---|---|---:|---|")
    for name, t in sorted(truth.items()):
        f = found.get(name)
        onset = dt.datetime.fromisoformat(t["onset"]) if t["onset"] else None
        got = dt.datetime.fromisoformat(f["onset"]).replace(tzinfo=dt.timezone.utc) if f and f["onset"] else None
        off = abs((got - onset).total_seconds()) / 86400.0 if onset and got else None
        freq = [s for s in (f or {}).get("series", []) if s["quantity"] == "resonance"]
        drift = "; ".join(f"{s['speed_rpm']} rpm {s['drift_pct_per_month']:+.2f} [{s['drift_ci_low']:+.2f}, "
                          f"{s['drift_ci_high']:+.2f}]" for s in freq if s["drift_pct_per_month"] is not None)
        if t["condition"] == "healthy":
            good = f is not None and f["verdict"] == "no trend"
        else:
            good = f is not None and f["level"] >= 1 and off is not None and off <= 7.0
        ok &= good
        cond = t["condition"] + (f" {t['wear_per_month_pct']:.1f} %/month" if t["condition"] == "wear" else "")
        print(f"| {name} | {cond} | {onset:%Y-%m-%d} |" if onset else f"| {name} | {cond} | - |",
              f"{(f or {}).get('verdict', 'missing')} | {got:%Y-%m-%d} |" if got else
              f"{(f or {}).get('verdict', 'missing')} | - |",
              f"{off:.1f} |" if off is not None else "- |", drift, "|" if good else "| MISSED")
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main(*sys.argv[1:3]))
