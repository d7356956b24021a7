"""Resumable on-disk store of a Monte Carlo campaign: one file per finished run.

Layout of a campaign folder::

    campaign.json          what was asked (scenario, estimator, runs, base seed) and the code
                           that computed it (``code_fingerprint``); checked on resume
    runs/run_000042.npz    one finished run (errors, NEES, NIS), written atomically
    runs/run_000042.failed.json   a run that raised: its seed and the error
    summary.json           written at the end

A run is identified by its index k; its random streams come from
``SeedSequence(base_seed, spawn_key=(k,))`` (the same as ``SeedSequence(base_seed).spawn(N)[k]``
for any N > k), so a resumed or enlarged campaign reproduces the same runs.
"""

from __future__ import annotations

import contextlib
import hashlib
import zipfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

import tumblenav
from tumblenav import io
from tumblenav.errors import InputError
from tumblenav.evaluation.metrics import RunErrors


def run_seed(base_seed: int, k: int) -> np.random.SeedSequence:
    return np.random.SeedSequence(base_seed, spawn_key=(k,))


_FINGERPRINT: list[str] = []


def code_fingerprint() -> str:
    """The package version and a hash of its Python sources: runs stored by other code are
    not mixed into a resumed campaign (they may differ from what this code computes)."""
    if not _FINGERPRINT:
        root = Path(tumblenav.__file__).parent
        h = hashlib.sha256()
        for f in sorted(root.rglob("*.py")):
            h.update(f.relative_to(root).as_posix().encode())
            h.update(f.read_bytes())
        _FINGERPRINT.append(f"{tumblenav.__version__}+{h.hexdigest()[:12]}")
    return _FINGERPRINT[0]


