"""Every key of the loop and loop-map recipes against a bad value, as a user would give it to
``metadesign loop`` / ``metadesign loop-map``: one line on stderr naming the field, exit 2, nothing written
(NaN and infinities included).  A last test checks that the tables name every key of both recipes, so a new
key without a bad-input case fails here.  (tests/test_recipe_fields.py walks the numeric keys' ranges at the
parser as well.)"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import run_main

REPO = Path(__file__).resolve().parents[1]
DEVICE = {"design": f'"{REPO / "layouts" / "demo.toml"}"', "sensor": f'"{REPO / "sensing" / "demo.toml"}"',
          "turbulence": f'"{REPO / "sensing" / "turbulence.toml"}"'}
MAP = {"rates_hz": "[1000, 2000]", "greenwood_hz": "[100]", "rytov": "[0.5]"}


def _doc(changes: dict, map_: bool = False) -> str:
    """A loop (or map) recipe: the good base with ``{(section, key): TOML literal or None (removed)}`` applied
    (``(section, None)``: the whole section's literal, e.g. ``wind = 3``)."""
    secs = {"device": dict(DEVICE), "loop": {"methods": '["ideal", "open"]'}, "dm": {}, "wind": {"speed_m_s": "3.0"}}
    if map_:
        secs["map"] = dict(MAP)
    top = []
    for (sec, key), v in changes.items():
        if key is None:
            secs.pop(sec)
            top.append(f"{sec} = {v}")
        elif v is None:
            secs[sec].pop(key, None)
        else:
            secs.setdefault(sec, {})[key] = v
    text = "".join(f"{t}\n" for t in top)
    for sec, kv in secs.items():
        text += f"[{sec}]\n" + "".join(f"{k} = {v}\n" for k, v in kv.items())
    return text


def _influence_files(folder: Path) -> None:
    """Bad influence matrices next to the recipe (the crop of sensing/turbulence.toml is 41 x 41)."""
    np.save(folder / "flat.npy", np.zeros((41, 41), np.float32))
    np.save(folder / "small.npy", np.zeros((3, 10, 10), np.float32))
    bad = np.zeros((3, 41, 41), np.float32)
    bad[1, 5, 5] = np.nan
    np.save(folder / "nan.npy", bad)
    np.save(folder / "pickled.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    (folder / "text.npy").write_text("not an array\n")
    np.save(folder / "good.npy", np.zeros((3, 41, 41), np.float32))


def _tree(folder: Path) -> set:
    return {(str(p.relative_to(folder)), p.stat().st_size) for p in Path(folder).rglob("*")}


L, D, M, W = "loop", "dm", "device", "wind"
#: (changes, the field the one line names)
LOOP_CASES = [
    ({(M, "design"): '"nope.toml"'}, "device.design"),
    ({(M, "design"): "3"}, "device.design"),
    ({(M, "sensor"): '"nope.toml"'}, "device.sensor"),
    ({(M, "turbulence"): '"nope.toml"'}, "device.turbulence"),
    ({(M, "turbulence"): None}, "device.turbulence"),
    ({(M, "model"): '"nope.safetensors"'}, "device.model"),
    ({(L, "methods"): '["unet"]'}, "device.model"),
    ({(L, "methods"): '["realtime_tt", "open"]'}, "device.realtime"),
    ({(L, "methods"): '["realtime_peak", "open"]'}, "device.realtime"),
    ({(M, "realtime"): '"nope.safetensors"'}, "device.realtime"),
    ({(M, "colour"): '"red"'}, "device.colour"),
    ({(L, "rate_hz"): "nan"}, "loop.rate_hz"),
    ({(L, "rate_hz"): "inf"}, "loop.rate_hz"),
    ({(L, "rate_hz"): "0.5"}, "loop.rate_hz"),
    ({(L, "steps"): "1"}, "loop.steps"),
    ({(L, "steps"): "10.5"}, "loop.steps"),
    ({(L, "steps"): "nan"}, "loop.steps"),
    ({(L, "substeps"): "0"}, "loop.substeps"),
    ({(L, "substeps"): "65"}, "loop.substeps"),
    ({(L, "rytov"): "0"}, "loop.rytov"),
    ({(L, "rytov"): "nan"}, "loop.rytov"),
    ({(L, "rytov"): "inf"}, "loop.rytov"),
    ({(L, "rytov"): "6"}, "loop.rytov"),
    ({(L, "gain"): "nan"}, "loop.gain"),
    ({(L, "gain"): "-inf"}, "loop.gain"),
    ({(L, "gain"): '"fast"'}, "loop.gain"),
    ({(L, "gain"): "{ ideal = 3.0 }"}, "loop.gain.ideal"),
    ({(L, "gain"): "{ ideal = nan }"}, "loop.gain.ideal"),
    ({(L, "gain"): "{ bogus = 0.2 }"}, "loop.gain"),  # a table names every closed loop, no other
    ({(L, "gain"): '{ ideal = "fast" }'}, "loop.gain.ideal"),
    ({(L, "gain"): '{ ideal = "optimise" }', (L, "gain_steps"): "100000"}, "loop.gain_steps"),  # > loop.steps
    ({(L, "gain_steps"): "1"}, "loop.gain_steps"),
    ({(L, "gain_steps"): "inf"}, "loop.gain_steps"),
    ({(L, "pseudo_open_loop"): "1"}, "loop.pseudo_open_loop"),
    ({(L, "seeds"): "0"}, "loop.seeds"),
    ({(L, "seeds"): "nan"}, "loop.seeds"),
    ({(L, "leak"): "-0.1"}, "loop.leak"),
    ({(L, "leak"): "1.5"}, "loop.leak"),
    ({(L, "leak"): "nan"}, "loop.leak"),
    ({(L, "noise_percent"): "-1"}, "loop.noise_percent"),
    ({(L, "noise_percent"): "101"}, "loop.noise_percent"),
    ({(L, "noise_percent"): "nan"}, "loop.noise_percent"),
    ({(L, "noise_percent"): "inf"}, "loop.noise_percent"),
    ({(L, "photons_per_frame"): "-1"}, "loop.photons_per_frame"),
    ({(L, "photons_per_frame"): "nan"}, "loop.photons_per_frame"),
    ({(L, "photons_per_frame"): "inf"}, "loop.photons_per_frame"),
    ({(L, "photons_per_frame"): "2e15"}, "loop.photons_per_frame"),
    ({(L, "photons_per_frame"): '"many"'}, "loop.photons_per_frame"),
    ({(L, "read_noise_e"): "-1", (L, "photons_per_frame"): "100"}, "loop.read_noise_e"),
    ({(L, "read_noise_e"): "nan", (L, "photons_per_frame"): "100"}, "loop.read_noise_e"),
    ({(L, "read_noise_e"): "inf", (L, "photons_per_frame"): "100"}, "loop.read_noise_e"),
    ({(L, "read_noise_e"): "3.0"}, "loop.read_noise_e"),  # read noise without photons
    ({(L, "sh_lenslets"): "1"}, "loop.sh_lenslets"),
    ({(L, "sh_lenslets"): "65"}, "loop.sh_lenslets"),
    ({(L, "sh_lenslets"): "8.0"}, "loop.sh_lenslets"),
    ({(L, "sh_lenslets"): "nan"}, "loop.sh_lenslets"),
    ({(L, "sh_lenslets"): "true"}, "loop.sh_lenslets"),
    ({(L, "sh_lenslets"): '"many"'}, "loop.sh_lenslets"),
    ({(L, "readout_frames"): "-1"}, "loop.readout_frames"),
    ({(L, "readout_frames"): "nan"}, "loop.readout_frames"),
    ({(L, "readout_frames"): "inf"}, "loop.readout_frames"),
    ({(L, "dm_frames"): "-0.5"}, "loop.dm_frames"),
    ({(L, "dm_frames"): "nan"}, "loop.dm_frames"),
    ({(L, "dm_frames"): "inf"}, "loop.dm_frames"),
    ({(L, "latency_ms"): "3"}, "loop.latency_ms"),
    ({(L, "latency_ms"): "{ideal = nan}"}, "loop.latency_ms"),
    ({(L, "latency_ms"): "{ideal = inf}"}, "loop.latency_ms"),
    ({(L, "latency_ms"): "{psychic = 1}"}, "loop.latency_ms"),
    ({(L, "methods"): '["ideal", "ideal"]'}, "loop.methods"),
    ({(L, "methods"): "[]"}, "loop.methods"),
    ({(L, "seed"): "-1"}, "loop.seed"),
    ({(L, "seed"): "1.5"}, "loop.seed"),
    ({(L, "threshold_db"): "0"}, "loop.threshold_db"),
    ({(L, "threshold_db"): "nan"}, "loop.threshold_db"),
    ({(L, "threshold_db"): "61"}, "loop.threshold_db"),
    ({(L, "retrieval_budget_ms"): "0"}, "loop.retrieval_budget_ms"),
    ({(L, "retrieval_budget_ms"): "-5"}, "loop.retrieval_budget_ms"),
    ({(L, "retrieval_budget_ms"): "nan"}, "loop.retrieval_budget_ms"),
    ({(L, "retrieval_budget_ms"): "inf"}, "loop.retrieval_budget_ms"),
    ({(L, "retrieval_budget_ms"): "1e6"}, "loop.retrieval_budget_ms"),
    ({(L, "retrieval_budget_ms"): '"fast"'}, "loop.retrieval_budget_ms"),
    ({(L, "methods"): '["refine_warm"]'}, "device.model"),  # no model
    ({(L, "methods"): '["refine_warm", "open"]', (M, "model"): '"good.npy"'}, "device.model"),  # not a refiner
    ({(L, "colour"): "3"}, "loop.colour"),
    ({(D, "kind"): '"magic"'}, "dm.kind"),
    ({(D, "modes"): "1"}, "dm.modes"),
    ({(D, "modes"): "nan"}, "dm.modes"),
    ({(D, "actuators"): "1"}, "dm.actuators"),
    ({(D, "actuators"): "257"}, "dm.actuators"),
    ({(D, "actuators"): "12.5"}, "dm.actuators"),
    ({(D, "actuators"): "inf"}, "dm.actuators"),
    ({(D, "coupling"): "0"}, "dm.coupling"),
    ({(D, "coupling"): "0.95"}, "dm.coupling"),
    ({(D, "coupling"): "nan"}, "dm.coupling"),
    ({(D, "regularisation"): "-1e-3"}, "dm.regularisation"),
    ({(D, "regularisation"): "inf"}, "dm.regularisation"),
    ({(D, "regularisation"): "nan"}, "dm.regularisation"),
    ({(D, "stroke_um"): "0"}, "dm.stroke_um"),
    ({(D, "stroke_um"): "-2"}, "dm.stroke_um"),
    ({(D, "stroke_um"): "nan"}, "dm.stroke_um"),
    ({(D, "stroke_um"): "inf"}, "dm.stroke_um"),
    ({(D, "stroke_um"): "1001"}, "dm.stroke_um"),
    ({(D, "influence"): '"missing.npy"'}, "dm.influence"),
    ({(D, "influence"): '"flat.npy"'}, "dm.influence"),
    ({(D, "influence"): '"small.npy"'}, "dm.influence"),
    ({(D, "influence"): '"nan.npy"'}, "dm.influence"),
    ({(D, "influence"): '"pickled.npy"'}, "dm.influence"),
    ({(D, "influence"): '"text.npy"'}, "dm.influence"),
    ({(D, "influence"): "3"}, "dm.influence"),
    ({(D, "influence"): '"good.npy"', (D, "kind"): '"modal"'}, "dm.influence"),
    ({(D, "tip_tilt"): '"yes"'}, "dm.tip_tilt"),
    ({(D, "tip_tilt"): "1"}, "dm.tip_tilt"),
    ({(D, "colour"): "1"}, "dm.colour"),
    ({(W, None): "3"}, "wind"),
    ({(W, "speed_m_s"): "-3.0"}, "wind.speed_m_s"),
    ({(W, "speed_m_s"): "nan"}, "wind.speed_m_s"),
    ({(W, "speed_m_s"): "inf"}, "wind.speed_m_s"),
    ({(W, "end_speed_m_s"): "nan"}, "wind.end_speed_m_s"),
    ({(W, "end_speed_m_s"): "201"}, "wind.end_speed_m_s"),
    ({(W, "direction_deg"): "inf"}, "wind.direction_deg"),
    ({(W, "direction_deg"): "400"}, "wind.direction_deg"),
    ({(W, "speed_m_s"): None, (W, "speeds_m_s"): "[1.0, 2.0]"}, "wind.speeds_m_s"),
    ({(W, "speed_m_s"): None, (W, "speeds_m_s"): "[" + ", ".join(["1.0"] * 12 + ["nan"]) + "]"}, "wind.speeds_m_s"),
    ({(W, "directions_deg"): "[0.0]"}, "wind.directions_deg"),
    ({(W, "directions_deg"): "[" + ", ".join(["0.0"] * 12 + ["inf"]) + "]"}, "wind.directions_deg"),
    ({(W, "colour"): "1"}, "wind.colour"),
    ({("extra", "x"): "1"}, "extra"),
]

P = "map"
#: map cases (a map recipe is a loop recipe with [map]; a few loop keys are checked through it too)
MAP_CASES = [
    ({(P, "rates_hz"): None}, "map.rates_hz"),
    ({(P, "rates_hz"): "[nan]"}, "map.rates_hz"),
    ({(P, "rates_hz"): "[inf, 1000]"}, "map.rates_hz"),
    ({(P, "rates_hz"): "[0.5]"}, "map.rates_hz"),
    ({(P, "rates_hz"): "2000"}, "map.rates_hz"),
    ({(P, "latency_ms"): "[0, 1]"}, "map.latency_ms"),  # with a rate axis
    ({(P, "rates_hz"): None, (P, "latency_ms"): "[nan]"}, "map.latency_ms"),
    ({(P, "rates_hz"): None, (P, "latency_ms"): "[-1]"}, "map.latency_ms"),
    ({(P, "rates_hz"): None, (P, "latency_ms"): "[inf]"}, "map.latency_ms"),
    ({(P, "greenwood_hz"): None}, "map.greenwood_hz"),
    ({(P, "greenwood_hz"): "[0]"}, "map.greenwood_hz"),
    ({(P, "greenwood_hz"): "[nan]"}, "map.greenwood_hz"),
    ({(P, "greenwood_hz"): "[inf]"}, "map.greenwood_hz"),
    ({(P, "rytov"): "[0]"}, "map.rytov"),
    ({(P, "rytov"): "[nan]"}, "map.rytov"),
    ({(P, "rytov"): "[inf]"}, "map.rytov"),
    ({(P, "steps"): "1"}, "map.steps"),
    ({(P, "steps"): "nan"}, "map.steps"),
    ({(P, "scan_latency_ms"): "[-1]"}, "map.scan_latency_ms"),
    ({(P, "scan_latency_ms"): "[nan]"}, "map.scan_latency_ms"),
    ({(P, "scan_latency_ms"): "[inf]"}, "map.scan_latency_ms"),
    ({(P, "verdict_rytov"): "0"}, "map.verdict_rytov"),
    ({(P, "verdict_rytov"): "nan"}, "map.verdict_rytov"),
    ({(P, "verdict_greenwood_hz"): "inf"}, "map.verdict_greenwood_hz"),
    ({(P, "verdict_greenwood_hz"): "-1"}, "map.verdict_greenwood_hz"),
    ({(P, "verdict_rate_hz"): "nan"}, "map.verdict_rate_hz"),
    ({(P, "verdict_rate_hz"): "0"}, "map.verdict_rate_hz"),
    ({(P, "latency_methods"): '["ideal"]'}, "map.latency_methods"),  # with a rate axis
    ({(P, "rates_hz"): None, (P, "latency_ms"): "[0]", (P, "latency_methods"): '["open"]'}, "map.latency_methods"),
    ({(P, "colour"): "1"}, "map.colour"),
    ({(P, None): "3"}, "map"),
    ({(L, "gain"): '"fast"'}, "loop.gain"),
    ({(L, "gain"): '"optimise"', (L, "gain_steps"): "300", (P, "steps"): "200"}, "loop.gain_steps"),  # > the map's
    ({(L, "gain"): "{ bogus = 0.4 }"}, "loop.gain"),  # a table of gains names every closed loop, no other
    ({(L, "gain"): '{ ideal = "fast" }'}, "loop.gain.ideal"),
    ({(L, "methods"): '["open"]'}, "loop.methods"),
    ({(L, "photons_per_frame"): "nan"}, "loop.photons_per_frame"),
    ({(L, "sh_lenslets"): "0"}, "loop.sh_lenslets"),
    ({(D, "stroke_um"): "inf"}, "dm.stroke_um"),
    ({(D, "influence"): '"small.npy"'}, "dm.influence"),
]


def _check(cmd: str, changes: dict, match: str, tmp_path: Path, capsys, map_: bool = False):
    _influence_files(tmp_path)
    rec = tmp_path / "r.toml"
    rec.write_text(_doc(changes, map_))
    before = _tree(tmp_path)
    rc, _, err = run_main([cmd, rec, "-o", tmp_path / "out"], capsys)
    assert rc == 2 and len(err) == 1 and err[0].startswith("metadesign: error:"), (rc, err)
    assert f"error: {match}" in err[0] or f"error: [{match}]" in err[0], err[0]
    assert _tree(tmp_path) == before, "a refused recipe wrote or changed files"


@pytest.mark.parametrize("changes, match", [pytest.param(c, m, id=f"{m}:{i}") for i, (c, m) in enumerate(LOOP_CASES)])
def test_every_bad_loop_key_is_one_line_and_writes_nothing(changes, match, tmp_path, capsys):
    _check("loop", changes, match, tmp_path, capsys)


@pytest.mark.parametrize("changes, match", [pytest.param(c, m, id=f"{m}:{i}") for i, (c, m) in enumerate(MAP_CASES)])
def test_every_bad_map_key_is_one_line_and_writes_nothing(changes, match, tmp_path, capsys):
    _check("loop-map", changes, match, tmp_path, capsys, map_=True)


def test_the_good_base_recipes_load(tmp_path):
    """The bases the cases damage are good (each case fails for its own key, not the base's)."""
    from metadesign.studies.loop_map import load_map_recipe
    from metadesign.studies.loop_recipe import load_loop_recipe

    _influence_files(tmp_path)
    (tmp_path / "r.toml").write_text(_doc({(D, "influence"): '"good.npy"', (L, "photons_per_frame"): "100",
                                          (L, "read_noise_e"): "2", (L, "sh_lenslets"): '"auto"'}))
    rec = load_loop_recipe(tmp_path / "r.toml")
    assert rec.influence == tmp_path / "good.npy" and rec.loop.sh_lenslets == "auto"
    (tmp_path / "m.toml").write_text(_doc({}, map_=True))
    assert load_map_recipe(tmp_path / "m.toml").rates_hz == (1000.0, 2000.0)


def test_the_tables_name_every_key_of_both_recipes():
    from metadesign.studies.loop_map import MAP_SECTION
    from metadesign.studies.loop_recipe import SECTIONS
    from metadesign.turbulence.scenario import SECTIONS as SCENARIO

    wind = next(s for s in SCENARIO if s.name == "wind")
    loop_keys = {f"{s.name}.{p.key}" for s in (*SECTIONS, wind) for p in s.params}
    loop_keys |= {"loop.gain", "loop.methods", "loop.latency_ms", "loop.sh_lenslets"}  # read outside the schema
    map_keys = {f"map.{p.key}" for p in MAP_SECTION.params} | {"map.latency_methods"}
    named = {m for _, m in LOOP_CASES}
    assert loop_keys <= named, sorted(loop_keys - named)
    assert map_keys <= {m for _, m in MAP_CASES}, sorted(map_keys - {m for _, m in MAP_CASES})
