"""The loop map (issue #50, section 4) on the small demo device: the wind scaled to each point gives the target
Greenwood frequency (the path-integral formula, computed here with numpy), the region criterion and the
verdict are applied as stated (synthetic numbers), a tiny map has the same bytes on 1 and 2 workers and
after a killed run resumes, a latency axis declares the metasurface loop's latency, and bad recipes are one
line with nothing written."""

from __future__ import annotations

import contextlib
import io
import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from conftest import run_main

torch = pytest.importorskip("torch")
REPO = Path(__file__).resolve().parents[1]

#: a tiny map: 2 rates x 1 f_G x 1 Rytov, 4 steps, the ideal, open and linear loops (the linear one's latency
#: declared, so the numbers do not depend on this machine's timing), the verdict's point on the grid
MAP = "rates_hz = [1000, 2000]\ngreenwood_hz = [100]\nrytov = [0.5]\nscan_latency_ms = [0, 1]\n"
LOOP = 'methods = ["ideal", "open", "linear"]\nsteps = 4\nsubsteps = 1\nlatency_ms = {linear = 0.2}\n'


def _recipe(folder: Path, map_: str = MAP, loop: str = LOOP, wind: str = "speed_m_s = 3.0\n",
            extra: str = "[dm]\nmodes = 3\n") -> Path:
    p = Path(folder) / "map.toml"
    p.write_text(f'[device]\ndesign = "{REPO / "layouts" / "demo.toml"}"\nsensor = "{REPO / "sensing" / "demo.toml"}"\n'
                 f'turbulence = "{REPO / "sensing" / "turbulence.toml"}"\n[loop]\n{loop}{extra}[wind]\n{wind}'
                 + (f"[map]\n{map_}" if map_ is not None else ""))
    return p


def _main(argv) -> tuple[int, str]:
    from metadesign.cli import main

    err = io.StringIO()
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
        rc = main([str(a) for a in argv])
    return rc, err.getvalue()


def _numbers(out: Path) -> str:
    """map.json without its timings and paths (what must not depend on the worker count)."""
    def strip(d):
        if isinstance(d, dict):
            return {k: strip(v) for k, v in d.items() if k not in ("seconds", "figures", "recipe")}
        if isinstance(d, list):
            return [strip(v) for v in d]
        return d

    return json.dumps(strip(json.loads((out / "map.json").read_text())), sort_keys=True)


def test_the_scaled_wind_gives_the_target_greenwood_frequency(tmp_path):
    """A ramped, oblique wind scaled to 50 and 200 Hz at Rytov 0.3 and 0.5: the plane-wave
    ``f_G = 2.31 lambda^(-6/5) [sum Cn2 dz v^(5/3)]^(3/5)`` of each point's wind (Cn2 dz from the screens' r0,
    ``r0^(-5/3) = 0.423 k^2 Cn2 dz``) is the target; the spherical one (weights ``(z/L)^(5/3)``) is reported
    beside it; the ramp's shape and the direction are kept."""
    from metadesign.studies.loop_map import load_map_recipe
    from metadesign.turbulence.path import solve_path
    from metadesign.turbulence.scenario import load_scenario

    rec = _recipe(tmp_path, "rates_hz = [2000]\ngreenwood_hz = [50, 200]\nrytov = [0.3, 0.5]\n",
                  wind="speed_m_s = 2.0\nend_speed_m_s = 6.0\ndirection_deg = 30.0\n")
    m = load_map_recipe(rec)
    sc0 = load_scenario(REPO / "sensing" / "turbulence.toml")
    assert {k for k in m.scenes} == {(0.3, 50.0), (0.3, 200.0), (0.5, 50.0), (0.5, 200.0), (0.5, 100.0)}  # + verdict
    for (ry, g), s in m.scenes.items():
        sc = replace(sc0, rytov=ry)
        r0 = solve_path(sc).r0_screens
        k = 2 * np.pi / sc.wavelength
        cdz = np.where(np.isfinite(r0), r0 ** (-5 / 3), 0.0) / (0.423 * k * k)
        w = s["wind"]
        v = w["speed_m_s"] + (w["end_speed_m_s"] - w["speed_m_s"]) * np.asarray(sc.z) / sc.length
        fg = 2.31 * sc.wavelength ** (-6 / 5) * np.sum(cdz * v ** (5 / 3)) ** (3 / 5)
        assert fg == pytest.approx(g, rel=1e-9)
        assert s["greenwood_hz"] == pytest.approx(g, rel=1e-9)
        sph = 2.31 * sc.wavelength ** (-6 / 5) * np.sum((np.asarray(sc.z) / sc.length) ** (5 / 3) * cdz
                                                        * v ** (5 / 3)) ** (3 / 5)
        assert s["greenwood_spherical_hz"] == pytest.approx(sph, rel=1e-9) and sph < g
        assert w["end_speed_m_s"] / w["speed_m_s"] == pytest.approx(3.0) and w["direction_deg"] == 30.0
    # stronger turbulence needs less wind for the same f_G
    assert m.scenes[(0.5, 50.0)]["scale"] < m.scenes[(0.3, 50.0)]["scale"]


