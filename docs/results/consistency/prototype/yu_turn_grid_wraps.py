"""A fix's turn about its rectangle's normal against the ray grid's alignment with the face's
edges (thirteenth session, issue 18). For each fix of the given runs (gross fixes left out):
the sensor's ray grid (rows along S's x, columns along S's z, about the line of sight: the
simulated flash LIDAR's window grid) projected on the face along the view, scaled to the
fix's area per point; for each lattice family, the number of times its phase wraps along the
long edge (``a |k . y_P|``) and along the short edge (``b |k . x_P|``), the smaller of the
two families taken (``r_long``, ``r_short``); printed: the turn's squared error whitened by
the filter's fix model at scale 1 (fixes.fix_noise, white and slow), binned by them.

Usage: python yu_turn_grid_wraps.py SCENARIO RUNS (e.g. yu2019 0,1,2,3)
"""
import sys, numpy as np
sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parents[4] / "benchmarks"))
from yu2019_fix_errors import fix_errors, gross
from tumblenav.scenario import load_scenario
from tumblenav.simulation import target_model
from tumblenav.estimators.yu2019.fixes import fix_noise
sc = load_scenario(sys.argv[1]); runs = [int(s) for s in sys.argv[2].split(",")]
model = target_model(sc); sigma = sc.sensor.range_noise_m
cen = {r.name: np.asarray(r.centre_M, float) for r in model.rectangles}
RL, RS, Z2 = [], [], []
for run in runs:
    for k, fx, za, zp, ea in fix_errors(sc, run):
        if gross(za, zp): continue
        c = cen.get(fx.rectangle, np.zeros(3))
        view = fx.p_MinS + fx.R_SM @ c
        nz = fix_noise(fx, sigma, 3*sigma, centre_M=c, view_S=view)
        C = nz.cov() + (lambda F: F @ F.T)(nz.slow_factor())
        e = fx.R_MP.T @ ea
        R_SP = fx.R_SM @ fx.R_MP
        n = R_SP[:, 2]; d = view / np.linalg.norm(view)
        b, a = fx.sides_m
        # lattice steps on the face (per unit ray-angle step), in P's in-plane coords
        S = []
        for ax in (np.array([1.0, 0, 0]), np.array([0, 0, 1.0])):
            s = ax - (n @ ax) / (n @ d) * d
            S.append((R_SP.T @ s)[:2])
        S = np.array(S)  # rows s1, s2 (unscaled)
        # scale: area per point = a b / n = |det(S)| * scale^2
        scale = np.sqrt(a * b / max(fx.n_points, 3) / abs(np.linalg.det(S)))
        S = S * scale
        K = np.linalg.inv(S).T  # reciprocal: rows k_i with k_i . s_j = delta_ij
        rl = min(a * abs(K[i] @ [0, 1.0]) for i in range(2))
        rs = min(b * abs(K[i] @ [1.0, 0]) for i in range(2))
        RL.append(rl); RS.append(rs); Z2.append(e[2]**2 / C[2, 2])
RL, RS, Z2 = map(np.array, (RL, RS, Z2))
for name, R in (("r_long", RL), ("r_short", RS), ("max", np.maximum(RL, RS))):
    print(name)
    for lo, hi in [(0,0.25),(0.25,0.5),(0.5,1),(1,2),(2,4),(4,8),(8,16),(16,32),(32,1e9)]:
        m = (R >= lo) & (R < hi)
        if m.sum(): print(f"  {lo:5.2f}-{hi:5.2f} n={m.sum():4d} mean z^2 {Z2[m].mean():.3f} median {np.median(Z2[m]):.3f}")
