"""One TrackerConfig: flags generated from its fields, its [tracker] TOML table, JSON."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import pytest

from formtwin.cli.options import add_tracker_options, tracker_config
from formtwin.tracker import TrackerConfig


def parse(argv: list[str], exclude: tuple[str, ...] = ()) -> argparse.Namespace:
    p = argparse.ArgumentParser()
    add_tracker_options(p, exclude=exclude)
    return p.parse_args(argv)


def test_every_field_has_a_flag_and_defaults_stay_defaults() -> None:
    assert tracker_config(parse([])) == TrackerConfig()
    cfg = tracker_config(parse(["--n-particles", "64", "--no-estimate-deviation",
                                "--mu", "1,2,3,4,5,6,7", "--nu", "5", "--filter", "sir",
                                "--angle-particles", "32", "--learn-mu"]))
    assert cfg == TrackerConfig(n_particles=64, estimate_deviation=False,
                                mu=(1, 2, 3, 4, 5, 6, 7), nu=5.0, angle_particles=32,
                                learn_mu=True, mu_known=True)
    # the older spellings still work
    assert tracker_config(parse(["--particles", "7", "--no-deviation", "--robust-nu", "3"])
                          ) == TrackerConfig(n_particles=7, estimate_deviation=False, nu=3.0)
    with pytest.raises(SystemExit):
        parse(["--seed", "3"], exclude=("seed",))


def test_given_means_are_the_lines_unless_said() -> None:
    """``--mu`` gives the line's means: mu_known (no assumed-mu term in the intervals);
    ``--no-mu-known`` makes them a guess; without ``--mu`` the mid-range is assumed."""
    mu = ["--mu", "1,2,3,4,5,6,7"]
    assert tracker_config(parse(mu)).mu_known
    assert not tracker_config(parse([*mu, "--no-mu-known"])).mu_known
    assert not tracker_config(parse([])).mu_known


def test_toml_table_then_flags(tmp_path: Path) -> None:
    f = tmp_path / "line1.toml"
    f.write_text("[tracker]\nn_particles = 300\nalpha = 0.02\nmu = [1, 2, 3, 4, 5, 6, 7]\n"
                 "nu = inf\n[other]\nx = 1\n")
    cfg = tracker_config(parse(["--config", str(f), "--alpha", "0.05"]))
    assert cfg == TrackerConfig(n_particles=300, alpha=0.05, mu=(1, 2, 3, 4, 5, 6, 7),
                                mu_known=True)
    f.write_text("[tracker]\nparticles = 3\n")
    with pytest.raises(ValueError, match=r"unknown setting\(s\) particles; known: n_particles"):
        tracker_config(parse(["--config", str(f)]))
    with pytest.raises(ValueError, match="n_particles = 0"):
        tracker_config(parse(["--n-particles", "0"]))


def test_json_round_trip_keeps_inf_and_tuples() -> None:
    cfg = TrackerConfig(mu=(1.0,) * 7, nu=math.inf, angle_particles=5)
    assert TrackerConfig.from_json(cfg.to_json()) == cfg
    assert '"nu": null' in cfg.to_json()
    assert TrackerConfig.from_json('{"n_particles": 10}') == TrackerConfig(n_particles=10)


@pytest.mark.parametrize(("trim", "learn"), [(0.1, True), (0.0, False)])
def test_an_older_configs_sensor_trim_becomes_camera_discrepancy(trim: float,
                                                                 learn: bool) -> None:
    cfg = TrackerConfig.from_dict({"n_particles": 10, "sensor_trim": trim})
    assert cfg == TrackerConfig(n_particles=10, camera_discrepancy=learn)