def test_the_region_criterion_and_the_verdict_are_applied_as_stated():
    from metadesign.studies.loop_map import in_region, latency_reaching, map_verdict, regions

    assert in_region(0.40, 0.5, 0.0)  # exactly 0.8 x the ideal's
    assert not in_region(0.399, 0.5, 0.0)
    assert in_region(0.45, 0.5, 0.01)  # exactly 1e-2
    assert not in_region(0.45, 0.5, 0.0101)
    assert not in_region(0.2, 0.5, 0.5)

    def pt(rate, ideal, rt, sh):
        return {"rytov": 0.5, "greenwood_hz": 100.0, "rate_hz": rate,
                "methods": {"ideal": {"npib_mean": ideal[0], "fade_probability": ideal[1]},
                            "realtime": {"npib_mean": rt[0], "fade_probability": rt[1]},
                            "shack_hartmann": {"npib_mean": sh[0], "fade_probability": sh[1]}}}

    pts = [pt(1000.0, (0.5, 0.0), (0.45, 0.0), (0.30, 0.0)),   # realtime in, SH out (0.6 of the ideal)
           pt(2000.0, (0.5, 0.02), (0.45, 0.005), (0.41, 0.0)),  # the ideal fades too often; both others in
           pt(4000.0, (0.5, 0.0), (0.45, 0.03), (0.39, 0.0))]    # realtime fades; SH 0.78 of the ideal: out
    reg = regions(pts, "rate_hz")
    rates = {m: [p["rate_hz"] for p in r] for m, r in reg.items()}
    assert rates == {"ideal": [1000.0, 4000.0], "realtime": [1000.0, 2000.0], "shack_hartmann": [2000.0]}

    # the largest scanned latency up to which every scanned value keeps the level, and the crossing
    assert latency_reaching([0, 1, 2], [1.0, 0.0, 1.0], 0.5) == {"latency_ms": 0.0, "interpolated_ms": 0.5}
    assert latency_reaching([2, 0, 1], [3, 5, 4], 1.0) == {"latency_ms": 2.0, "interpolated_ms": None}
    assert latency_reaching([0, 1], [0.1, 0.2], 0.5) == {"latency_ms": None, "interpolated_ms": None}

    cell = {"methods": {"ideal": {"npib_mean": 0.5, "latency_ms": 0.0, "delay_frames": 1.0},
                        "shack_hartmann": {"npib_mean": 0.15, "latency_ms": 2.0, "delay_frames": 5.0},
                        "realtime": {"npib_mean": 0.38, "latency_ms": 0.3, "delay_frames": 1.6},
                        "linear": {"npib_mean": 0.1, "latency_ms": 0.1, "delay_frames": 1.2}}}
    scan = {"realtime": {"latency_ms": [0.0, 0.25, 0.5, 1.0], "npib_mean": [0.45, 0.41, 0.36, 0.2]}}
    v = map_verdict(cell, scan, {"rytov": 0.5, "greenwood_hz": 100.0, "rate_hz": 2000.0})
    assert v["best_metasurface"] == "realtime"
    assert v["vs_ideal"] == pytest.approx(0.76) and v["vs_shack_hartmann"] == pytest.approx(0.38 / 0.15)
    assert v["meets_ideal"] is False and v["meets_shack_hartmann"] is True and v["met"] is False
    r = v["latency_for"]
    assert r["ideal"]["latency_ms"] == 0.25 and r["ideal"]["interpolated_ms"] == pytest.approx(0.30)
    assert r["shack_hartmann"]["latency_ms"] == 0.5 and r["shack_hartmann"]["interpolated_ms"] == pytest.approx(0.6875)
    assert r["both"]["latency_ms"] == 0.25 and r["both"]["interpolated_ms"] == pytest.approx(0.30)
    assert "0.76 of the ideal-phase loop's (goal >= 0.8: NOT met)" in v["statement"]
    assert "(goal >= 2x: met)" in v["statement"] and "0.8 of the ideal: reached up to 0.25 ms" in v["statement"]
    assert map_verdict({"methods": {"ideal": cell["methods"]["ideal"]}}, {}, {"rytov": 0.5, "greenwood_hz": 100.0,
                                                                                 "rate_hz": 2000.0})["best_metasurface"] is None
    # the best loop's gain is called optimised only where it was searched (a gain table may give it)
    cell["methods"]["realtime"]["gain"] = 0.4
    where = {"rytov": 0.5, "greenwood_hz": 100.0, "rate_hz": 2000.0}
    assert "gain 0.4 (optimised)" in map_verdict(cell, scan, where, optimised=frozenset({"realtime"}))["statement"]
    assert "optimised" not in map_verdict(cell, scan, where, optimised=frozenset({"ideal"}))["statement"]
    assert "gain 0.4 (optimised)" in map_verdict(cell, scan, where, optimised=True)["statement"]


