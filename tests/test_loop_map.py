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
    (MAP, LOOP + 'gain = "optimise"\n', "speed_m_s = 3.0\n", "loop.gain"),
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
