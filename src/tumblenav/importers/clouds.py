"""Depth point clouds: an index table (``t_s, file``) naming one PLY or PCD file per epoch.

The readers are small and our own: trimesh (a dependency) reads PLY but processes the geometry
(merging, dropping) and has no PCD reader; open3d reads both but is a 600 MB optional
dependency; pypcd is unmaintained. Here: PLY ascii / binary_little_endian / binary_big_endian
and PCD ascii / binary (not binary_compressed), the ``x y z`` fields of any numeric type, rows
with a NaN coordinate dropped (an organised cloud's "no return"), the rest kept in file order
and at full precision.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from tumblenav.errors import InputError

__all__ = ["read_cloud", "read_pcd", "read_ply", "write_pcd", "write_ply"]

Array = NDArray[np.float64]

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip


def read_cloud(path: Path) -> Array:
    """(m, 3) points of a PLY or PCD file (by suffix); InputError naming the file."""
    path = Path(path)
    if path.is_dir():
        raise InputError("a folder, not a point cloud file", str(path))
    if not path.is_file():
        raise InputError("point cloud file not found", str(path))
    suffix = path.suffix.lower()
    if suffix not in (".ply", ".pcd"):
        raise InputError("not a .ply or .pcd file", str(path))
    try:
        pts = read_ply(path) if suffix == ".ply" else read_pcd(path)
    except (ValueError, IndexError, TypeError) as exc:  # InputError is handled by the caller
        if isinstance(exc, InputError):
            raise
        raise InputError(f"malformed {suffix[1:].upper()} file ({exc})", str(path)) from None
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    if len(pts) == 0:
        raise InputError(
            "empty point cloud (no finite point); leave the index's file cell empty for an "
            "epoch without returns",
            str(path),
        )
    return pts


def _header(data: bytes, end: bytes, path: Path, limit: int = 65536) -> tuple[list[str], int]:
    """Header lines up to and including the line starting with ``end``; offset of the data."""
    lines, pos = [], 0
    while pos < min(len(data), limit):
        nl = data.find(b"\n", pos)
        if nl < 0:
            break
        line = data[pos:nl].decode("ascii", "replace").strip()
        lines.append(line)
        pos = nl + 1
        if line.startswith(end.decode()):
            return lines, pos
    raise InputError(f"no {end.decode()} line: not a valid header", str(path))


def read_ply(path: Path) -> Array:
    """The vertex ``x, y, z`` of a PLY file (ascii or binary)."""
    path = Path(path)
    data = path.read_bytes()
    if not data.startswith(b"ply"):
        raise InputError("not a PLY file (no 'ply' magic)", str(path))
    lines, offset = _header(data, b"end_header", path)
    fmt = None
    elements: list[tuple[str, int, list[tuple[str, str]]]] = []
    for line in lines[1:]:
        parts = line.split()
        if not parts or parts[0] in ("comment", "obj_info", "end_header"):
            continue
        if parts[0] == "format" and len(parts) >= 2:
            fmt = parts[1]
        elif parts[0] == "element" and len(parts) == 3:
            elements.append((parts[1], int(parts[2]), []))
        elif parts[0] == "property" and elements:
            if parts[1] == "list":
                elements[-1][2].append(("list", parts[-1]))
            elif parts[1] in _PLY_TYPES and len(parts) == 3:
                elements[-1][2].append((_PLY_TYPES[parts[1]], parts[2]))
            else:
                raise InputError(f"unknown property type in {line!r}", str(path))
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise InputError(f"unknown PLY format {fmt!r}", str(path))
    if not elements or elements[0][0] != "vertex":
        raise InputError("the first element must be 'vertex'", str(path))
    _, count, props = elements[0]
    if count < 0:
        raise InputError(f"element vertex {count}: a negative count", str(path))
    names = [p[1] for p in props]
    if not {"x", "y", "z"} <= set(names):
        raise InputError("the vertex element has no x, y, z properties", str(path))
    if any(p[0] == "list" for p in props):
        raise InputError("list properties in the vertex element are not supported", str(path))
    idx = [names.index(c) for c in "xyz"]
    if fmt == "ascii":
        rows = data[offset:].decode("ascii", "replace").splitlines()
        rows = [r for r in rows if r.strip()]
        # fewer lines than vertices, or other lines after them with no other element
        if len(rows) < count or (len(elements) == 1 and len(rows) != count):
            raise InputError(f"{len(rows)} vertex lines, the header says {count}", str(path))
        rows = rows[:count]
        out = np.empty((count, 3))
        for i, r in enumerate(rows):
            parts = r.split()
            if len(parts) != len(names):
                raise InputError(
                    f"vertex {i}: {len(parts)} numbers, expected {len(names)}", str(path)
                )
            try:
                out[i] = [float(parts[j]) for j in idx]
            except (ValueError, IndexError):
                raise InputError(f"vertex {i}: not {len(names)} numbers", str(path)) from None
        return out
    order = "<" if fmt == "binary_little_endian" else ">"
    dtype = np.dtype([(n, order + t) for t, n in props])
    if len(data) - offset < count * dtype.itemsize:
        raise InputError(
            f"truncated: {count} vertices need {count * dtype.itemsize} bytes", str(path)
        )
    rec = np.frombuffer(data, dtype=dtype, count=count, offset=offset)
    return np.stack([rec[c].astype(float) for c in "xyz"], axis=1)


_PCD_TYPES = {("F", 4): "f4", ("F", 8): "f8", ("I", 1): "i1", ("I", 2): "i2", ("I", 4): "i4",
              ("I", 8): "i8", ("U", 1): "u1", ("U", 2): "u2", ("U", 4): "u4", ("U", 8): "u8"}  # fmt: skip


def read_pcd(path: Path) -> Array:
    """The ``x, y, z`` fields of a PCD file (DATA ascii or binary)."""
    path = Path(path)
    data = path.read_bytes()
    lines, offset = _header(data, b"DATA", path)
    head: dict[str, list[str]] = {}
    for line in lines:
        parts = line.split()
        if parts and not parts[0].startswith("#"):
            head[parts[0].upper()] = parts[1:]
    try:
        fields = head["FIELDS"]
        sizes = [int(s) for s in head["SIZE"]]
        types = head["TYPE"]
        counts = [int(c) for c in head.get("COUNT", ["1"] * len(fields))]
        n = (
            int(head["POINTS"][0])
            if "POINTS" in head
            else int(head["WIDTH"][0]) * int(head.get("HEIGHT", ["1"])[0])
        )
        mode = head["DATA"][0].lower()
    except (KeyError, IndexError, ValueError):
        raise InputError(
            "malformed PCD header (FIELDS, SIZE, TYPE, POINTS, DATA)", str(path)
        ) from None
    if n < 0:
        raise InputError(f"POINTS {n}: a negative count", str(path))
    if "POINTS" in head and "WIDTH" in head:
        try:
            wh = int(head["WIDTH"][0]) * int(head.get("HEIGHT", ["1"])[0])
        except (IndexError, ValueError):
            raise InputError("malformed WIDTH or HEIGHT", str(path)) from None
        if wh != n:
            raise InputError(f"WIDTH x HEIGHT = {wh} but POINTS = {n}", str(path))
    if not (len(fields) == len(sizes) == len(types) == len(counts)):
        raise InputError("FIELDS, SIZE, TYPE and COUNT have different lengths", str(path))
    if not {"x", "y", "z"} <= set(fields):
        raise InputError("no x, y, z fields", str(path))
    vp = head.get("VIEWPOINT")
    try:
        vp_values = [float(v) for v in vp] if vp is not None else None
    except ValueError:
        raise InputError(f"VIEWPOINT {' '.join(vp or [])!r}: not numbers", str(path)) from None
    if vp_values is not None and vp_values != [0, 0, 0, 1, 0, 0, 0]:
        raise InputError(
            "VIEWPOINT is not 0 0 0 1 0 0 0: give the points in the sensor frame", str(path)
        )
    if mode == "ascii":
        width = sum(counts)
        rows = [r for r in data[offset:].decode("ascii", "replace").splitlines() if r.strip()]
        if len(rows) != n:
            raise InputError(f"{len(rows)} point lines, POINTS says {n}", str(path))
        col, cols = 0, {}
        for f, c in zip(fields, counts, strict=True):
            cols[f] = col
            col += c
        out = np.empty((n, 3))
        for i, r in enumerate(rows[:n]):
            parts = r.split()
            if len(parts) != width:
                raise InputError(f"point {i}: {len(parts)} values, expected {width}", str(path))
            try:
                out[i] = [float(parts[cols[c]]) for c in "xyz"]  # 'nan' parses to NaN
            except ValueError:
                raise InputError(f"point {i}: not numbers ({r.strip()!r})", str(path)) from None
        return out
    if mode != "binary":
        raise InputError(
            f"DATA {mode} is not supported: save the cloud as ascii or binary", str(path)
        )
    try:
        dtype = np.dtype(
            [
                (f, "<" + _PCD_TYPES[(t.upper(), s)], (c,))
                if c > 1
                else (f, "<" + _PCD_TYPES[(t.upper(), s)])
                for f, s, t, c in zip(fields, sizes, types, counts, strict=True)
            ]
        )
    except KeyError:
        raise InputError("unknown field TYPE/SIZE", str(path)) from None
    if len(data) - offset < n * dtype.itemsize:
        raise InputError(f"truncated: {n} points need {n * dtype.itemsize} bytes", str(path))
    rec = np.frombuffer(data, dtype=dtype, count=n, offset=offset)
    return np.stack([rec[c].astype(float) for c in "xyz"], axis=1)


def write_ply(path: Path, points: Array, binary: bool = False) -> Path:
    """Write (m, 3) points as PLY: ascii with ``repr`` floats, or binary little-endian doubles
    (both exact), atomically."""
    from tumblenav.io import atomic_write

    p = np.asarray(points, dtype=float).reshape(-1, 3)
    fmt = "binary_little_endian" if binary else "ascii"
    head = (
        f"ply\nformat {fmt} 1.0\ncomment tumblenav depth cloud, sensor frame\n"
        f"element vertex {len(p)}\nproperty double x\nproperty double y\nproperty double z\n"
        "end_header\n"
    ).encode("ascii")
    return atomic_write(Path(path), lambda tmp: tmp.write_bytes(head + _xyz_body(p, binary)))


def _xyz_body(p: Array, binary: bool) -> bytes:
    """The points of a PLY or PCD body: little-endian doubles, or ``repr`` floats a line each
    (exact round trip)."""
    if binary:
        return p.astype("<f8").tobytes()
    return "".join(f"{x!r} {y!r} {z!r}\n" for x, y, z in p.tolist()).encode("ascii")


def write_pcd(path: Path, points: Array, binary: bool = False) -> Path:
    """Write (m, 3) points as PCD v0.7 (ascii ``repr`` floats or binary doubles), atomically."""
    from tumblenav.io import atomic_write

    p = np.asarray(points, dtype=float).reshape(-1, 3)
    head = (
        "# .PCD v0.7 - tumblenav depth cloud, sensor frame\nVERSION 0.7\nFIELDS x y z\n"
        f"SIZE 8 8 8\nTYPE F F F\nCOUNT 1 1 1\nWIDTH {len(p)}\nHEIGHT 1\n"
        f"VIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(p)}\nDATA {'binary' if binary else 'ascii'}\n"
    ).encode("ascii")
    return atomic_write(Path(path), lambda tmp: tmp.write_bytes(head + _xyz_body(p, binary)))


def read_index(path: Path, columns: tuple[str, ...]) -> tuple[Array, dict[str, NDArray]]:
    """An index table (``t_s`` plus file columns): times strictly increasing (InputError
    naming the row of an unsorted or duplicate timestamp)."""
    from tumblenav.importers.tables import missing_columns, read_table, row_name

    cols = read_table(path, text=columns, numeric=("t_s",))
    missing_columns(cols, ("t_s", *columns), path)
    t = cols["t_s"]
    if len(t) < 2:
        raise InputError(f"{len(t)} row(s): needs at least two epochs", str(path))
    bad = ~np.isfinite(t)
    if bad.any():
        raise InputError(
            f"{row_name(path, int(np.flatnonzero(bad)[0]))}: t_s is not a number", str(path)
        )
    d = np.diff(t)
    for i in np.flatnonzero(d <= 0)[:1]:
        what = "duplicate timestamp" if d[i] == 0 else "unsorted: earlier than the row before"
        raise InputError(
            f"{row_name(path, int(i) + 1)}: t_s {float(t[i + 1])!r}: {what}", str(path)
        )
    return t, cols


def depth_measurements(path: Path, cfg: dict, cal_path: Path):
    """DepthMeasurements of an index (``t_s, file``; an empty file cell = no returns at that
    epoch) and the context mapping: ``camera_axes`` (opencv: x right, y down, z boresight;
    tumblenav: x right, y boresight, z = x cross y), ``fov_deg``, ``range_noise_m`` and the
    ``chaser`` block. Returns the measurements, the context, the time offset and the
    scenario's sensor keys."""
    from tumblenav import rotations as rot
    from tumblenav.importers.calibration import R_TN_CV, _choice, _number, load_context
    from tumblenav.importers.tables import row_name
    from tumblenav.measurements import DepthMeasurements

    where = str(cal_path)
    path = Path(path)
    t_file, cols = read_index(path, ("file",))
    axes = _choice(cfg, "camera_axes", ("opencv", "tumblenav"), where, "opencv")
    fov_deg = _number(cfg, "fov_deg", where)
    noise = _number(cfg, "range_noise_m", where)
    if not 0 < fov_deg < 180 or noise < 0:
        raise InputError("fov_deg must be in (0, 180) and range_noise_m >= 0", where)
    clouds = []
    for i, name in enumerate(cols["file"]):
        if name == "":
            clouds.append(np.empty((0, 3)))
            continue
        try:
            pts = read_cloud(path.parent / name)
        except InputError as exc:
            raise InputError(
                f"{exc.what} ({row_name(path, i)} of {path.name})", exc.where
            ) from None
        if axes == "opencv":
            pts = np.stack([pts[:, 0], pts[:, 2], -pts[:, 1]], axis=1)  # R_TN_CV, exact
        clouds.append(pts)
    width = max(1, max(len(c) for c in clouds))
    P = np.full((len(clouds), width, 3), np.nan)
    M = np.zeros((len(clouds), width), dtype=bool)
    for k, c in enumerate(clouds):
        P[k, : len(c)] = c
        M[k, : len(c)] = True
    t_offset = float(t_file[0])
    t = t_file - t_offset if t_offset != 0 else t_file
    ctx = load_context(cfg, where, path.parent, t, "tumblenav", t_offset)
    q_SL = (
        ctx.q_C0L
        if axes == "tumblenav"
        else rot.quat_multiply(rot.matrix_to_quat(R_TN_CV), ctx.q_C0L)
    )
    meas = DepthMeasurements(
        t=t,
        points=P,
        observed=M,
        q_CL=q_SL,
        q_LI=ctx.q_LI,
        fov_rad=float(np.radians(fov_deg)),
        range_noise_m=noise,
    )
    sensor = {"kind": "depth", "fov_deg": fov_deg, "points": width, "range_noise_m": noise}
    return meas, ctx, t_offset, sensor