@pytest.fixture(scope="module")
def one_worker(tmp_path_factory):
    """The tiny map on one worker (the reference of the next two tests)."""
    base = tmp_path_factory.mktemp("loop-map")
    rec = _recipe(base)
    rc, err = _main(["loop-map", rec, "-o", base / "j1", "-j", "1", "--json"])
    assert rc == 0, err
    return rec, base / "j1"


def test_a_tiny_map_has_the_same_bytes_on_two_workers(one_worker, tmp_path, capsys):
    rec, j1 = one_worker
    rep = json.loads((j1 / "map.json").read_text())
    assert [(p["rytov"], p["greenwood_hz"], p["rate_hz"]) for p in rep["points"]] == [(0.5, 100.0, 1000.0),
                                                                                      (0.5, 100.0, 2000.0)]
    assert rep["greenwood"]["scenes"][0]["greenwood_hz"] == pytest.approx(100.0, rel=1e-9)
    p = rep["points"][1]["methods"]
    assert p["linear"]["latency_ms"] == pytest.approx(0.2) and p["linear"]["delay_frames"] == pytest.approx(1.4)
    assert p["ideal"]["vs_ideal"] == 1.0 and 0 < p["open"]["npib_mean"] <= 1.5
    v = rep["verdict"]
    assert v["on_grid"] and v["best_metasurface"] == "linear" and v["methods"]["linear"] == {
        k: x for k, x in p["linear"].items() if k not in ("vs_ideal", "in_region")}
    assert v["latency_scan"]["latency_ms"] == [0.0, 1.0] and "statement" in v
    assert (j1 / "map.png").is_file() and not (j1.parent / "j1.partial").exists()
    rc, out, err = run_main(["loop-map", rec, "-o", tmp_path / "j2", "-j", "2"], capsys)
    assert rc == 0, err
    assert "Rytov 0.5" in out and "At Rytov 0.5, f_G 100 Hz, 2000 Hz" in out
    assert _numbers(tmp_path / "j2") == _numbers(j1)


