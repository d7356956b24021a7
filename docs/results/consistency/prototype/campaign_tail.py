"""Which runs carry a campaign's NEES (twenty-fourth session, issue 18): the per-run NEES/dof
in the summary's steady-state window of a `tumblenav montecarlo` output folder, the worst
first, with the mean and median over the runs.

Usage::

    python campaign_tail.py OUT [N]

hu_selfocc over 200 runs on the twenty-fourth session's code: mean 1.157, median 0.891; runs
147 (21.5) and 182 (14.8), then 2.3 and below.
"""

import json
import sys
from pathlib import Path

import numpy as np

d = Path(sys.argv[1])
show = int(sys.argv[2]) if len(sys.argv) > 2 else 8
w0, w1 = json.load(open(d / "summary.json"))["window_s"]
rows = []
for f in sorted((d / "runs").glob("run_*.npz")):
    z = np.load(f)
    m = (z["t"] >= w0) & (z["t"] <= w1) & np.isfinite(z["nees"])
    if m.any():
        rows.append(
            (float(np.sum(z["nees"][m]) / (m.sum() * float(z["nees_dof"]))), int(f.stem[4:]))
        )
rows.sort(reverse=True)
v = np.array([r[0] for r in rows])
print(f"runs {len(rows)} mean of per-run {v.mean():.3f} median {np.median(v):.3f}")
for value, run in rows[:show]:
    print(f"  run {run:4d} NEES/dof {value:.3g}")
