"""Reading an .rrd back with rerun's own reader (`rerun.chunk.RrdReader`), for the tests.

`read_rrd` flattens a recording into rows per entity: each row holds its timeline values
(integers: sequence numbers, or nanoseconds for durations and timestamps) and its components as
Python lists, so a test can ask "what did /world/truth hold at scan 4?".
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import pyarrow as pa


@dataclass
class Row:
    """One logged row of an entity."""

    times: dict[str, int]
    components: dict[str, object] = field(default_factory=dict)


@dataclass
class Recording:
    """The rows of every entity of one recording, and how many blueprints the file carried."""

    entities: dict[str, list[Row]]
    blueprints: int
    timelines: set[str]

    def rows(self, entity: str, component: str | None = None) -> list[Row]:
        """Rows of `entity` (those carrying `component`, if given), in file order."""
        rows = self.entities.get(entity, [])
        if component is not None:
            rows = [r for r in rows if r.components.get(component) is not None]
        return rows

    def at(self, entity: str, timeline: str, value: int, component: str) -> list[object]:
        """`component`'s values at `timeline` == `value` (one per row logged there)."""
        return [r.components[component] for r in self.rows(entity, component)
                if r.times.get(timeline) == value]

    def per_step(self, entity: str, timeline: str, component: str) -> dict[int, int]:
        """How many rows carrying `component` each value of `timeline` has."""
        out: dict[int, int] = defaultdict(int)
        for r in self.rows(entity, component):
            if timeline in r.times:
                out[r.times[timeline]] += 1
        return dict(out)


def read_rrd(path: str | Path) -> Recording:
    """Every chunk of the first recording in `path`, as rows (static rows have no times)."""
    from rerun.chunk import RrdReader

    reader = RrdReader(path)
    entities: dict[str, list[Row]] = defaultdict(list)
    timelines: set[str] = set()
    for chunk in reader.stream():
        batch = chunk.to_record_batch()
        names = chunk.timeline_names
        timelines.update(names)
        cols = {}
        for name in batch.schema.names:
            if name == "rerun.controls.RowId":
                continue
            col = batch.column(name)
            if name in names:
                # Durations and timestamps as integer nanoseconds (pyarrow would make datetimes).
                col = col.cast(pa.int64())
            cols[name] = col.to_pylist()
        for i in range(batch.num_rows):
            times = {t: cols[t][i] for t in names if cols[t][i] is not None}
            comps = {k: v[i] for k, v in cols.items() if k not in names}
            entities[chunk.entity_path].append(Row(times, comps))
    return Recording(dict(entities), len(reader.blueprints()), timelines)