def test_a_killed_map_resumes_to_the_same_bytes(one_worker, tmp_path, capsys, monkeypatch):
    import functools

    from metadesign.execution import Execution
    from metadesign.studies import cli_loop_map

    rec, j1 = one_worker
    monkeypatch.setattr(cli_loop_map, "Execution", functools.partial(Execution, stop_after=3), raising=False)
    rc, _, err = run_main(["loop-map", rec, "-o", tmp_path / "k", "-j", "1", "--json"], capsys)
    assert rc == 130 and "interrupted" in err[-1], err
    assert len(list((tmp_path / "k.partial").glob("ry*.npz"))) == 3
    monkeypatch.setattr(cli_loop_map, "Execution", Execution, raising=False)
    rc, _, err = run_main(["loop-map", rec, "-o", tmp_path / "k", "-j", "2"], capsys)
    assert rc == 0, err
    assert any("resuming: 3/8 tasks" in e for e in err), err
    assert _numbers(tmp_path / "k") == _numbers(j1)
    assert not (tmp_path / "k.partial").exists()


def test_a_latency_axis_declares_the_metasurface_loops_latency(tmp_path, capsys):
    """latency_ms = [0, 1] at 2 kHz: the linear loop's latency is the axis's (1 + 2 kHz x latency frames of
    delay), the ideal and open loops run once for both cells (the same numbers), the verdict's point keeps
    the declared 0.2 ms, and its scan is the axis."""
    rec = _recipe(tmp_path, "latency_ms = [0, 1]\ngreenwood_hz = [100]\nrytov = [0.5]\n")
    rc, _, err = run_main(["loop-map", rec, "-o", tmp_path / "out", "--json"], capsys)
    assert rc == 0, err
    rep = json.loads((tmp_path / "out" / "map.json").read_text())
    a, b = (p["methods"] for p in rep["points"])
    assert [p["latency_ms"] for p in rep["points"]] == [0.0, 1.0] and rep["axis"] == "latency_ms"
    assert (a["linear"]["latency_ms"], b["linear"]["latency_ms"]) == (0.0, 1.0)
    assert (a["linear"]["delay_frames"], b["linear"]["delay_frames"]) == (1.0, 3.0)
    assert a["ideal"] == b["ideal"] and a["open"] == b["open"]
    assert rep["verdict"]["latency_ms"] == pytest.approx(0.2) and not rep["verdict"]["on_grid"]
    scan = rep["verdict"]["scans"]["linear"]
    assert scan["latency_ms"] == [0.0, 1.0] and scan["npib_mean"] == [a["linear"]["npib_mean"], b["linear"]["npib_mean"]]


