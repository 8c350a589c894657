"""Results that last: a Parquet dataset, one file per finished task, written as tasks end.

::

    OUT/study.json                       the study's fingerprint, columns and curve grids
    OUT/results/part-<first>-<last>.parquet   one finished task's samples

Each file is written under a hidden temporary name (``.part-*.tmp``, which Parquet
readers such as ``pyarrow.parquet.read_table(OUT/results)`` skip) and renamed when
complete, so a study killed at any moment leaves only whole files to read; on a restart
the leftover of a write cut short is removed, and the sample ids found in the whole
files are not computed again (``--fresh`` starts over).  A folder that holds another
study's results (another fingerprint) is refused.

Columns: ``sample_id`` (int64), ``status`` ("ok" or why the sample failed), ``worker``
(the Dask worker that ran it), ``started_utc`` / ``finished_utc`` (timestamps, µs),
``compute_s`` (the sample's own time on the worker), one float64 column per parameter
(named as in the study file, the key's unit), one per output (the unit in its name), and
``curve_<i>`` (list of float32) for experiment i's curve.
"""

import json
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from hil.study.keys import StudySpecError
from hil.study.spec import Study

MANIFEST = "study.json"
RESULTS = "results"
BASE_COLUMNS = (("sample_id", pa.int64()), ("status", pa.string()), ("worker", pa.string()),
                ("started_utc", pa.timestamp("us", tz="UTC")),
                ("finished_utc", pa.timestamp("us", tz="UTC")), ("compute_s", pa.float64()))


def schema(study: Study) -> pa.Schema:
    """The results' columns for ``study`` (module docstring)."""
    cols = [pa.field(name, kind) for name, kind in BASE_COLUMNS]
    cols += [pa.field(ref.name, pa.float64()) for ref in study.parameters]
    cols += [pa.field(name, pa.float64()) for name in study.outputs]
    cols += [pa.field(f"curve_{i}", pa.list_(pa.float32()))
             for i, exp in enumerate(study.experiments) if exp.curve is not None]
    return pa.schema(cols)


@dataclass(frozen=True)
class Results:
    """Every stored sample, sorted by id.

    Attributes:
        ids: sample ids, shape (n,).
        status: "ok" or the reason, per sample.
        params: parameter name -> values, shape (n,).
        outputs: output name -> values, shape (n,) (NaN where a sample failed).
        curves: experiment index -> values, shape (n, grid points).
        table: the whole Arrow table (timestamps, workers).
    """
    ids: np.ndarray
    status: list
    params: dict
    outputs: dict
    curves: dict
    table: pa.Table

    @property
    def ok(self) -> np.ndarray:
        """True for samples that ran to the end, shape (n,)."""
        return np.array([s == "ok" for s in self.status], dtype=bool)


class ResultStore:
    """The study's output folder (module docstring).

    Args:
        out: the folder.
        study: the study whose results it holds.
        fresh: delete earlier results instead of resuming them.
    """

    def __init__(self, out: Path, study: Study, fresh: bool = False):
        self.out = Path(out)
        self.dir = self.out / RESULTS
        self.schema = schema(study)
        self.param_names = tuple(r.name for r in study.parameters)
        self.output_names = study.outputs
        manifest = self.out / MANIFEST
        if fresh and self.dir.exists():
            shutil.rmtree(self.dir)
        if manifest.exists() and self.dir.exists():
            earlier = json.loads(manifest.read_text())
            if earlier.get("fingerprint") != study.fingerprint:
                raise StudySpecError(
                    f"{self.out}: holds the results of another study ({earlier.get('study')}, "
                    f"fingerprint {earlier.get('fingerprint')}; this one is "
                    f"{study.fingerprint}): use --fresh to replace them, or another --out")
        self.dir.mkdir(parents=True, exist_ok=True)
        for cut_short in self.dir.glob(".part-*.tmp"):  # a write a kill interrupted
            cut_short.unlink()
        curves = {f"curve_{i}": {"experiment": exp.kind, "name": exp.curve.name,
                                 "unit": exp.curve.unit, "grid": exp.curve.grid.tolist(),
                                 "grid_name": exp.curve.grid_name,
                                 "grid_unit": exp.curve.grid_unit,
                                 "log_grid": exp.curve.log_grid}
                  for i, exp in enumerate(study.experiments) if exp.curve is not None}
        manifest.write_text(json.dumps({
            "study": study.path, "name": study.study.name, "fingerprint": study.fingerprint,
            "method": study.study.method, "parameters": [r.name for r in study.parameters],
            "outputs": list(study.outputs), "curves": curves}, indent=1))

    def files(self) -> list[Path]:
        """The finished tasks' files."""
        return sorted(self.dir.glob("part-*.parquet"))

    def done_ids(self) -> set[int]:
        """Sample ids already stored."""
        done: set[int] = set()
        for f in self.files():
            done.update(pq.read_table(f, columns=["sample_id"])["sample_id"].to_pylist())
        return done

    def write(self, table: pa.Table) -> Path:
        """Store one finished task's samples (whole file or nothing)."""
        ids = table["sample_id"].to_pylist()
        path = self.dir / f"part-{min(ids):08d}-{max(ids):08d}.parquet"
        tmp = path.with_name(f".{path.name}.tmp")
        pq.write_table(table.cast(self.schema), tmp)
        os.replace(tmp, path)
        return path

    def read(self) -> Results:
        """Every stored sample, sorted by id."""
        files = self.files()
        table = (pa.concat_tables([pq.read_table(f, schema=self.schema) for f in files])
                 if files else self.schema.empty_table())
        table = table.sort_by("sample_id")
        curves = {int(n.split("_")[1]): _curve_matrix(table[n]) for n in self.schema.names
                  if n.startswith("curve_")}

        def floats(names):
            return {n: table[n].to_numpy(zero_copy_only=False).astype(float) for n in names}

        return Results(table["sample_id"].to_numpy(), table["status"].to_pylist(),
                       floats(self.param_names), floats(self.output_names), curves, table)


def _curve_matrix(column: pa.ChunkedArray) -> np.ndarray:
    rows = column.to_pylist()
    width = max((len(r) for r in rows if r), default=0)
    out = np.full((len(rows), width), np.nan)
    for i, r in enumerate(rows):
        if r:
            out[i] = r
    return out
