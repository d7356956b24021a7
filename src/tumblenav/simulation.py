"""Truth and sensor simulation for a scenario: the first two stages of the pipeline.

``simulate(scenario, seed)`` returns a :class:`Truth` and the sensor's measurements
(:class:`tumblenav.measurements.StereoMeasurements` or ``DepthMeasurements``, re-exported
here); both convert to self-describing xarray datasets (``truth.nc``, ``measurements.nc``;
see docs/formats.md).

Random streams: one ``SeedSequence`` per run is split into independent children for the
feature geometry, the truth and the sensor noise, so that changing the noise level of a
scenario keeps the same geometry and trajectory (common random numbers when estimators or
noise levels are compared head to head).
"""

from __future__ import annotations

import dataclasses
import functools
import os
from dataclasses import dataclass

import numpy as np
import xarray as xr
from numpy.typing import NDArray

from tumblenav import dynamics, sensors
from tumblenav import rotations as rot
from tumblenav.dynamics.disturbances import disturbed_attitude, translational_disturbance
from tumblenav.errors import InputError
from tumblenav.frames import lvlh_axes
from tumblenav.measurements import (
    STEREO_IMAGES,
    DepthMeasurements,
    StereoImageMeasurements,
    StereoMeasurements,
    kind_of,
)
from tumblenav.measurements._attrs import _a
from tumblenav.scenario import (
    DepthSensorConfig,
    RandomFeatures,
    Scenario,
    StereoSensorConfig,
)

Array = NDArray[np.float64]