@pytest.mark.parametrize("map_, loop, wind, match", [
    (None, LOOP, "speed_m_s = 3.0\n", "[map]"),
    ("greenwood_hz = [100]\nrytov = [0.5]\n", LOOP, "speed_m_s = 3.0\n", "map.rates_hz"),
    (MAP + "latency_ms = [0, 1]\n", LOOP, "speed_m_s = 3.0\n", "map.latency_ms"),
    (MAP.replace("[100]", "[nan]"), LOOP, "speed_m_s = 3.0\n", "map.greenwood_hz"),
    (MAP.replace("[100]", "[]"), LOOP, "speed_m_s = 3.0\n", "map.greenwood_hz"),
    (MAP.replace("[1000, 2000]", "[1000, 1000]"), LOOP, "speed_m_s = 3.0\n", "map.rates_hz"),
    (MAP.replace("[1000, 2000]", "[0, 2000]"), LOOP, "speed_m_s = 3.0\n", "map.rates_hz"),
    (MAP.replace("[0.5]", "[-0.5]"), LOOP, "speed_m_s = 3.0\n", "map.rytov"),
    (MAP.replace("[0.5]", "[4.5]"), LOOP, "speed_m_s = 3.0\n", "map.rytov"),  # infeasible sampling
    (MAP.replace("[100]", "[90000]"), LOOP, "speed_m_s = 3.0\n", "map.greenwood_hz"),  # wind beyond 200 m/s
    (MAP + "steps = 1\n", LOOP, "speed_m_s = 3.0\n", "map.steps"),
    (MAP + "colour = 3\n", LOOP, "speed_m_s = 3.0\n", "map.colour"),
    (MAP + 'latency_methods = ["linear"]\n', LOOP, "speed_m_s = 3.0\n", "map.latency_methods"),
    ("latency_ms = [0]\ngreenwood_hz = [100]\nrytov = [0.5]\nlatency_methods = [\"open\"]\n", LOOP,
     "speed_m_s = 3.0\n", "map.latency_methods"),
    ("latency_ms = [0]\ngreenwood_hz = [100]\nrytov = [0.5]\nverdict_rate_hz = 1000.0\n", LOOP,
     "speed_m_s = 3.0\n", "map.verdict_rate_hz"),
    (MAP, LOOP, "speed_m_s = 0.0\n", "wind"),
    (MAP, LOOP + 'gain = "fast"\n', "speed_m_s = 3.0\n", "loop.gain"),
    # "optimise" tries each gain on the first gain_steps frames of a run: no more than the map's steps
    (MAP + "steps = 4\n", LOOP.replace("steps = 4", "steps = 10") + 'gain = "optimise"\ngain_steps = 8\n',
     "speed_m_s = 3.0\n", "loop.gain_steps"),
    (MAP, LOOP.replace('"ideal", ', ""), "speed_m_s = 3.0\n", "loop.methods"),
    (MAP, LOOP + "rate_hz = nan\n", "speed_m_s = 3.0\n", "loop.rate_hz"),
])
def test_bad_map_recipes_are_one_line_and_write_nothing(map_, loop, wind, match, tmp_path, capsys):
    rec = _recipe(tmp_path, map_, loop, wind)
    rc, _, err = run_main(["loop-map", rec, "-o", tmp_path / "out"], capsys)
    assert rc == 2 and len(err) == 1 and match in err[0], err
    assert not (tmp_path / "out").exists() and not (tmp_path / "out.partial").exists()


def test_bad_map_options_are_refused(tmp_path, capsys):
    rec = _recipe(tmp_path)
    rc, _, err = run_main(["loop-map", rec, "-o", tmp_path / "out", "-j", "0"], capsys)
    assert rc == 2 and "--workers" in err[-1]
    rc, _, err = run_main(["loop-map", rec, "-o", tmp_path / "out", "--scheduler", "nowhere"], capsys)
    assert rc == 2 and len(err) == 1 and "--scheduler" in err[0], err
    rc, _, err = run_main(["loop-map", tmp_path / "none.toml", "-o", tmp_path / "out"], capsys)
    assert rc == 2 and len(err) == 1, err
    assert not (tmp_path / "out").exists()


