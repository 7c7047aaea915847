"""The line's sensors in the process spec (formtwin.spec.sensors): the demonstrator's gauge
and camera in internal units, named errors for bad entries, the settings flag, and the
pseudo-data's sensor readings on their own random stream."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pytest

from formtwin._config import add_arguments, resolve
from formtwin.production import draw_production_run
from formtwin.spec import SpecError, load_spec, parse_spec
from formtwin.spec.sensors import line_sensors, output_column
from formtwin.study.pseudodata import Realisation
from formtwin.study.sensor_data import sensor_noise, sensor_readings
from formtwin.tracker import TrackerConfig

BUNDLED = (Path(__file__).parents[1] / "src/formtwin/specs/demonstrator.toml").read_text()
CAMERA = 'name = "camera"\nlabel = "final-angle camera"\nmeasures = "angle_stage2"\n' \
         'unit = "deg"\nnoise = 0.2\ndelay = 1'


def test_demonstrator_sensors_in_internal_units() -> None:
    spec = load_spec()
    gauge, camera = spec.sensor("gauge"), spec.sensor("camera")
    assert (gauge.kind, gauge.measures, gauge.delay) == ("state", "thickness", 0)
    assert gauge.noise == pytest.approx(0.5e-3)  # 0.5 um in mm, the thickness's unit
    assert (camera.kind, camera.measures, camera.delay, camera.noise) == (
        "output", "angle_stage2", 1, 0.2)
    assert output_column(spec, "angle_stage2") == 1
    with pytest.raises(KeyError, match="no sensor 'laser'.*gauge, camera"):
        spec.sensor("laser")


@pytest.mark.parametrize(("old", "new", "words"), [
    ('measures = "angle_stage2"', 'measures = "angle_3"', "measures = 'angle_3'"),
    ('measures = "angle_stage2"', 'measures = "thick"', "a state variable"),
    ("noise = 0.2", "noise = -0.2", "noise = -0.2"),
    ("delay = 1", "delay = 1.5", "delay = 1.5"),
    ("delay = 1", "delay = -1", "whole number of products"),
    ('unit = "deg"\nnoise = 0.2', 'unit = "rad"\nnoise = 0.2', "unit = 'rad'"),
    ('name = "camera"', 'name = "gauge"', "used twice"),
    ("delay = 1", "delay = 1\ncolour = 3", "colour"),
])
def test_bad_sensor_entries_are_named(old: str, new: str, words: str) -> None:
    assert CAMERA in BUNDLED
    text = BUNDLED.replace(CAMERA, CAMERA.replace(old, new))
    with pytest.raises(SpecError, match=words.replace("(", r"\(").replace(".", r"\.")) as e:
        parse_spec(text, source="bad.toml")
    assert "bad.toml" in str(e.value)


def test_gauge_unit_must_be_a_thickness_unit() -> None:
    text = BUNDLED.replace('measures = "thickness"\nunit = "um"',
                           'measures = "thickness"\nunit = "MPa"')
    with pytest.raises(SpecError, match="a unit of thickness"):
        parse_spec(text, source="bad.toml")


def test_a_spec_without_sensors_has_none_unless_it_is_the_demonstrator() -> None:
    bare = BUNDLED[:BUNDLED.index("[[sensor]]")]
    spec = parse_spec(bare)
    assert spec.sensors == ()
    assert [s.name for s in line_sensors(spec)] == ["gauge", "camera"]  # the bundled line
    other = parse_spec(bare.replace('name = "demonstrator"', 'name = "other"'))
    assert line_sensors(other) == ()


def test_sensors_setting_from_flags_and_toml(tmp_path: Path) -> None:
    p = argparse.ArgumentParser()
    add_arguments(p, TrackerConfig)
    assert resolve(TrackerConfig, p.parse_args(["--sensors", "gauge,camera"])).sensors == (
        "gauge", "camera")
    f = tmp_path / "c.toml"
    f.write_text('[tracker]\nsensors = ["camera"]\nsensor_lag = 2\n')
    c = resolve(TrackerConfig, p.parse_args([]), f, "tracker")
    assert (c.sensors, c.sensor_lag) == (("camera",), 2)
    with pytest.raises(ValueError, match="sensor_lag"):
        TrackerConfig(sensor_lag=-1)


def test_pseudo_data_readings_on_their_own_stream() -> None:
    """The readings are the truth plus noise of the spec's sd (sample std within 4
    standard errors over 20 000 products); the realisation's own stream is not touched
    (its draws are those of a fresh generator on the same seed); the camera's draws do
    not depend on whether the gauge is read."""
    spec = load_spec()
    n, seed = 20_000, 3
    rng = np.random.default_rng(np.random.SeedSequence([seed, 0]))
    run = draw_production_run(spec, n, rng)
    fresh = draw_production_run(spec, n, np.random.default_rng(np.random.SeedSequence([seed,
                                                                                        0])))
    angles = np.column_stack([np.full(n, 40.0), np.full(n, 88.0)])
    ok = np.ones(n, dtype=bool)
    real = Realisation(mu=run.mu, theta=run.theta, theta_d=run.theta_d, x=run.x, u=run.u,
                       index=0, curves={}, angles={"FE": angles}, ok={"FE": ok})
    before = rng.bit_generator.state
    r = sensor_readings(spec, real, "FE", seed)
    assert rng.bit_generator.state == before
    np.testing.assert_array_equal(fresh.x, run.x)
    err_g = (r["gauge"] - run.x[:, spec.state.index["thickness"]]) / 0.5e-3
    err_c = (r["camera"] - 88.0) / 0.2
    for e in (err_g, err_c):
        assert abs(e.std() - 1.0) < 4 / np.sqrt(2 * n) and abs(e.mean()) < 4 / np.sqrt(n)
    assert abs(np.corrcoef(err_g, err_c)[0, 1]) < 4 / np.sqrt(n)
    only = sensor_readings(spec, real, "FE", seed, names=["camera"], noise={"camera": 0.05})
    # the same draws: equal to the rounding of 88 deg (~1e-14) over 0.05 and 0.2
    np.testing.assert_allclose((only["camera"] - 88.0) / 0.05, err_c,
                               atol=100 * 88 * 2.0**-52 / 0.05)
    assert set(sensor_noise(spec, seed, 0, 4)) == {"gauge", "camera"}
    with pytest.raises(ValueError, match="laser"):
        sensor_readings(spec, real, "FE", seed, names=["laser"])