@dataclass(frozen=True)
class Truth:
    """True motion, sampled at the scenario's times.

    Attributes
    ----------
    t : (n,) s
    q_TI, omega_TI_T : (n,4), (n,3) rad/s -- target attitude (maps I into T) and rate in T.
    r_L, v_L : (n,3) m, m/s -- target mass centre relative to the chaser, in L (rotating).
    q_LI : (n,4) -- LVLH attitude (maps I into L); identity when the chaser has no orbit.
    q_CL : (n,4) -- stereo rig attitude (maps L into the rig frame C).
    chaser_r_I, chaser_v_I : (n,3) -- chaser inertial state (zeros without an orbit).
    features_T : (N,3) m; normals_T : (N,3) -- feature points and outward normals in T.
    inertia_T : (3,3) kg m^2 in T; mass_centre_offset_T : (3,) m.
    """

    t: Array
    q_TI: Array
    omega_TI_T: Array
    r_L: Array
    v_L: Array
    q_LI: Array
    q_CL: Array
    chaser_r_I: Array
    chaser_v_I: Array
    features_T: Array
    normals_T: Array
    inertia_T: Array
    mass_centre_offset_T: Array

    @property
    def R_LT(self) -> Array:
        """(n,3,3): maps T into L."""
        return rot.quat_to_matrix(self.q_LI) @ np.swapaxes(rot.quat_to_matrix(self.q_TI), -1, -2)

    @property
    def q_CI(self) -> Array:
        """(n,4): rig attitude w.r.t. inertial (known to the chaser; Hu 2024 eq. 31)."""
        return rot.quat_multiply(self.q_CL, self.q_LI)

    @property
    def features_L(self) -> Array:
        """(n,N,3) m: feature positions relative to the chaser, in L (Hu 2024 eq. 32)."""
        # (t,N,3): R_LT(t) f_n, as one stacked matmul (einsum without a path is 10x slower)
        return self.r_L[:, None, :] + self.features_T @ np.swapaxes(self.R_LT, -1, -2)

    @property
    def features_C(self) -> Array:
        """(n,N,3) m: feature positions in the rig frame C (rig origin at the chaser CM)."""
        R_CL = rot.quat_to_matrix(self.q_CL)
        return self.features_L @ np.swapaxes(R_CL, -1, -2)  # (t,N,3): R_CL(t) p_n(t)

    def to_dataset(self, scenario_name: str = "") -> xr.Dataset:
        from tumblenav.io import with_coordinates

        ds = xr.Dataset(
            {
                "q_TI": (
                    ("time", "quat"),
                    self.q_TI,
                    _a("1", "target attitude: maps I into T; continuous in time (w may be < 0)"),
                ),
                "omega_TI_T": (
                    ("time", "xyz"),
                    self.omega_TI_T,
                    _a("rad/s", "rate of T relative to I, in T"),
                ),
                "r_L": (
                    ("time", "xyz"),
                    self.r_L,
                    _a("m", "position of the target mass centre relative to the chaser, in L"),
                ),
                "v_L": (
                    ("time", "xyz"),
                    self.v_L,
                    _a(
                        "m/s",
                        "velocity of the target mass centre relative to the chaser, seen from "
                        "the rotating L, in L",
                    ),
                ),
                "q_LI": (
                    ("time", "quat"),
                    self.q_LI,
                    _a("1", "LVLH attitude: maps I into L (identity without an orbit)"),
                ),
                "q_CL": (
                    ("time", "quat"),
                    self.q_CL,
                    _a("1", "attitude of the stereo rig or depth sensor: maps L into C"),
                ),
                "chaser_r_I": (
                    ("time", "xyz"),
                    self.chaser_r_I,
                    _a("m", "chaser position in I (zeros without an orbit)"),
                ),
                "chaser_v_I": (
                    ("time", "xyz"),
                    self.chaser_v_I,
                    _a("m/s", "chaser velocity in I (zeros without an orbit)"),
                ),
                "features_T": (
                    ("feature", "xyz"),
                    self.features_T,
                    _a("m", "feature points relative to the target mass centre, in T"),
                ),
                "normals_T": (
                    ("feature", "xyz"),
                    self.normals_T,
                    _a("1", "unit outward surface normals at the features, in T"),
                ),
                "inertia_T": (
                    ("row", "col"),
                    self.inertia_T,
                    _a("kg m^2", "inertia tensor of the target about its mass centre, in T"),
                ),
                "mass_centre_offset_T": (
                    ("xyz",),
                    self.mass_centre_offset_T,
                    _a(
                        "m",
                        "mass-centre offset b: the target mass centre relative to the model "
                        "origin, in T (Yu 2019)",
                    ),
                ),
            },
            attrs={
                "title": "tumblenav truth",
                "scenario": scenario_name,
                "quaternion_convention": "[x,y,z,w], Hamilton; q_AB maps B-coordinates into A",
                "frames": "I inertial; L LVLH (x along-track, y -orbit normal, z nadir); "
                "C stereo rig (x baseline, y boresight); T target principal axes",
            },
        )
        return with_coordinates(ds, time=self.t, feature=np.arange(len(self.features_T)))

    @classmethod
    def from_dataset(cls, ds: xr.Dataset) -> Truth:
        """The truth of a ``truth.nc`` dataset (variables by name; others are ignored)."""
        names = [k for k in cls.__dataclass_fields__ if k != "t"]
        g = {k: np.asarray(ds[k].values, dtype=float) for k in names}
        return cls(t=np.asarray(ds["time"].values, dtype=float), **g)


# --- the pieces ------------------------------------------------------------------------------


def run_streams(seed: int | np.random.SeedSequence) -> dict[str, np.random.Generator]:
    """Independent generators for one run: 'features', 'truth', 'sensor', 'estimator'."""
    ss = seed if isinstance(seed, np.random.SeedSequence) else np.random.SeedSequence(seed)
    names = ("features", "truth", "sensor", "estimator")
    return {n: np.random.default_rng(c) for n, c in zip(names, ss.spawn(len(names)), strict=True)}


def draw_features(scenario: Scenario, rng: np.random.Generator) -> tuple[Array, Array]:
    """Feature points (N,3) in T and their outward normals (N,3)."""
    f = scenario.target.features_T_m
    if f is None:
        return np.zeros((0, 3)), np.zeros((0, 3))
    if isinstance(f, RandomFeatures):
        g = np.random.default_rng(f.seed) if f.seed is not None else rng
        pts = g.uniform(f.low_m, f.high_m, size=(f.count, 3))
    else:
        pts = np.asarray(f, dtype=float)
    if scenario.target.feature_normals_T is not None:
        nrm = np.asarray(scenario.target.feature_normals_T, dtype=float)
    else:
        nrm = pts.copy()  # default: radial from the mass centre (a convex, roughly round body)
    norms = np.linalg.norm(nrm, axis=1, keepdims=True)
    nrm = np.where(norms > 1e-12, nrm / np.where(norms > 1e-12, norms, 1.0), [[0.0, 1.0, 0.0]])
    return pts, nrm