@dataclass(frozen=True)
class CampaignStore:
    root: Path

    @property
    def runs_dir(self) -> Path:
        return self.root / "runs"

    def run_path(self, k: int) -> Path:
        return self.runs_dir / f"run_{k:06d}.npz"

    def failed_path(self, k: int) -> Path:
        return self.runs_dir / f"run_{k:06d}.failed.json"

    @contextlib.contextmanager
    def exclusive(self) -> Iterator[None]:
        """Hold ``root/.lock`` exclusively while a campaign writes here: a second command on
        the same folder at the same time is refused (InputError) instead of mixing its runs,
        its campaign.json and its summary with the first's (an advisory lock, released when
        this process ends, however it ends)."""
        import fcntl

        self.root.mkdir(parents=True, exist_ok=True)
        with open(self.root / ".lock", "a+b") as fh:
            try:
                fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                raise InputError(
                    "another tumblenav command is writing this campaign now: wait for it to "
                    "finish (then run this one again to resume or extend it), or choose "
                    "another folder",
                    str(self.root),
                ) from None
            try:
                yield
            finally:
                fcntl.flock(fh.fileno(), fcntl.LOCK_UN)

    def open(self, spec: dict[str, Any]) -> list[str]:
        """Create the folder, or check that an existing one holds the same campaign, computed
        by the same code (``code_fingerprint``, added to ``spec``) if it holds runs. Returns
        the stored runs that could not be read, set aside to be computed again
        (:meth:`set_aside_damaged`)."""
        spec = {**spec, "code_fingerprint": code_fingerprint()}
        self.runs_dir.mkdir(parents=True, exist_ok=True)
        spec_path = self.root / "campaign.json"
        if spec_path.exists():
            old = io.read_json(spec_path)
            keys = ("scenario", "estimator", "base_seed", "scenario_hash")
            diff = [k for k in keys if old.get(k) != spec.get(k)]
            if diff:
                raise InputError(
                    f"holds a different campaign ({', '.join(diff)} differ); "
                    "use another output folder",
                    str(self.root),
                )
            stored = len(self.done()) + len(list(self.runs_dir.glob("run_*.failed.json")))
            if stored and old.get("code_fingerprint") != spec["code_fingerprint"]:
                raise InputError(
                    f"holds {stored} runs computed by other tumblenav code "
                    f"({old.get('code_fingerprint', 'unrecorded')}, now "
                    f"{spec['code_fingerprint']}); resuming would mix their results with this "
                    "code's: use another output folder (or delete its runs/ to recompute)",
                    str(self.root),
                )
        self.remove_partial()
        damaged = self.set_aside_damaged()
        io.write_json(spec, spec_path)
        return damaged

    def set_aside_damaged(self) -> list[str]:
        """Rename every stored run that cannot be read whole (a disk fault, a file edited or
        truncated by hand: writes themselves are atomic) to ``run_NNNNNN.npz.damaged`` so that
        it is computed again; returns their names. Call only while no worker writes here."""
        damaged = []
        for path in sorted(self.runs_dir.glob("run_*.npz")):
            try:
                with np.load(path) as z:
                    for key in z.files:
                        z[key]  # reads and checks every member (zip CRC)
            except Exception:  # noqa: BLE001 - any unreadable file is set aside, named
                path.replace(path.with_name(path.name + ".damaged"))
                damaged.append(path.name)
        return damaged

    def remove_partial(self) -> None:
        """Delete temporary files of writes that a killed worker never finished (every write
        goes to a hidden ``.NAME.*.tmp`` first and is renamed when whole: see
        :func:`tumblenav.io.atomic_write`). Call only while no worker writes here."""
        if self.runs_dir.is_dir():
            for tmp in self.runs_dir.glob(".run_*.tmp"):
                tmp.unlink(missing_ok=True)

    def done(self) -> set[int]:
        if not self.runs_dir.exists():
            return set()
        return {int(p.stem.split("_")[1]) for p in self.runs_dir.glob("run_*.npz")}

    def save_run(self, k: int, seed_entropy: Any, r: RunErrors, extra: dict[str, Any]) -> Path:
        arrays = {f"err_{key}": v for key, v in r.errors.items()}
        arrays.update(
            t=r.t,
            nees=r.nees,
            nees_dof=np.array(r.nees_dof),
            nis=r.nis,
            nis_dof=r.nis_dof,
            k=np.array(k),
        )
        for key, v in extra.items():
            arrays[f"extra_{key}"] = np.asarray(v)
        if r.components:  # per-axis errors at about 1 Hz, for figures of their spread over runs
            every = max(1, int(round(1.0 / float(np.median(np.diff(r.t)))))) if len(r.t) > 1 else 1
            arrays["cmp_t"] = r.t[::every]
            for key, c in r.components.items():
                arrays[f"cmp_{key}"] = np.asarray(c[::every], dtype=np.float32)
        path = self.run_path(k)

        def _write(tmp: Path) -> None:
            # an .npz as np.savez_compressed writes it, but at zlib level 1: 2.6 instead of
            # 4.1 ms per hu2024 run, and as small (91 kB: noisy floats barely compress)
            with zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED, compresslevel=1) as zf:
                for name, value in arrays.items():
                    with zf.open(f"{name}.npy", "w", force_zip64=True) as fh:
                        np.lib.format.write_array(fh, np.asanyarray(value), allow_pickle=False)

        out = io.atomic_write(path, _write)
        self.failed_path(k).unlink(missing_ok=True)
        return out

    def save_failure(self, k: int, base_seed: int, error: str) -> None:
        io.write_json(
            {"run": k, "base_seed": base_seed, "spawn_key": [k], "error": error},
            self.failed_path(k),
        )

    def failures(self) -> list[dict[str, Any]]:
        return [io.read_json(p) for p in sorted(self.runs_dir.glob("run_*.failed.json"))]

    def load_components(self, k: int) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """Run k's per-axis errors at about 1 Hz: times (m,) and ``{quantity: (m, 3)}``
        (empty for a run stored without them)."""
        with np.load(self.run_path(k)) as z:
            if "cmp_t" not in z.files:
                return np.zeros(0), {}
            comps = {key[4:]: z[key].astype(float) for key in z.files if key.startswith("cmp_")}
            return comps.pop("t"), comps

    def load_run(self, k: int) -> RunErrors:
        return self.load(k)[0]

    def load(self, k: int) -> tuple[RunErrors, dict[str, Any]]:
        """Run k's errors and its extras (``skipped_*`` counts, ...), as :meth:`save_run`
        wrote them."""
        with np.load(self.run_path(k)) as z:
            errors = {key[4:]: z[key] for key in z.files if key.startswith("err_")}
            # scalars as Python numbers, lists (the estimator's warnings) as lists
            extra = {
                key[6:]: z[key].item() if z[key].ndim == 0 else z[key].tolist()
                for key in z.files
                if key.startswith("extra_")
            }
            r = RunErrors(
                t=z["t"],
                errors=errors,
                nees=z["nees"],
                nees_dof=int(z["nees_dof"]),
                nis=z["nis"],
                nis_dof=z["nis_dof"],
            )
        return r, extra