def test_the_committed_map_recipe_loads_with_its_verdict_point_on_its_grid(tmp_path):
    """sensing/loop-map.toml (its real-time model replaced by the linear reconstructor while the model is not
    there): 3 rates x 3 f_G x 2 Rytov numbers, the verdict's point on the grid, 77 runs."""
    from metadesign.studies.loop_map import _plan, load_map_recipe

    path = REPO / "sensing" / "loop-map.toml"
    if not (REPO / "sensing" / "models" / "realtime-modal100.safetensors").exists():
        text = path.read_text().replace('realtime = "models/realtime-modal100.safetensors"\n', "")
        text = text.replace('"realtime", "open"]', '"linear", "open"]')
        for rel in ("../layouts/paper-5mm.toml", "paper.toml", "turbulence.toml"):
            text = text.replace(f'"{rel}"', f'"{(REPO / "sensing" / rel).resolve()}"')
        path = tmp_path / "loop-map.toml"
        path.write_text(text)
    m = load_map_recipe(path)
    assert (m.rates_hz, m.greenwood_hz, m.rytov) == ((1000.0, 2000.0, 4000.0), (50.0, 100.0, 200.0), (0.3, 0.5))
    cells, scan, runs = _plan(m)
    assert m.verdict == (0.5, 100.0, 2000.0) and any(c[3] == (0.5, 100.0, 2000.0, None) for c in cells)
    assert len(cells) == 18 and len(scan) == 5 and len(runs) == 18 * 4 + 5
    for (r, g), s in m.scenes.items():
        assert s["greenwood_hz"] == pytest.approx(g, rel=1e-9)


#: an optimised map: 2 rates x 1 f_G x 1 Rytov, the ideal and Shack-Hartmann loops' gains chosen at each point
#: (the Shack-Hartmann's latency declared: the numbers do not depend on this machine's timing), the verdict's
#: point on the grid
OPT_MAP = ("rates_hz = [1000, 4000]\ngreenwood_hz = [200]\nrytov = [0.5]\nverdict_greenwood_hz = 200.0\n"
           "verdict_rate_hz = 1000.0\n")
OPT_LOOP = ('methods = ["ideal", "shack_hartmann", "open"]\nsteps = 3\nsubsteps = 1\ngain = "optimise"\n'
            'gain_steps = 3\nlatency_ms = {shack_hartmann = 0.1}\n')


@pytest.fixture(scope="module")
def optimised(tmp_path_factory):
    """The optimised map on one worker (the reference of the next two tests)."""
    base = tmp_path_factory.mktemp("loop-map-opt")
    rec = _recipe(base, OPT_MAP, OPT_LOOP)
    rc, err = _main(["loop-map", rec, "-o", base / "j1", "-j", "1", "--json"])
    assert rc == 0, err
    return rec, base / "j1"


def _loop_at(folder: Path, rep: dict, rytov: float, greenwood: float, rate: float, loop: str) -> dict:
    """``metadesign loop`` on the recipe of one map point (its rate, Rytov number and scaled wind): loop.json."""
    scene = next(s for s in rep["greenwood"]["scenes"]
                 if s["rytov"] == rytov and s["greenwood_hz"] == pytest.approx(greenwood, rel=1e-9))
    folder.mkdir()
    rec = _recipe(folder, None, loop + f"rate_hz = {rate!r}\nrytov = {rytov!r}\n",
                  wind=f"speed_m_s = {scene['wind']['speed_m_s']!r}\n")
    rc, err = _main(["loop", rec, "-o", folder / "out"])
    assert rc == 0, err
    return json.loads((folder / "out" / "loop.json").read_text())