# The truth motion does not depend on the random streams, so Monte Carlo runs of one scenario
# share it: it is integrated once per process (the tight tolerances make it the costliest
# part of a run). Results are returned read-only.
@functools.lru_cache(maxsize=16)
def _attitude_truth(q0, w0, inertia, t_bytes) -> tuple[Array, Array]:
    t = np.frombuffer(t_bytes, dtype=float)
    q, w = dynamics.propagate_attitude(np.array(q0), np.array(w0), np.array(inertia), t)
    q.setflags(write=False)
    w.setflags(write=False)
    return q, w


@functools.lru_cache(maxsize=16)
def _orbit_truth(r0, v0, r0_L, v0_L, t_bytes, j2, mu):
    t = np.frombuffer(t_bytes, dtype=float)
    return dynamics.nonlinear_relative(
        np.array(r0), np.array(v0), np.array(r0_L), np.array(v0_L), t, j2=j2, mu=mu
    )


def simulate_truth(
    scenario: Scenario,
    rng_features: np.random.Generator,
    rng_truth: np.random.Generator | None = None,
) -> Truth:
    """Torque-free attitude (Euler + kinematics) and nonlinear relative orbit, both tight;
    with ``process_noise.disturb_truth`` the random torque and force of the scenario's process
    noise are added (:mod:`tumblenav.dynamics.disturbances`), drawn from ``rng_truth`` (the
    run's 'truth' stream; required then)."""
    t = scenario.times
    tg = scenario.target
    inertia = tg.inertia_matrix
    pn = scenario.process_noise
    disturbed = pn.disturb_truth and (pn.rotational_rad2_s4 > 0 or pn.translational_m2_s4 > 0)
    if disturbed and rng_truth is None:
        raise ValueError("process_noise.disturb_truth needs the run's truth generator")
    if disturbed and pn.rotational_rad2_s4 > 0:
        assert rng_truth is not None
        q_TI, omega = disturbed_attitude(
            tg.q0_TI, tg.omega0_T_rad_s, inertia, t, pn.rotational_rad2_s4, rng_truth
        )
    else:
        q_TI, omega = _attitude_truth(
            tuple(tg.q0_TI), tuple(tg.omega0_T_rad_s), tuple(map(tuple, inertia)), t.tobytes()
        )
    orbit = scenario.chaser.orbit
    n = len(t)
    if orbit is None:
        # Kabir 2025 Sec. 2.1: chaser inertially fixed, no gravity: L = I, force-free drift.
        r_L = np.asarray(tg.r0_L_m, float) + np.outer(t, tg.v0_L_m_s)
        v_L = np.broadcast_to(np.asarray(tg.v0_L_m_s, float), (n, 3)).copy()
        q_LI = np.tile(rot.IDENTITY, (n, 1))
        cr, cv = np.zeros((n, 3)), np.zeros((n, 3))
    else:
        r0, v0 = dynamics.circular_orbit_state(
            orbit.radius_m,
            np.radians(orbit.inclination_deg),
            np.radians(orbit.raan_deg),
            np.radians(orbit.arg_latitude_deg),
            orbit.mu_m3_s2,
        )
        rel = _orbit_truth(
            tuple(r0),
            tuple(v0),
            tuple(tg.r0_L_m),
            tuple(tg.v0_L_m_s),
            t.tobytes(),
            orbit.j2,
            orbit.mu_m3_s2,
        )
        r_L, v_L = np.array(rel.r_L), np.array(rel.v_L)
        cr, cv = np.array(rel.chaser_r_I), np.array(rel.chaser_v_I)
        q_LI = rot.matrix_to_quat(np.swapaxes(lvlh_axes(cr, cv), -1, -2))
    if disturbed and pn.translational_m2_s4 > 0:
        assert rng_truth is not None
        n_orbit = orbit.mean_motion_rad_s if orbit is not None else 0.0
        dr, dv = translational_disturbance(n_orbit, t, pn.translational_m2_s4, rng_truth)
        r_L, v_L = r_L + dr, v_L + dv
    if scenario.chaser.attitude == "target-pointing":
        R_LC = _target_pointing(scenario, r_L)
    else:
        R_LC = np.broadcast_to(scenario.chaser.R_LC_fixed, (n, 3, 3))
    q_CL = rot.matrix_to_quat(np.swapaxes(R_LC, -1, -2))
    feats, normals = draw_features(scenario, rng_features)
    return Truth(
        t=t,
        q_TI=q_TI,
        omega_TI_T=omega,
        r_L=r_L,
        v_L=v_L,
        q_LI=q_LI,
        q_CL=q_CL,
        chaser_r_I=cr,
        chaser_v_I=cv,
        features_T=feats,
        normals_T=normals,
        inertia_T=inertia,
        mass_centre_offset_T=np.asarray(tg.mass_centre_offset_T_m, float),
    )


