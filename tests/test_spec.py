"""Process spec: the bundled Table 1, unit conversion and named errors for bad files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from formtwin.cli import main
from formtwin.cli.spec import format_table
from formtwin.spec import SpecError, load_spec, parse_spec

BUNDLED = (Path(__file__).parents[1] / "src/formtwin/specs/demonstrator.toml").read_text()


def test_table1_values_in_internal_units() -> None:
    spec = load_spec()
    assert spec.state.names == ("yield_stress", "log_rate", "rate_exponent", "thickness",
                                "friction_tool_tool", "friction_tool_flap",
                                "punch_end_distance")
    assert spec.params.names == ("horizontal_alignment", "vertical_alignment", "press_stiffness")
    ys = spec.state["yield_stress"]
    assert (ys.lo, ys.hi, ys.mu_min, ys.mu_max, ys.sigma, ys.rho) == (275, 336, 291, 321, 6, 0.8)
    t = spec.state["thickness"]  # um -> mm
    assert t.lo == pytest.approx(0.295) and t.sigma == pytest.approx(0.001) and t.rho == 0.7
    # the row of Table 1 that lost a cell, read as DESIGN.md says
    lr = spec.state["log_rate"]
    assert (lr.lo, lr.hi, lr.mu_min, lr.mu_max, lr.sigma, lr.rho) == (1.5, 2.9, 2.0, 2.4, 0.05, 0.8)
    assert "lost a cell" in lr.note
    assert spec.params["press_stiffness"].lo == 5000.0  # kN/mm -> N/mm
    assert spec.params["vertical_alignment"].lo == pytest.approx(-0.020)
    np.testing.assert_allclose(spec.deviation.group.lo, -0.2)
    np.testing.assert_allclose(spec.deviation.knots * 1e3, [-80, -80 + 100 / 3, -80 + 200 / 3, 20])
    assert spec.n_t == 101 and spec.dt == pytest.approx(1e-3)
    assert len(spec.augmented) == 18
    assert spec.augmented.index["speed_scaling_4"] == 17
    np.testing.assert_allclose(spec.state.mu_mid, [306, 2.2, 0.8, 0.3, 0.25, 0.15, 0.36])


def test_spec_show_prints_all_of_table1(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["spec", "show"]) == 0
    out = capsys.readouterr().out
    for name in load_spec().augmented.names:
        assert name in out
    assert "336" in out and "kN/mm" in out and "lost a cell" in out
    assert format_table(load_spec()).count("\n") > 20


def test_unknown_variable_is_a_clear_key_error() -> None:
    with pytest.raises(KeyError, match="no variable 'yield'"):
        load_spec().state["yield"]


MALFORMED = [
    # (what to replace, replacement, words the error must contain)
    ("min = 275.0", "min = 400.0", "max = 336.0"),
    ("sigma = 6.0", "sigma = -6.0", "sigma"),
    ("rho = 0.8\n\n[[state]]\nname = \"log_rate\"", "rho = 1.3\n\n[[state]]\nname = \"log_rate\"",
     "rho = 1.3"),
    ("mu_max = 321.0", "mu_max = 350.0", "mu_min"),
    ("mu_min = 291.0", "mu_min = 325.0", "mu_min"),
    ('unit = "MPa"', 'unit = "furlong"', "'furlong'"),
    ('name = "thickness"', 'name = "yield_stress"', "used twice"),
    ('name = "thickness"', 'name = "sheet thickness"', "identifier"),
    ("sigma = 6.0", 'sigma = "six"', "a number"),
    ("n_samples = 101", "n_samples = 2", "n_samples"),
    ("t_end = 20.0", "t_end = -90.0", "t_start"),
    ("knots = 4", "knots = 1", "knots"),
    ("force_scaling_min = -20.0", "force_scaling_min = -120.0", "-100 %"),
    ("[deviation]", "[deviations]", "deviation"),
    ('force_unit = "N"', 'force_unit = "lbf"', "force_unit"),
    ("max = 40.0", "max = nan", "finite"),
    ("rho = 0.95\n\n[[state]]\nname = \"friction_tool_flap\"",
     "rho = 0.95\ncolour = 3\n\n[[state]]\nname = \"friction_tool_flap\"", "colour"),
    ("[curve]", "[curve\n", "TOML"),
]


@pytest.mark.parametrize(("old", "new", "words"), MALFORMED)
def test_malformed_spec_names_file_field_and_value(old: str, new: str, words: str) -> None:
    assert old in BUNDLED, old
    with pytest.raises(SpecError) as info:
        parse_spec(BUNDLED.replace(old, new, 1), source="bad.toml")
    message = str(info.value)
    assert message.startswith("bad.toml"), message
    assert words in message, message


def test_missing_field_and_missing_file(tmp_path: Path) -> None:
    with pytest.raises(SpecError, match=r"state\[0\] 'yield_stress'.rho is missing"):
        parse_spec(BUNDLED.replace("rho = 0.8\n", "", 1), source="x.toml")
    with pytest.raises(SpecError, match="cannot read"):
        load_spec(tmp_path / "nope.toml")
    good = tmp_path / "good.toml"
    good.write_text(BUNDLED)
    assert load_spec(good).source == str(good)
