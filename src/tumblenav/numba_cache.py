"""Whether numba's on-disk cache already holds the compiled kernels (``cache=True``).

The first run after an installation compiles them (about 30 s); commands say so instead of
staying silent. numba writes an index file ``<module>.<function>-<line>.py<ver>.nbi`` beside
each cached module, in its ``__pycache__`` (or under ``NUMBA_CACHE_DIR`` when set).
"""

from __future__ import annotations

import os
from pathlib import Path

import tumblenav

# the modules whose kernels numba caches; rotations_compiled and dynamics/compiled are inlined
# into these (inline="always": no cache files of their own, so they must not be listed).
# frontends/stereo_images/ecc_kernel.py is cached too but not listed: only image runs compile it
# (about 3 s), so listing it kept the message on for every points-only run (the check of
# tests/test_cli_contract.py::test_the_compile_message_is_not_shown_once_the_kernels_are_cached)
KERNEL_MODULES = ("estimators/hu2024/kernels.py", "frontends/_points_kernel.py")


def kernels_compiled() -> bool:
    """True if every kernel module has cache entries (so no long compilation is ahead)."""
    root = Path(tumblenav.__file__).parent
    custom = os.environ.get("NUMBA_CACHE_DIR")
    for rel in KERNEL_MODULES:
        mod = root / rel
        places = [mod.parent / "__pycache__"]
        if custom:
            places.append(Path(custom))
        if not any(any(p.rglob(f"{mod.stem}.*.nbi")) for p in places if p.is_dir()):
            return False
    return True