def _target_pointing(scenario: Scenario, r_L: Array) -> Array:
    """``R_LC`` of a rig that keeps the target centred: the rig's ``y`` axis points at the
    target from the rig origin (the left camera); for a convergent rig, from the midpoint of
    the two cameras, so that the target sits symmetrically between the two toed-in views
    instead of ``toe_in_deg`` off the left camera's centre (3 fixed-point steps: the offset
    is a baseline against a range of metres)."""
    R_LC = sensors.target_pointing_R_LC(r_L)
    cfg = scenario.sensor
    if isinstance(cfg, StereoSensorConfig) and cfg.rig == "convergent":
        mid_C = np.array([cfg.baseline_m / 2, 0.0, 0.0])
        for _ in range(3):
            R_LC = sensors.target_pointing_R_LC(r_L - R_LC @ mid_C)
    return R_LC


def visibility(scenario: Scenario, truth: Truth, rig: sensors.StereoRig) -> NDArray[np.bool_]:
    """(n, 2, N) occlusion mask (True = not occluded) from the scenario's occlusion settings."""
    occ = scenario.occlusion
    t = truth.t
    n, N = len(t), truth.features_T.shape[0]
    vis = np.ones((n, 2, N), dtype=bool)
    sched = sensors.scheduled_mask(t, [(w.start_s, w.end_s) for w in occ.windows])
    vis &= sched[:, None, None]
    if occ.loss_from_s is not None:
        vis &= sensors.loss_from_mask(t, occ.loss_from_s)[:, None, None]
    if occ.self_occlusion:
        R_CL = rot.quat_to_matrix(truth.q_CL)
        n_C = truth.normals_T @ np.swapaxes(R_CL @ truth.R_LT, -1, -2)  # (t,N,3) in C
        centres = np.stack([rig.left.p_CkinC, rig.right.p_CkinC])
        vis &= sensors.self_occlusion_mask(truth.features_C, n_C, centres)
    return vis


def simulate_stereo(
    scenario: Scenario, truth: Truth, rng_sensor: np.random.Generator
) -> StereoMeasurements:
    cfg = scenario.sensor
    if not isinstance(cfg, StereoSensorConfig):
        raise InputError(f"scenario {scenario.name} has a {cfg.kind} sensor, not a stereo rig")
    rig = sensors.make_rig(cfg)
    noise_px = cfg.noise.sigma_px(cfg.focal_px)
    meas = sensors.measure(
        rig, truth.features_C, rng_sensor, noise_px, visible=visibility(scenario, truth, rig)
    )
    return StereoMeasurements(
        t=truth.t,
        uv=meas.uv,
        observed=meas.observed,
        q_CL=truth.q_CL,
        q_LI=truth.q_LI,
        rig=rig,
        noise_px=noise_px,
    )


def target_model(scenario: Scenario):
    """The target's geometry (procedural satellite or the user's mesh)."""
    from tumblenav import target_model as tm

    return tm.from_config(scenario.target.model)


