"""Per-step metrics, computed once per step whatever sinks are on, and the metrics table."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from hairexp.memory import release, use_system_arrow_pool
from hairexp.outputs.files import atomic_write_bytes
from hairexp.physics.info import StepInfo
from hairexp.model.scene import Scene
from hairexp.physics.state import State

#: Columns every metrics table has (the run-folder contract, README "Run folder").
CONTRACT_COLUMNS = ("frame", "time", "controller", "iterations", "converged", "residual_max", "residual_rel_max",
                    "stretch_max", "stretch_mean", "variance_ratio_mean", "contacts", "step_seconds")


def stretch(scene: Scene, x: np.ndarray) -> np.ndarray:
    """(E,) signed edge strain l / l0 - 1."""
    e = scene.strands.edges
    return np.linalg.norm(x[e[:, 1]] - x[e[:, 0]], axis=1) / scene.strands.rest_lengths - 1.0


def energies(scene: Scene, state: State, sim) -> tuple[float, float]:
    """Kinetic and potential (elastic + gravity) energy in J."""
    import torch

    kin = 0.5 * float(np.sum(scene.strands.masses[:, None] * state.v ** 2))
    terms = [t for t in sim.terms + sim.external if t.name in ("stretch", "bending", "gravity")]
    pot = 0.0
    kern = getattr(getattr(sim, "objective", None), "kernels", None)
    if kern is not None and any(kern.handles(t) for t in terms):   # compiled (with gravity's numpy: 5.6-8 -> 0.7-0.9 ms on Celia)
        stretch, bending = kern.elastic_energies(state.x)
        pot += (stretch if any(t is kern.stretch for t in terms) else 0.0)
        pot += (bending if any(t is kern.bending for t in terms) else 0.0)
        terms = [t for t in terms if not kern.handles(t)]
    for t in [t for t in terms if hasattr(t, "total_numpy")]:   # gravity
        pot += t.total_numpy(state.x)
        terms.remove(t)
    if terms:
        x = torch.from_numpy(state.x)
        with torch.no_grad():
            pot += sum(float(t.total(x)) for t in terms)
    return kin, pot


def measure(scene: Scene, state: State, info: StepInfo, sim, step: int, frame: int, controller: str,
            extra: dict | None = None) -> dict:
    """The metrics row of one step.  Residual and variance columns are NaN where they do not
    apply (a free run has no tracking constraints and no clusters)."""
    eps = stretch(scene, state.x)
    kin, pot = energies(scene, state, sim)
    sec = info.seconds
    row = {
        "step": step, "frame": frame, "time": state.time, "dt": info.dt, "controller": controller,
        "status": str(info.status), "converged": bool(info.converged), "iterations": info.iterations,
        "iterations_attempted": info.iterations_attempted,
        "backtracks": info.backtracks, "substeps": info.substeps, "recovered": bool(info.recovered),
        "restarts": info.restarts,
        "grad_norm": info.grad_norm, "force_scale": info.force_scale,
        "residual_max": math.nan, "residual_rms": math.nan, "residual_rel_max": math.nan,
        "stretch_max": float(np.abs(eps).max()), "stretch_mean": float(np.abs(eps).mean()),
        "variance_ratio_mean": math.nan, "constraint_force": math.nan, "constraint_force_rel": math.nan,
        "constraint_norm": info.constraint_norm,
        "contacts": info.object_contacts + info.hair_contacts, "object_contacts": info.object_contacts,
        "hair_contacts": info.hair_contacts, "penetration_max": info.penetration_max,
        "contact_planes": info.contact_planes, "resolve_fallbacks": info.resolve_fallbacks,
        "kinetic_energy": kin, "potential_energy": pot,
        "step_seconds": sec.get("total", 0.0),
        "t_derivatives": sec.get("derivatives", 0.0), "t_assembly": sec.get("assembly", 0.0),
        "t_solve": sec.get("solve", 0.0), "t_collision": sec.get("collision", 0.0), "t_other": sec.get("other", 0.0),
    }
    for name, n in info.collider_contacts.items():
        row[f"contacts_{name}"] = n
    if extra:
        row.update(extra)
    return row


#: rows per row group of metrics.parquet (the parts are gathered into groups this large; the writer
#: holds about 3.5 kB per row of a group, so 1,024 rows cost 3 MB more at the peak than 256)
ROW_GROUP_ROWS = 256


class MetricsTable:
    """Collects rows; ``frame()`` gives the pandas table (one row per step).

    With a ``folder`` the table is streamed: ``flush()`` writes the rows since the last flush as
    one parquet part ``part-<k>.parquet`` (atomically) and drops them from memory, so a crash
    keeps every flushed step (``pd.read_parquet(folder)`` reads the parts as one table)."""

    def __init__(self, folder: Path | None = None):
        self.folder = None if folder is None else Path(folder)
        self.rows: list[dict] = []     # the rows not yet in a part
        self.parts: list[Path] = []
        self.steps = 0
        self.written: MetricColumns | None = None   # the parquet file ``write`` wrote last
        self.written_parts = 0
        use_system_arrow_pool()   # freed parquet buffers go back to the system (hairexp/memory.py)
        if self.folder is not None:
            self.folder.mkdir(parents=True, exist_ok=True)

    def on_step(self, row: dict, state: State) -> None:
        self.rows.append(row)
        self.steps += 1

    def flush(self) -> None:
        if self.folder is None or not self.rows:
            return
        import pandas as pd

        path = self.folder / f"part-{len(self.parts):05d}.parquet"
        df = pd.DataFrame(self.rows)
        atomic_write_bytes(path, lambda f: df.to_parquet(f))
        self.parts.append(path)
        self.rows = []

    def write(self, path: Path) -> "MetricColumns":
        """Write the whole table to the parquet file ``path`` (atomically), one part at a time
        (memory: one part, whatever the run's length), and return its lazy ``MetricColumns``.

        The parts' column types are unified as one table of all rows would have them: a
        column missing from a part is null there, integers meeting floats become floats, and
        columns whose types cannot be unified are written as text."""
        try:
            self.flush()
        except OSError:
            if not self.rows:
                raise
            # the stream's folder cannot take the rows since the last part (made read-only or
            # immutable mid-run), the run folder may: the whole table from the parts and these
            # rows (a failed ending lost every row; independent probe of issue 12, round 26)
            rows = self.frame()
            atomic_write_bytes(Path(path), lambda f: rows.to_parquet(f))
            self.written, self.written_parts = MetricColumns(Path(path)), -1
            return self.written
        if self.written is not None and self.written.path == Path(path) and self.written_parts == len(self.parts) \
                and not self.rows:
            return self.written    # already written, nothing new since
        self.written, self.written_parts = self._write(Path(path)), len(self.parts)
        return self.written

    def _write(self, path: Path) -> "MetricColumns":
        import pyarrow as pa
        import pyarrow.parquet as pq

        if self.folder is None or not self.parts:   # an in-memory table, or nothing flushed: one frame
            atomic_write_bytes(path, lambda f: self.frame().to_parquet(f))
            return MetricColumns(path)
        schemas = []   # the distinct ones: one schema kept per part grew the end's memory with the run's length
        for p in self.parts:
            sch = pq.read_schema(p).remove_metadata()
            if not any(sch.equals(t) for t in schemas):
                schemas.append(sch)
        try:
            schema = pa.unify_schemas(schemas, promote_options="permissive")
        except (pa.ArrowInvalid, pa.ArrowTypeError):
            schema = _text_unified(schemas)

        # dictionary encoding only for the text columns: for a float column of distinct values the
        # writer's dictionary grows with the rows (up to 1 MB a column) and buys nothing
        text = [fld.name for fld in schema if pa.types.is_string(fld.type) or pa.types.is_large_string(fld.type)]

        def write(f):
            with pq.ParquetWriter(f, schema, use_dictionary=text) as w:
                group, rows = [], 0
                for k, p in enumerate(self.parts):
                    # ParquetFile.read, not read_table: the dataset reader behind read_table keeps
                    # about 0.5 MB of resident memory per file read (measured, pyarrow 26)
                    t = pq.ParquetFile(p, pre_buffer=False).read(use_threads=False).replace_schema_metadata(None)
                    cols = [t.column(n).cast(fld.type) if n in t.column_names else pa.nulls(len(t), fld.type)
                            for n, fld in zip(schema.names, schema)]
                    group.append(pa.Table.from_arrays(cols, schema=schema))
                    rows += len(t)
                    if rows >= ROW_GROUP_ROWS or k == len(self.parts) - 1:   # few, large row groups
                        w.write_table(pa.concat_tables(group).combine_chunks())
                        group, rows = [], 0
                        release()   # the parts read for this group: their freed blocks back to the system

        atomic_write_bytes(path, write)
        return MetricColumns(path)

    def frame(self):
        """The whole table: the parts and the rows not yet flushed, with the columns and dtypes
        of one ``DataFrame`` of all rows."""
        import pandas as pd

        if not self.parts:
            return pd.DataFrame(self.rows)
        dfs = [pd.read_parquet(p) for p in self.parts] + ([pd.DataFrame(self.rows)] if self.rows else [])
        df = pd.concat(dfs, ignore_index=True)
        if len({tuple(d.dtypes.items()) for d in dfs}) > 1:   # parts inferred differently: infer over all rows
            df = pd.DataFrame(df.to_dict("records"))
        return df


def read_parts(folder: Path):
    """The rows a streamed table (``MetricsTable(folder)``) flushed before its process ended, as one
    pandas table (the parts in order), or None when there are none or they cannot be read."""
    import pandas as pd

    parts = sorted(Path(folder).glob("part-*.parquet"))
    if not parts:
        return None
    try:
        return pd.concat([pd.read_parquet(p) for p in parts], ignore_index=True)
    except Exception:  # noqa: BLE001  (a part cut short by the kill: nothing to add to the summary)
        return None


def _text_unified(schemas):
    """The union of ``schemas``' fields; a field whose types differ (beyond null) becomes text."""
    import pyarrow as pa

    types: dict[str, set] = {}
    for sch in schemas:
        for fld in sch:
            types.setdefault(fld.name, set()).add(fld.type)
    fields = []
    for name, ts in types.items():
        ts = {t for t in ts if t != pa.null()} or {pa.null()}
        if len(ts) == 1:
            fields.append(pa.field(name, ts.pop()))
        elif all(pa.types.is_integer(t) or pa.types.is_floating(t) for t in ts):
            fields.append(pa.field(name, pa.float64()))
        else:
            fields.append(pa.field(name, pa.string()))
    return pa.schema(fields)


class MetricColumns:
    """A metrics parquet file read column by column (``table["converged"]`` is a pandas
    Series), so the end of a run summarises and measures a long run without loading the
    whole table: ``len``, ``in``, ``[name]``, ``columns``, ``numeric(name)``.

    Reads are single-threaded, a row group at a time: pyarrow's threaded column read left
    about 2 MB more resident after reading the 36 columns of a 3,000-row table than of a
    200-row one (per-thread heaps and read buffers that ``release()`` does not return), against
    0.6 MB this way (2026-12-03, issue 12; the data itself is 0.9 MB)."""

    def __init__(self, path: Path):
        import pyarrow.parquet as pq

        self.path = Path(path)
        meta = pq.read_metadata(self.path)
        self.schema = pq.read_schema(self.path)
        self.columns = list(self.schema.names)
        self._len = meta.num_rows

    def __len__(self) -> int:
        return self._len

    def __contains__(self, name) -> bool:
        return name in self.columns

    def _chunks(self, name: str):
        import pyarrow.parquet as pq

        if name not in self.columns:
            raise KeyError(name)
        f = pq.ParquetFile(self.path, pre_buffer=False)
        for i in range(f.metadata.num_row_groups):
            yield f.read_row_group(i, columns=[name], use_threads=False).column(0)

    def __getitem__(self, name: str):
        import pandas as pd
        import pyarrow as pa

        chunks = list(self._chunks(name))
        col = pa.chunked_array(chunks, type=self.schema.field(name).type) if chunks else \
            pa.chunked_array([], type=self.schema.field(name).type)
        return pd.Series(col.to_pandas(), name=name)

    def numeric(self, name: str):
        """Column ``name`` as float64 (booleans 0/1, nulls NaN), or None when it is not numeric
        or boolean; filled a row group at a time (no table of the whole column)."""
        import pyarrow as pa
        import pyarrow.compute as pc

        t = self.schema.field(name).type
        if not (pa.types.is_integer(t) or pa.types.is_floating(t) or pa.types.is_boolean(t) or pa.types.is_null(t)):
            return None
        out = np.full(self._len, np.nan)
        a = 0
        for c in self._chunks(name):
            n = len(c)
            if not pa.types.is_null(t):
                out[a:a + n] = pc.cast(c, pa.float64()).to_numpy(zero_copy_only=False)
            a += n
        return out

    def frame(self):
        """The whole table (pandas DataFrame)."""
        import pandas as pd

        return pd.read_parquet(self.path)