def test_optimise_chooses_each_points_gain_by_the_loop_studys_search(optimised, tmp_path):
    """Each closed loop's gain at each point is the loop study's choice at that point: ``metadesign loop`` on
    the 4 kHz point's recipe (its rate and scaled wind, gain = "optimise") tries the same gains with the same
    mean NPiB and picks the same gain, and its runs at that gain are the map's; the 1 kHz point's search
    differs (a search per point, not one gain everywhere); the oracles carry none; map.json records the rule."""
    from metadesign.studies.loop_study import GAIN_GRID, GAIN_REFINE

    _, j1 = optimised
    rep = json.loads((j1 / "map.json").read_text())
    g = rep["gain"]
    assert (g["rule"], g["grid"], g["refine"], g["steps"]) == ("optimise", list(GAIN_GRID), list(GAIN_REFINE), 3)
    search = {(s["rate_hz"], s["method"]): s for s in g["searches"]}
    assert sorted(search) == [(1000.0, "ideal"), (1000.0, "shack_hartmann"), (4000.0, "ideal"),
                              (4000.0, "shack_hartmann")]
    for p in rep["points"]:
        for m in ("ideal", "shack_hartmann"):
            s = search[(p["rate_hz"], m)]
            assert p["methods"][m]["gain"] == s["gain"] and s["gain"] in s["gains"]
            assert set(GAIN_GRID) <= set(s["gains"]) and len(s["gains"]) > len(GAIN_GRID)  # grid, then refined
        assert p["methods"]["open"]["gain"] is None
    assert rep["verdict"]["methods"]["ideal"]["gain"] == search[(1000.0, "ideal")]["gain"]
    study = _loop_at(tmp_path / "study", rep, 0.5, 200.0, 4000.0, OPT_LOOP)
    point = rep["points"][1]
    assert point["rate_hz"] == 4000.0
    for m in ("ideal", "shack_hartmann"):
        mine, theirs = search[(4000.0, m)], study["methods"][m]["gain_search"]
        assert mine["gains"] == theirs["gains"] and mine["gain"] == theirs["gain"] == study["methods"][m]["gain"]
        assert mine["npib_mean"] == pytest.approx(theirs["npib_mean"], rel=1e-12, abs=1e-12)
        assert point["methods"][m]["npib_mean"] == pytest.approx(study["methods"][m]["npib_mean"], rel=1e-12)
        other = search[(1000.0, m)]
        assert other["npib_mean"][:len(GAIN_GRID)] != mine["npib_mean"][:len(GAIN_GRID)]


def test_an_optimised_map_resumes_on_two_workers_to_the_same_bytes(optimised, tmp_path, capsys, monkeypatch):
    """Killed in the middle of the gain search (20 of its 36 grid trials done, one worker), then resumed on
    two workers: the same map.json numbers and map.png bytes as one worker from scratch."""
    import functools

    from metadesign.execution import Execution
    from metadesign.studies import cli_loop_map

    rec, j1 = optimised
    monkeypatch.setattr(cli_loop_map, "Execution", functools.partial(Execution, stop_after=20), raising=False)
    rc, _, err = run_main(["loop-map", rec, "-o", tmp_path / "k", "-j", "1", "--json"], capsys)
    assert rc == 130 and "interrupted" in err[-1], err
    assert len(list((tmp_path / "k.partial").glob("gain-*.npz"))) == 20
    monkeypatch.setattr(cli_loop_map, "Execution", Execution, raising=False)
    rc, out, err = run_main(["loop-map", rec, "-o", tmp_path / "k", "-j", "2"], capsys)
    assert rc == 0, err
    assert any("resuming: 20/36 tasks" in e for e in err), err
    assert "gains (optimised per point" in out and "gain 0.4" not in out
    assert _numbers(tmp_path / "k") == _numbers(j1)
    assert (tmp_path / "k" / "map.png").read_bytes() == (j1 / "map.png").read_bytes()
    assert not (tmp_path / "k.partial").exists()