def simulate_depth(
    scenario: Scenario, truth: Truth, rng_sensor: np.random.Generator
) -> DepthMeasurements:
    """Scan the target mesh at the true pose at every epoch (Yu 2019 Sec. 4)."""
    from tumblenav.sensors.depth import DepthSensor, scan

    cfg = scenario.sensor
    if not isinstance(cfg, DepthSensorConfig):
        raise InputError(f"scenario {scenario.name} has a {cfg.kind} sensor, not a depth sensor")
    sensor = DepthSensor(
        np.radians(cfg.fov_deg),
        cfg.points,
        cfg.range_noise_m,
        cfg.outlier_fraction,
        cfg.max_range_m,
    )
    model = target_model(scenario)
    R_SM, p_MinS = model_pose_in_rig(truth)
    clouds, masks = [], []
    for k in range(len(truth.t)):
        pts, ok = scan(sensor, model, R_SM[k], p_MinS[k], rng_sensor, on_target=cfg.on_target)
        clouds.append(pts)
        masks.append(ok)
    # keep only the returns, padded to a common length (missing = NaN, explicit mask)
    width = max(1, max(int(m.sum()) for m in masks))
    P = np.full((len(clouds), width, 3), np.nan)
    M = np.zeros((len(clouds), width), dtype=bool)
    for k, (pts, ok) in enumerate(zip(clouds, masks, strict=True)):
        P[k, : ok.sum()] = pts[ok]
        M[k, : ok.sum()] = True
    return DepthMeasurements(
        t=truth.t,
        points=P,
        observed=M,
        q_CL=truth.q_CL,
        q_LI=truth.q_LI,
        fov_rad=sensor.fov_rad,
        range_noise_m=sensor.range_noise_m,
    )


def model_pose_in_rig(truth: Truth) -> tuple[Array, Array]:
    """``R_CM`` (n,3,3) and ``p_MinC`` (n,3): the target model frame M (parallel to T, its origin
    at ``-b`` in T) in the rig frame C at every epoch."""
    R_CL = rot.quat_to_matrix(truth.q_CL)
    R_LT = truth.R_LT
    p_MinL = truth.r_L - np.einsum("tij,j->ti", R_LT, truth.mass_centre_offset_T)
    return R_CL @ R_LT, (R_CL @ p_MinL[:, :, None])[:, :, 0]


def sun_in_rig(scenario: Scenario, truth: Truth) -> Array:
    """(n,3): the unit vector towards the sun in C at every epoch; NaN rows in eclipse."""
    from tumblenav.frames import R_EARTH_M

    cfg = getattr(scenario.sensor, "images", None)
    if cfg is None:
        raise InputError(f"scenario {scenario.name} does not render images (sensor.images)")
    R_LI = rot.quat_to_matrix(truth.q_LI)
    if cfg.sun_direction_I is not None:
        sun_I = np.asarray(cfg.sun_direction_I, float)
    else:  # behind the chaser at the start, 30 deg off the line of sight (about L's y)
        back_L = -truth.r_L[0] / np.linalg.norm(truth.r_L[0])
        sun_I = R_LI[0].T @ (rot.exp_map(np.radians(30.0) * np.array([0.0, 1.0, 0.0])) @ back_L)
    norm = np.linalg.norm(sun_I)
    if not norm > 0:
        raise InputError("sensor.images.sun_direction_I must be a nonzero vector")
    sun_I = sun_I / norm
    sun_C = np.einsum("tij,tjk,k->ti", rot.quat_to_matrix(truth.q_CL), R_LI, sun_I)
    if cfg.eclipse and scenario.chaser.orbit is not None:
        r = truth.chaser_r_I  # cylindrical Earth shadow
        along = r @ sun_I
        perp = np.linalg.norm(r - along[:, None] * sun_I, axis=1)
        sun_C[(along < 0) & (perp < R_EARTH_M)] = np.nan
    return sun_C


@dataclass(frozen=True)
class RenderedFrames:
    """The image pairs of a simulated run, rendered when asked for (a run's images do not fit
    in memory); epoch ``k``'s noise comes from its own stream, so any order gives the same
    pixels."""

    renderer: object
    R_CM: Array
    p_MinC: Array
    sun_C: Array
    entropy: int

    def __len__(self) -> int:
        return len(self.R_CM)

    def pair(self, k: int):
        sun = self.sun_C[k]
        rng = np.random.default_rng([self.entropy, k])
        out = self.renderer.render(  # type: ignore[attr-defined]
            self.R_CM[k], self.p_MinC[k], None if np.isnan(sun).any() else sun, rng, truth=False
        )
        return out.images[0], out.images[1]


