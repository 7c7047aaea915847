"""The CalculiX model: deck pieces against closed forms; ccx runs (skipped without ccx)."""

from __future__ import annotations

import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from formtwin.physics.bending import FlapGeometry, Material
from formtwin.physics.calculix import CalculixModel, FeSettings
from formtwin.physics.calculix.deck import ram_height, rate_factor
from formtwin.physics.calculix.mesh import sample_tool, sheet_mesh, tool_mesh
from formtwin.physics.calculix.model import run_ccx
from formtwin.physics.calculix.results import chord_angle, read_dat

needs_ccx = pytest.mark.skipif(shutil.which("ccx") is None, reason="CalculiX (ccx) not "
                               "installed: apt-get install calculix-ccx, or `make fe-deps`")


def _area(xy: np.ndarray) -> float:
    x, y = xy[:, 0], xy[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def test_ram_height_is_the_bending_models_crank() -> None:
    from formtwin.physics.bending.solver import crank

    g = FlapGeometry()
    t = np.linspace(-0.08, 0.07, 31)
    c, v = ram_height(t, g)
    press = np.array([0.0, 0.0, 1.0, 0.5 * g.stroke, g.rod, g.omega, 0.0])
    ref = np.array([crank(ti, press) for ti in t])
    np.testing.assert_allclose(c, ref[:, 0], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(v, ref[:, 1], rtol=1e-12, atol=1e-9)
    assert ram_height(np.array([0.0]), g)[0][0] == 0.0  # bottom dead centre


def test_sheet_mesh_counts_orientation_and_mid_line() -> None:
    m = sheet_mesh(-0.6, 2.0, 0.3, 13, 4)
    assert m.elements.shape == (52, 8)
    assert m.node_ids.size == 27 * 9 - 13 * 4  # no element centres
    for conn in m.elements:
        corners = m.nodes[np.searchsorted(m.node_ids, conn[:4])]
        assert _area(corners) == pytest.approx(0.2 * 0.075)  # counter-clockwise, 0.2 x 0.075
    mid = m.nodes[np.searchsorted(m.node_ids, m.mid)]
    np.testing.assert_allclose(mid[:, 1], 0.15)
    assert [f[1] for f in m.faces("bottom")] == [1] * 13
    assert m.element_x(1) == pytest.approx(-0.5)
    with pytest.raises(ValueError, match="unknown side"):
        m.faces("left")


def test_tools_are_counter_clockwise_rows_on_their_working_side() -> None:
    g = FlapGeometry()
    for pts, radii in (g.die1()[0], g.punch1(0.36, 0.0, 0.0)[0]):
        surf = sample_tool(pts, radii, 0.05, 4.0, 1.0, 1.0)
        tm = tool_mesh("T", surf, 0.05, 1, 1)
        for conn in tm.elements:
            assert _area(tm.nodes[conn - 1]) > 0.0
    die = sample_tool(*g.die1()[0], 0.05, 4.0, 1.5, 3.5)
    assert die[:, 1].max() == pytest.approx(0.0)  # the die top is the sheet's lower surface
    r = np.hypot(die[:, 0], die[:, 1] + g.r_die)
    on_arc = (die[:, 0] > 1e-9) & (die[:, 0] < g.r_die * math.sin(math.pi / 4) - 1e-9)
    np.testing.assert_allclose(r[on_arc], g.r_die, rtol=1e-12)


def test_rate_factor_is_cowper_symonds_of_the_ram_speed() -> None:
    g = FlapGeometry()
    t = np.linspace(-0.08, 0.0, 81)
    mat = Material(log_rate=2.0, rate_exponent=0.5)
    s = FeSettings(rate_per_speed=0.2, rate_window=0.0)
    _, v = ram_height(t, g)
    np.testing.assert_allclose(rate_factor(t, g, mat, s), 1 + (0.2 * np.abs(v) / 100) ** 0.5)
    assert np.all(rate_factor(t, g, Material(rate=False), s) == 1.0)
    smooth = rate_factor(t, g, mat, FeSettings(rate_per_speed=0.2))
    assert smooth[-1] > rate_factor(t, g, mat, s)[-1]  # lags the slowing ram


def test_read_dat_and_chord_angle(tmp_path: Path) -> None:
    text = ("\n forces (fx,fy,fz) for set NRAM and time  0.1000000E-02\n\n"
            "       7  0.000000E+00 -1.500000E+00  0.000000E+00\n\n"
            " total force (fx,fy,fz) for set NPUNCH and time  0.1000000E-02\n\n"
            "        2.0E+00 -3.0E+00  0.0E+00\n\n"
            " forces (fx,fy,fz) for set NRAM and time  0.2000000E-02\n\n"
            "       7  0.000000E+00 -2.500000E+00  0.000000E+00\n")
    (tmp_path / "a.dat").write_text(text)
    tab = read_dat(tmp_path / "a.dat")
    np.testing.assert_allclose(tab[("forces", "NRAM")].times, [1e-3, 2e-3])
    np.testing.assert_allclose(tab[("forces", "NRAM")].values[:, 0, 1], [-1.5, -2.5])
    assert tab[("forces", "NRAM")].ids.tolist() == [7]
    np.testing.assert_allclose(tab[("total force", "NPUNCH")].values[0, 0], [2.0, -3.0, 0.0])
    s = np.linspace(0.0, 1.0, 11)
    line = np.column_stack([s * math.cos(0.3), -s * math.sin(0.3)])
    assert chord_angle(line, s, 0.5) == pytest.approx(math.degrees(0.3))


def test_missing_ccx_is_a_failure_record_not_an_exception() -> None:
    model = CalculixModel(ccx="no-such-ccx-here")
    r = model.run(model.centre())
    assert not r.ok and "not found" in r.reason and np.isnan(r.curve).all()
    with pytest.raises(ValueError, match="expected shape"):
        model.run(np.zeros(3))
    with pytest.raises(ValueError, match="even"):
        CalculixModel(n_thick=3)


def test_deck_has_both_stages_and_compact_ids() -> None:
    model = CalculixModel(n_thick=2)
    deck = model.deck(model.centre())
    assert deck.text.count("*STEP") == 3 and deck.stage2
    assert [tm.name for tm in deck.tools] == ["DIE", "DIEF1", "PUNCH", "DIEF2", "PUNCH2"]
    ids = np.concatenate([deck.sheet.node_ids] + [tm.node_ids for tm in deck.tools])
    assert np.unique(ids).size == ids.size and ids.max() < 1.2 * ids.size  # no big ids
    die, face1, face2 = deck.tools[0].nodes, deck.tools[1].nodes, deck.tools[3].nodes
    np.testing.assert_allclose(die[die.shape[0] // 2 - 1], face1[0])  # the arc's end joins
    np.testing.assert_allclose(face1[0], face2[0])
    assert np.all(face2[: face2.shape[0] // 2, 0] <= FlapGeometry().r_die + 1e-9)
    x = model.centre()
    if x.size == 11:  # the spec's stage-2 depth u lowers the stage-2 punch
        x[-1] += 0.1
        low = model.deck(x).tools[4].nodes[:, 1].min()
        assert low == pytest.approx(deck.tools[4].nodes[:, 1].min() - 0.1)
    one = CalculixModel(n_thick=2, stage2=False).deck(model.centre())
    assert one.text.count("*STEP") == 1 and "stage 1 only" in CalculixModel(
        stage2=False).version


@needs_ccx
def test_ccx_plane_strain_cantilever_matches_beam_theory(tmp_path: Path) -> None:
    """CPE8R cantilever (L = 10, t = 0.5, 1 mm section), tip load P: Timoshenko deflection
    ``P L^3 / (3 E' I) + P L / (kappa G A)`` with plane-strain ``E' = E / (1 - nu^2)``."""
    E, nu, L, t, P = 200_000.0, 0.3, 10.0, 0.5, 0.01
    m = sheet_mesh(0.0, L, t, 40, 2)
    tip = m.node_ids[np.abs(m.nodes[:, 0] - L) < 1e-9]
    lines = ["*NODE, NSET=NALL"] + [f"{i}, {x:.12g}, {y:.12g}" for i, (x, y) in
                                    zip(m.node_ids, m.nodes, strict=True)]
    lines += ["*ELEMENT, TYPE=CPE8R, ELSET=E"] + [
        f"{k + 1}, " + ", ".join(map(str, c)) for k, c in enumerate(m.elements)]
    lines += ["*MATERIAL, NAME=M", "*ELASTIC", f"{E!r}, {nu!r}",
              "*SOLID SECTION, ELSET=E, MATERIAL=M", "1.", "*BOUNDARY"]
    lines += [f"{n}, 1, 2" for n in m.root]
    lines += ["*STEP", "*STATIC", "*CLOAD"] + [f"{n}, 2, {-P / tip.size!r}" for n in tip]
    lines += ["*NODE PRINT, NSET=NALL", "U", "*END STEP"]
    text = "\n".join(lines) + "\n"
    tab = read_dat(run_ccx(text, tmp_path))[("displacements", "NALL")]
    mid_tip = int(m.mid[-1])
    w = -tab.values[-1, list(tab.ids).index(mid_tip), 1]
    Ep, inertia, G = E / (1 - nu**2), t**3 / 12, E / (2 * (1 + nu))
    ref = P * L**3 / (3 * Ep * inertia) + P * L / (5 / 6 * G * t)
    assert w == pytest.approx(ref, rel=0.01)


@needs_ccx
def test_coarse_two_stage_run_is_flap_bending(spec) -> None:  # type: ignore[no-untyped-def]
    # 2 elements through the thickness, each 3 thicknesses long (the default mesh has 4, 1.5
    # long): two-thirds of the ccx time of a 1.5-long mesh, the same flap bending (angles
    # 46.2 and 74.7 deg, plateau above 75 N, measured with ccx 2.20)
    model = CalculixModel(spec, n_thick=2, aspect=3.0)
    r = model.run(model.centre())
    assert r.ok, r.reason
    t = spec.time
    c = r.curve
    assert np.all(np.abs(c[t < -0.06]) < 1e-6)  # the punch is above the flap
    assert np.all(c[(t > -0.05) & (t < -0.01)] > 40.0)  # bending plateau, N over 10 mm
    peak_t = t[int(np.argmax(c))]
    assert -0.006 <= peak_t <= 0.002 and c.max() > 2 * c[50]  # setting near BDC
    assert np.all(np.abs(c[t > 0.012]) < 1.0)  # released
    assert 40.0 < r.angles[0] < 50.0  # 45 deg die face, springback
    # stroke-controlled stage 2 (geometry of bending-2.0): the nose stops on the flap
    assert 68.0 < r.angles[1] < 78.0
    assert r.info["seconds"] > 0 and "ccx-" in model.version


def test_model_pickles_for_process_pools_and_dask() -> None:
    import pickle

    model = CalculixModel(n_thick=2, stage2=False, timeout=60.0)
    clone = pickle.loads(pickle.dumps(model))
    x = model.centre()
    assert clone.version == model.version and clone.settings == model.settings
    assert clone.deck(x).text == model.deck(x).text
