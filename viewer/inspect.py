"""Read a .rrd back with Rerun's own chunk API (``rerun.chunk.RrdReader``) and count what is in
it: used by the tests and by ``roadsurf view --save`` to print what was written."""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path


@dataclass
class ComponentCount:
    rows: int = 0  # log calls that set this component (non-null rows)
    instances: int = 0  # total instances over those rows (points, strips, ...)


@dataclass
class RrdSummary:
    """entity path -> component ("Archetype:field") -> counts; plus stores in the file."""

    entities: dict[str, dict[str, ComponentCount]] = field(default_factory=dict)
    n_recordings: int = 0
    n_blueprints: int = 0
    timelines: set[str] = field(default_factory=set)

    def instances(self, entity: str, component: str) -> int:
        return self.entities.get(entity, {}).get(component, ComponentCount()).instances

    def rows(self, entity: str, component: str) -> int:
        return self.entities.get(entity, {}).get(component, ComponentCount()).rows

    def has(self, entity: str) -> bool:
        return entity in self.entities

    def under(self, prefix: str) -> list[str]:
        p = prefix.rstrip("/") + "/"
        return sorted(e for e in self.entities if e.startswith(p))


def summarize_rrd(path: str | Path) -> RrdSummary:
    """Count rows and instances of every component of the first recording in ``path``."""
    import pyarrow as pa
    import pyarrow.compute as pc
    from rerun.chunk import RrdReader

    reader = RrdReader(path)
    out = RrdSummary(n_recordings=len(reader.recordings()), n_blueprints=len(reader.blueprints()))
    ents: dict[str, dict[str, ComponentCount]] = defaultdict(dict)
    for chunk in reader.stream():
        out.timelines.update(chunk.timeline_names)
        rb = chunk.to_record_batch()
        comps = ents[chunk.entity_path]
        for name in rb.schema.names:
            if ":" not in name or name.startswith("rerun."):
                continue
            col = rb.column(name)
            cc = comps.setdefault(name, ComponentCount())
            cc.rows += len(col) - col.null_count
            if pa.types.is_list(col.type) or pa.types.is_large_list(col.type):
                lengths = pc.list_value_length(col)
                cc.instances += int(pc.sum(lengths).as_py() or 0)
            else:
                cc.instances += len(col) - col.null_count
    out.entities = dict(ents)
    return out


def component_values(path: str | Path, entity: str, component: str) -> list[object]:
    """Every non-null value of ``entity``'s ``component`` column, one Python list per row
    (e.g. the positions of each Points3D log call), in file order."""
    from rerun.chunk import RrdReader

    rows: list[object] = []
    for chunk in RrdReader(path).stream():
        if chunk.entity_path != entity:
            continue
        rb = chunk.to_record_batch()
        if component in rb.schema.names:
            rows += [v for v in rb.column(component).to_pylist() if v is not None]
    return rows
