"""Speed of the truth attitude propagation (timings live here, never in tests/).

Ends with one line: ``kabir_3000s_s=<s> hu_200s_s=<s>``.
"""

import time

import numpy as np

from tumblenav import dynamics as dyn

Q0 = np.array([0.0, 0.0, 0.0, 1.0])
t0 = time.perf_counter()
w = 2 * np.pi * 0.175 * np.array([2 / 3, 1 / 3, 2 / 3])
dyn.propagate_attitude(Q0, w, [90.0, 100.0, 112.0], np.arange(3001.0))
t1 = time.perf_counter()
dyn.propagate_attitude(Q0, [0.1, 0.1, 0.1], [8.0, 5.0, 4.0], np.arange(2001) * 0.1)
t2 = time.perf_counter()
print(f"kabir_3000s_s={t1 - t0:.3f} hu_200s_s={t2 - t1:.3f}")