def image_renderer(scenario: Scenario):
    """The renderer of the scenario's images (target model, rig, light and camera noise)."""
    from tumblenav.sensors import render

    cfg = scenario.sensor
    assert isinstance(cfg, StereoSensorConfig) and cfg.images is not None
    im = cfg.images
    noise = None if im.noise is None else render.ImageNoise(**im.noise.model_dump())
    settings = render.RenderSettings(
        # both cores for one run; campaign workers (one per core) set 1
        threads=int(os.environ.get("TUMBLENAV_RENDER_THREADS", "2")),
        exposure=im.exposure,
        ambient=im.ambient,
        supersample=im.supersample,
        texture=im.texture,
        noise=noise,
    )
    return render.StereoRenderer(target_model(scenario), sensors.make_rig(cfg), settings)


def simulate_images(
    scenario: Scenario, truth: Truth, rng_sensor: np.random.Generator
) -> StereoImageMeasurements:
    """Stereo image pairs of the target at the true pose (Chang 2021 Sec. 3), rendered lazily."""
    cfg = scenario.sensor
    if not isinstance(cfg, StereoSensorConfig) or cfg.images is None:
        raise InputError(f"scenario {scenario.name} does not render images (sensor.images)")
    R_CM, p_MinC = model_pose_in_rig(truth)
    frames = RenderedFrames(
        image_renderer(scenario),
        R_CM,
        p_MinC,
        sun_in_rig(scenario, truth),
        int(rng_sensor.integers(2**62)),
    )
    return StereoImageMeasurements(
        t=truth.t,
        q_CL=truth.q_CL,
        q_LI=truth.q_LI,
        rig=sensors.make_rig(cfg),
        noise_px=cfg.noise.sigma_px(cfg.focal_px),
        source=frames,
    )


def with_track_truth(
    truth: Truth, images: StereoImageMeasurements, tracks: StereoMeasurements
) -> Truth:
    """``truth`` with ``features_T`` replaced by the true points of the image front end's
    tracks (feature axis = track ID), for judging estimators that estimate feature positions:
    the renderer's hit point at the left pixel where each track was first seen (the surface
    point under the corner, to the ~1/2 px of pixel-centre sampling: ~3 mm at 10 m), one truth
    render per epoch where a track starts. Tracks never seen (and a source that is not the
    renderer's) give NaN."""
    N = tracks.uv.shape[2]
    pts = np.full((N, 3), np.nan)
    src = images.source
    if not isinstance(src, RenderedFrames):
        return dataclasses.replace(truth, features_T=pts, normals_T=np.full((N, 3), np.nan))
    seen = tracks.observed[:, 0, :]
    first = np.argmax(seen, axis=0)
    has = seen.any(axis=0)
    b = np.asarray(truth.mass_centre_offset_T, float)
    for k in np.unique(first[has]):
        ids = np.flatnonzero(has & (first == k))
        sun = src.sun_C[k]
        out = src.renderer.render(  # type: ignore[attr-defined]
            src.R_CM[k],
            src.p_MinC[k],
            None if np.isnan(sun).any() else sun,
            np.random.default_rng(0),  # the noise does not touch the truth maps
            truth=True,
        )
        hit = np.asarray(out.hit_M[0])
        h, w = hit.shape[:2]
        u, v = tracks.uv[k, 0, ids, 0], tracks.uv[k, 0, ids, 1]
        col = np.clip(np.floor(u).astype(int), 0, w - 1)
        row = np.clip(np.floor(v).astype(int), 0, h - 1)
        pts[ids] = hit[row, col] - b  # M is T shifted by b: p_T = p_M - b
    return dataclasses.replace(truth, features_T=pts, normals_T=np.full((N, 3), np.nan))


Measurements = StereoMeasurements | DepthMeasurements | StereoImageMeasurements


def simulate(
    scenario: Scenario, seed: int | np.random.SeedSequence | None = None
) -> tuple[Truth, Measurements]:
    """Truth and measurements of one run; ``seed`` defaults to the scenario's base seed."""
    streams = run_streams(scenario.montecarlo.seed if seed is None else seed)
    truth = simulate_truth(scenario, streams["features"], streams["truth"])
    if kind_of(scenario.sensor) == STEREO_IMAGES:
        return truth, simulate_images(scenario, truth, streams["sensor"])
    if scenario.sensor.kind == "stereo":
        return truth, simulate_stereo(scenario, truth, streams["sensor"])
    return truth, simulate_depth(scenario, truth, streams["sensor"])
