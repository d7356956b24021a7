"""The inertia least squares' residual ratio per run (twenty-third session, issue 18): runs
benchmarks/block_nees.py with the same arguments and records, at every solution of the front
end, rss / expect, the momentum walk's share of expect, the axes it is spread over and whether
the covariance was scaled (inertia_ls._residual_scale); prints their medians over the second
half of the solutions, one line per run, after block_nees' own lines.

Usage (from the repository root)::

    python docs/results/consistency/prototype/hu_residual_scale.py SCENARIO ESTIMATOR --seeds 0,1,2
"""

import runpy
import sys
from pathlib import Path

import numpy as np

from tumblenav.frontends.stereo_points import inertia_ls as L

orig = L._residual_scale
rec = []


def wrap(rss, expect, walk, rows, corr, axes=3.0):
    s, g = orig(rss, expect, walk, rows, corr, axes)
    e = np.maximum(expect, 1e-30)
    rec.append((rss / e, np.clip(walk / e, 0, 1), s, np.broadcast_to(axes, np.shape(rss))))
    return s, g


L._residual_scale = wrap
bench = Path(__file__).resolve().parents[4] / "benchmarks" / "block_nees.py"
sys.argv = [str(bench)] + sys.argv[1:]
runpy.run_path(str(bench), run_name="__main__")
for r, w, s, ax in rec:
    late = slice(r.shape[-1] // 2, None)
    print(
        "ratio median(late) %.2f  walk share %.2f  axes %.2f  scaled fraction %.2f"
        % (np.nanmedian(r[..., late]), np.nanmedian(w[..., late]), np.nanmedian(ax[..., late]),
           np.mean(s[..., late] > 1))
    )
