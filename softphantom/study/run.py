"""Run a study on Dask: every variant evaluated once, cached under its key, written as Parquet.

``OUT/variants/<key>.json`` holds each finished variant's row (written as it arrives, so an
interrupted sweep resumes where it stopped: a variant whose file exists is not run again);
``OUT/results.parquet`` the table (one row per variant, in variant order; the sweep file is in
the schema metadata under ``softphantom``). A variant that the design rejects or the solver
cannot handle is a row with ``status`` ``invalid``/``failed`` and its ``error``; a task that
crashed (a lost worker) is a ``failed`` row that is not cached, so the next run retries it.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from softphantom.errors import UserError
from softphantom.parallel import TaskResult, map_tasks
from softphantom.study.config import Variant
from softphantom.study.variant import evaluate_variant

RESULTS = "results.parquet"
CACHE_DIR = "variants"


@dataclass(frozen=True)
class SweepRun:
    """What a run did: ``rows`` (one dict per variant, variant order), how many came from the
    cache, how many were computed, and the Parquet path."""

    rows: list[dict]
    cached: int
    computed: int
    path: Path | None


def _json_safe(row: dict) -> dict:
    return {k: (v.item() if hasattr(v, "item") else v) for k, v in row.items()}


def _cache_path(out: Path, key: str) -> Path:
    return out / CACHE_DIR / f"{key}.json"


def read_cached(out: Path, variant: Variant) -> dict | None:
    """The cached row of ``variant`` (None if absent or unreadable: it is then recomputed)."""
    p = _cache_path(out, variant.key)
    try:
        row = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    row["variant"] = variant.index  # the same design may sit at another index in another study
    return row


def write_cached(out: Path, row: dict) -> None:
    d = out / CACHE_DIR
    d.mkdir(parents=True, exist_ok=True)
    tmp = d / f".{row['key']}.{os.getpid()}.tmp"
    tmp.write_text(json.dumps(_json_safe(row), sort_keys=True), encoding="utf-8")
    tmp.replace(_cache_path(out, row["key"]))  # atomic: a killed run leaves no half file


def evaluate_variants(client: Any, variants: Sequence[Variant], out: Path,
                      label: str = "variants", on_row: Callable[[dict], None] | None = None) -> SweepRun:
    """Rows for ``variants``: from the cache where present, else computed on ``client`` (their
    progress reported as task ``label``, :func:`softphantom.parallel.map_tasks`)."""
    out.mkdir(parents=True, exist_ok=True)
    rows: dict[int, dict] = {}
    todo: list[Variant] = []
    for v in variants:
        row = read_cached(out, v)
        if row is None:
            todo.append(v)
        else:
            rows[v.index] = row
    cached = len(rows)

    def got(res: TaskResult) -> None:
        v = todo[res.index]
        if res.ok:
            row = dict(res.value, variant=v.index)
            write_cached(out, row)
        else:  # the task itself crashed: record it, do not cache (retried on the next run)
            row = {"variant": v.index, "key": v.key, "status": "failed", "error": res.error,
                   **{f"p.{k}": x for k, x in v.params.items()}}
        rows[v.index] = row
        if on_row is not None:
            on_row(row)

    if todo:
        map_tasks(client, evaluate_variant, [(v,) for v in todo], label=label, on_result=got)
    ordered = [rows[v.index] for v in variants]
    return SweepRun(ordered, cached, len(todo), None)


def _columns(rows: Sequence[dict]) -> list[str]:
    cols: dict[str, None] = {}
    for r in rows:
        for k in r:
            cols.setdefault(k, None)
    return list(cols)


def require_pyarrow() -> None:
    """Refuse before any work (one line) when the ``study`` extra is missing."""
    try:
        import pyarrow.parquet  # noqa: F401
    except ImportError:  # pragma: no cover - installed with the test extra
        raise UserError("results.parquet needs pyarrow: pip install 'softphantom[study]'") from None


def write_parquet(rows: Sequence[dict], path: Path, metadata: dict | None = None) -> Path:
    """One row per variant; columns are the union over rows (missing values null)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    cols = _columns(rows)
    data = {}
    for c in cols:
        vals = [r.get(c) for r in rows]
        if all(v is None or (isinstance(v, (int, float)) and not isinstance(v, bool)) for v in vals):
            vals = [None if v is None else float(v) for v in vals] if any(isinstance(v, float) for v in vals) else vals
        data[c] = vals
    table = pa.table(data)
    if metadata is not None:
        table = table.replace_schema_metadata({"softphantom": json.dumps(metadata, sort_keys=True)})
    tmp = path.with_suffix(".parquet.tmp")
    pq.write_table(table, tmp)
    tmp.replace(path)
    return path


def read_parquet(path: Path) -> list[dict]:
    """The rows of a results file (for the report and for tests)."""
    import pyarrow.parquet as pq

    try:
        return pq.read_table(path).to_pylist()
    except (OSError, ValueError) as exc:
        raise UserError(f"{path}: not a readable Parquet file ({exc})") from None


def rows_equal(a: Sequence[dict], b: Sequence[dict], ignore: Sequence[str], rtol: float = 0.0) -> list[str]:
    """Differences between two row lists (empty when equal), timing columns ignored."""
    diffs = []
    if len(a) != len(b):
        return [f"{len(a)} rows vs {len(b)}"]
    for ra, rb in zip(a, b):
        for k in sorted(set(ra) | set(rb)):
            if k in ignore:
                continue
            x, y = ra.get(k), rb.get(k)
            if isinstance(x, float) and isinstance(y, float):
                if math.isnan(x) and math.isnan(y):
                    continue
                if abs(x - y) <= rtol * max(abs(x), abs(y)):
                    continue
            elif x == y:
                continue
            diffs.append(f"variant {ra.get('variant')}: {k} {x!r} != {y!r}")
    return diffs
