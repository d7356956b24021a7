"""Per run of a campaign folder (``tumblenav montecarlo ... -o OUT``): the attitude error's RMS
over the steady-state window, its largest value, the last time with an estimate (a run
stopped as diverged has none after it) and the mean NEES/dof over the window. Fifteenth session, issue 18: Chang's printed 59 m on
point tracks, as shipped and with chang_check_epoch_sigma.patch applied to a checkout::

    python -c "import yaml; d = yaml.safe_load(open('src/tumblenav/scenarios/chang2021.yaml')); \\
        del d['sensor']['images']; d['name'] = 'chang2021_points59'; \\
        yaml.safe_dump(d, open('/tmp/c59pt.yaml', 'w'), sort_keys=False)"
    tumblenav montecarlo /tmp/c59pt.yaml --runs 6 --workers 1 --no-plots -o OUT
    python chang_far_runs.py OUT 40 120

Sixteenth session: the per-run NEES/dof of the rendered-images campaign
(``python benchmarks/consistency.py -o OUT --workers 2 --only chang2021_close_images``, then
``python chang_far_runs.py OUT/chang2021_close_images 40 120``).

Usage: python chang_far_runs.py OUT T0 T1
"""

import sys
from pathlib import Path

import numpy as np

t0, t1 = float(sys.argv[2]), float(sys.argv[3])
for f in sorted(Path(sys.argv[1], "runs").glob("run_*.npz")):
    z = np.load(f)
    t, a = z["t"], z["err_attitude_deg"]
    fin = np.isfinite(a)
    w = fin & (t >= t0) & (t <= t1)
    rms = np.sqrt(np.mean(a[w] ** 2)) if w.any() else np.nan
    last = t[fin][-1] if fin.any() else np.nan
    big = np.max(a[fin]) if fin.any() else np.nan
    nees = np.nanmean(z["nees"][(t >= t0) & (t <= t1)] / z["nees_dof"])
    print(
        f"{f.stem}: attitude RMS {rms:.3g} deg over {t0:g}-{t1:g} s, max {big:.3g} deg, last "
        f"estimate at {last:.0f} s, NEES/dof {nees:.2f}"
    )
