"""Tables of a user's files: CSV (Python's csv module and ``float``: correctly rounded, so a
``repr`` written float comes back bit for bit; '#' lines are comments) or Parquet (float64 columns as stored; needs pyarrow, the ``parquet`` extra)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from tumblenav.errors import InputError

__all__ = ["read_table", "row_name", "write_table"]


def read_table(
    path: Path, text: tuple[str, ...] = (), numeric: tuple[str, ...] | None = None
) -> dict[str, NDArray]:
    """Columns of a CSV or Parquet file by name: float arrays (empty cells NaN), the columns
    named in ``text`` as strings (empty cells ''). With ``numeric``, only those columns are
    read as numbers and any other column a CSV has is kept as strings (a column the caller
    does not use is no error). InputError naming the file and the row."""
    path = Path(path)
    if path.is_dir():
        raise InputError("a folder, not a file", str(path))
    if not path.is_file():
        raise InputError("file not found", str(path))
    if path.suffix.lower() in (".parquet", ".pq"):
        return _read_parquet(path, text)
    import csv

    try:
        with path.open(newline="", encoding="utf-8-sig") as fh:  # a BOM is no header
            lines = [ln for ln in fh if ln.strip() and not ln.lstrip().startswith("#")]
        rows = list(csv.reader(lines, skipinitialspace=True))
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise InputError(f"not a readable CSV file ({exc})", str(path)) from None
    if not rows:
        raise InputError("empty CSV file (no header row)", str(path))
    header = [h.strip() for h in rows[0]]
    body = rows[1:]
    for i, r in enumerate(body):
        if len(r) != len(header):
            raise InputError(
                f"row {i + 2}: {len(r)} cells, the header has {len(header)}", str(path)
            )
    out: dict[str, NDArray] = {}
    for c, key in enumerate(header):
        cells = np.array([r[c].strip() for r in body], dtype=object)
        as_text = key in text or (numeric is not None and key not in numeric)
        out[key] = cells if as_text else _floats(cells, key, path, lambda i: i + 2)
    return out


def missing_columns(cols: dict, need: tuple[str, ...], path: Path) -> None:
    """InputError naming the columns of ``need`` that ``cols`` lacks, and the ones it has."""
    missing = [c for c in need if c not in cols]
    if missing:
        raise InputError(
            f"missing column(s) {', '.join(missing)} (need {', '.join(need)}; the header has "
            f"{', '.join(cols) or 'nothing'})",
            str(path),
        )


def _floats(values: NDArray, name: str, path: Path, row) -> NDArray[np.float64]:
    if values.dtype.kind in "fiu":
        return values.astype(float)
    out = np.empty(len(values))
    for i, v in enumerate(values):
        s = str(v).strip()
        if s == "" or s.lower() in ("nan", "na"):
            out[i] = np.nan
            continue
        try:
            out[i] = float(s)
        except ValueError:
            raise InputError(
                f"row {row(i)}, column {name}: not a number ({s!r})", str(path)
            ) from None
    return out


def _read_parquet(path: Path, text: tuple[str, ...]) -> dict[str, NDArray]:
    try:
        import pyarrow.parquet as pq  # type: ignore[import-untyped]
    except ImportError:
        raise InputError(
            "reading Parquet needs pyarrow: pip install 'tumblenav[parquet]' (or give a CSV file)",
            str(path),
        ) from None
    try:
        table = pq.read_table(path)
    except Exception as exc:  # noqa: BLE001 - pyarrow raises many types for a bad file
        raise InputError(
            f"not a readable Parquet file ({exc.__class__.__name__})", str(path)
        ) from None
    out: dict[str, NDArray] = {}
    for name in table.column_names:
        col = table.column(name).to_numpy(zero_copy_only=False)
        if name in text:
            out[name] = np.array(["" if v is None else str(v) for v in col], dtype=object)
        else:
            out[name] = _floats(np.asarray(col), name, path, lambda i: i + 1)
    return out


def row_name(path: Path, i: int) -> str:
    """How a message names data row ``i`` (0-based): the CSV line (header = line 1), or the
    Parquet row counted from 1."""
    if Path(path).suffix.lower() in (".parquet", ".pq"):
        return f"row {i + 1}"
    return f"row {i + 2}"


def write_table(path: Path, columns: dict[str, NDArray]) -> Path:
    """Write columns as CSV (floats as ``repr``: exact; NaN as empty cells) or Parquet (float64)
    atomically."""
    from tumblenav.io import atomic_write

    path = Path(path)
    names = list(columns)
    n = len(next(iter(columns.values()))) if columns else 0
    if path.suffix.lower() in (".parquet", ".pq"):
        import pyarrow as pa
        import pyarrow.parquet as pq

        table = pa.table({k: pa.array(np.asarray(v)) for k, v in columns.items()})
        return atomic_write(path, lambda tmp: pq.write_table(table, tmp))

    def cell(v) -> str:
        if isinstance(v, (float, np.floating)):
            return "" if not np.isfinite(v) else repr(float(v))
        if isinstance(v, (int, np.integer)):
            return str(int(v))
        return str(v)

    lines = [",".join(names)]
    cols = [np.asarray(columns[k]) for k in names]
    for i in range(n):
        lines.append(",".join(cell(c[i]) for c in cols))
    text = "\n".join(lines) + "\n"
    return atomic_write(path, lambda tmp: tmp.write_text(text, encoding="utf-8"))