def test_auto_lenslets_follow_each_rytov_numbers_r0(tmp_path):
    """``sh_lenslets = "auto"`` on a map over Rytov 0.3 and 0.5: each point's count is ``ceil(D / r0)`` with
    r0 the closed-form spherical-wave Fried parameter of a uniform-Cn2 path at that Rytov number
    (``sigma_chi^2 = 0.563 k^(7/6) Cn2 L^(11/6) B(11/6, 11/6)``, ``r0 = (0.423 k^2 Cn2 3 L / 8)^(-3/5)``):
    4 and 5 lenslets; and the Rytov 0.5 point's Shack-Hartmann loop is the loop study's at that point with 5
    lenslets given (not the first Rytov number's 4)."""
    from scipy.special import beta

    from metadesign.turbulence.scenario import load_scenario

    loop = ('methods = ["ideal", "shack_hartmann", "open"]\nsteps = 3\nsubsteps = 1\nsh_lenslets = "auto"\n'
            'latency_ms = {shack_hartmann = 0.1}\n')
    rec = _recipe(tmp_path, "rates_hz = [1000]\ngreenwood_hz = [200]\nrytov = [0.3, 0.5]\nverdict_rytov = 0.3\n"
                  "verdict_greenwood_hz = 200.0\nverdict_rate_hz = 1000.0\n", loop)
    rc, err = _main(["loop-map", rec, "-o", tmp_path / "out", "--json"])
    assert rc == 0, err
    rep = json.loads((tmp_path / "out" / "map.json").read_text())
    sc = load_scenario(REPO / "sensing" / "turbulence.toml")
    D, L, k = sc.receiver_aperture, sc.length, 2 * np.pi / sc.wavelength
    counts = {}
    for p in rep["points"]:
        cn2 = p["rytov"] / (0.563 * k ** (7 / 6) * L ** (11 / 6) * beta(11 / 6, 11 / 6))
        r0 = (0.423 * k * k * cn2 * 3 * L / 8) ** (-3 / 5)
        sh = p["shack_hartmann"]
        assert sh["rule"] == "auto" and sh["lenslets"] == int(np.ceil(D / r0)) and sh["d_over_r0"] <= 1.0
        assert sh["r0_m"] == pytest.approx(r0, rel=0.015)
        counts[p["rytov"]] = sh["lenslets"]
    assert counts == {0.3: 4, 0.5: 5}
    assert [(s["rytov"], s["lenslets"]) for s in rep["shack_hartmann"]] == [(0.3, 4), (0.5, 5)]
    study = _loop_at(tmp_path / "study", rep, 0.5, 200.0, 1000.0, loop.replace('"auto"', "5"))
    assert study["shack_hartmann"]["lenslets"] == 5
    point = next(p for p in rep["points"] if p["rytov"] == 0.5)["methods"]["shack_hartmann"]
    assert point["npib_mean"] == pytest.approx(study["methods"]["shack_hartmann"]["npib_mean"], rel=1e-12)


def test_a_gain_table_gives_some_loops_their_gain_and_searches_the_others_per_point(optimised, tmp_path):
    """``gain = { ideal = "optimise", shack_hartmann = 0.3 }``: the ideal loop's gain searched at each point as
    the all-optimised map searches it (the same trials), the Shack-Hartmann at 0.3 at every point and never
    searched; map.json records the given gain."""
    _, j1 = optimised
    ref = json.loads((j1 / "map.json").read_text())
    rec = _recipe(tmp_path, OPT_MAP, OPT_LOOP.replace('gain = "optimise"',
                                                      'gain = { ideal = "optimise", shack_hartmann = 0.3 }'))
    rc, err = _main(["loop-map", rec, "-o", tmp_path / "out", "-j", "1", "--json"])
    assert rc == 0, err
    rep = json.loads((tmp_path / "out" / "map.json").read_text())
    assert rep["gain"]["rule"] == "optimise" and rep["gain"]["given"] == {"shack_hartmann": 0.3}
    mine = {(s["rate_hz"], s["method"]): s for s in rep["gain"]["searches"]}
    theirs = {(s["rate_hz"], s["method"]): s for s in ref["gain"]["searches"]}
    assert sorted(mine) == [(1000.0, "ideal"), (4000.0, "ideal")]
    for k, s in mine.items():
        assert s["gains"] == theirs[k]["gains"] and s["npib_mean"] == theirs[k]["npib_mean"]
    for p, q in zip(rep["points"], ref["points"]):
        assert p["methods"]["shack_hartmann"]["gain"] == 0.3
        assert p["methods"]["ideal"]["gain"] == q["methods"]["ideal"]["gain"]
        assert p["methods"]["ideal"]["npib_mean"] == q["methods"]["ideal"]["npib_mean"]
