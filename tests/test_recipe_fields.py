"""Every numeric field of every stage-6 recipe (dataset, training, tolerance, transfer, Table S2,
pipeline) and of the loop and loop-map recipes against bad values: NaN, infinities and values outside its range are one ConfigError naming
the field and what is allowed (the CLI prints it as one line and exits 2), and an in-range value passes."""

from __future__ import annotations

import math

import pytest

from metadesign.config import Param, parse
from metadesign.validation import ConfigError


def _schemas():
    import importlib

    from metadesign.reconstruction import dataset
    from metadesign.studies import loop_map, loop_recipe, pipeline, table_s2, tolerance, transfer
    from metadesign.turbulence import scenario

    train = importlib.import_module("metadesign.reconstruction.train")  # the package exports train(), the function
    wind = tuple(s for s in scenario.SECTIONS if s.name == "wind")  # the loop recipe's [wind]
    return {"dataset": dataset.SECTIONS, "train": train.SECTIONS, "tolerance": tolerance.TOLERANCE_SECTIONS,
            "transfer": transfer.SECTIONS, "table-s2": table_s2.SECTIONS, "pipeline": pipeline.SECTIONS,
            "loop": (*loop_recipe.SECTIONS, *wind), "loop-map": (loop_map.MAP_SECTION,)}


def _good(p: Param):
    """An in-range value of a numeric parameter (its default when it has one)."""
    from metadesign.config import _REQUIRED

    if p.default is not _REQUIRED and p.default is not None:
        return p.default
    lo = p.lo if p.lo is not None else 0
    v = lo + (1 if p.open_lo or lo == 0 else 0)
    if p.hi is not None:
        v = min(v, p.hi)
    return int(v) if p.kind is int else float(v)


def _bad_values(p: Param):
    out = [float("nan"), float("inf"), -float("inf")]
    if p.lo is not None:
        out.append(p.lo - 1 if not p.open_lo else p.lo)
    if p.hi is not None:
        out.append(p.hi + 1 if not p.open_hi else p.hi)
    return out


def _cases():
    for name, sections in _schemas().items():
        for sec in sections:
            for p in sec.params:
                if p.kind not in (int, float) or p.choices:
                    continue
                for v in _bad_values(p):
                    yield pytest.param(name, sec.name, p.key, v, id=f"{name}:{sec.name}.{p.key}={v}")


def _minimal(sections, section: str, key: str, value) -> dict:
    """A document with every required key of every section at a good value, and ``section.key = value``."""
    from metadesign.config import _REQUIRED

    doc: dict = {}
    for sec in sections:
        for p in sec.params:
            if p.default is _REQUIRED:
                doc.setdefault(sec.name, {})[p.key] = _good(p) if p.kind in (int, float) else \
                    ("x" if p.kind is str else [])
    doc.setdefault(section, {})[key] = value
    return doc


@pytest.mark.parametrize("schema,section,key,value", list(_cases()))
def test_every_numeric_recipe_field_refuses_bad_values(schema, section, key, value):
    sections = _schemas()[schema]
    p = next(q for s in sections if s.name == section for q in s.params if q.key == key)
    if p.kind is int and isinstance(value, float) and math.isfinite(value) and value == int(value):
        value = int(value)
    with pytest.raises(ConfigError) as e:
        parse(_minimal(sections, section, key, value), sections, schema)
    msg = str(e.value)
    assert msg.startswith(f"{section}.{key}") and "\n" not in msg, msg


def test_the_walk_covers_every_stage6_recipe():
    cases = list(_cases())
    assert {c.values[0] for c in cases} == set(_schemas())
    assert len(cases) > 100
