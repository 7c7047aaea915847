"""Command-line options shared by the commands that run a tracker (serve, track, study).

The tracker's flags are generated from the fields of
:class:`~formtwin.tracker.TrackerConfig` (:mod:`formtwin._config`); ``--config FILE.toml``
reads its ``[tracker]`` table; flags given on the command line win over the file.
"""

from __future__ import annotations

import argparse
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from formtwin._config import add_arguments, resolve
from formtwin.tracker import TrackerConfig


def add_tracker_options(p: argparse.ArgumentParser, exclude: tuple[str, ...] = ()) -> None:
    """``--config`` and one flag per :class:`TrackerConfig` field (except ``exclude``)."""
    p.add_argument("--config", metavar="FILE.toml",
                   help="settings file; its [tracker] table sets the tracker (flags win)")
    group = p.add_argument_group("tracker", "settings of the particle-filter tracker "
                                 "(TrackerConfig; also the [tracker] table of --config)")
    add_arguments(group, TrackerConfig, exclude=exclude)


def spec_defaults(spec: Any) -> dict[str, Any]:
    """Tracker settings a spec sets: the force sensor's std (``[curve] noise_sd``, N)."""
    noise = float(getattr(spec, "noise_sd", 0.0))
    return {"sensor_noise": noise} if noise > 0 else {}


def noise_note(config: TrackerConfig, spec: Any) -> str:
    """Why a poor fit may be the sensor noise's fault: the noise in use and where it came
    from (the spec's ``[curve] noise_sd``, a flag, or the default 0)."""
    given = float(getattr(spec, "noise_sd", 0.0))
    src = ("the spec's [curve] noise_sd" if given > 0 and config.sensor_noise == given
           else "the default: no noise_sd in the spec's [curve]"
           if given == 0 and config.sensor_noise == 0 else "--sensor-noise / --config")
    return (f"sensor noise in use: {config.sensor_noise:g} N ({src}). A sensor noise below "
            "the real sensor's makes every curve look like a model mismatch: set [curve] "
            "noise_sd in the spec or pass --sensor-noise with the sensor's std.")


def tracker_config(args: argparse.Namespace, base: Mapping[str, Any] | None = None
                   ) -> TrackerConfig:
    """The :class:`TrackerConfig` of defaults < ``base`` < ``--config`` < flags; given the
    line's means (``mu``), ``mu_known`` defaults to True (``--no-mu-known``: a guess)."""
    config = resolve(TrackerConfig, args, getattr(args, "config", None), "tracker", base)
    if config.mu is None or config.mu_known:
        return config
    known = {**(base or {}), "mu_known": True}
    return resolve(TrackerConfig, args, getattr(args, "config", None), "tracker", known)


def model_spec(args: argparse.Namespace) -> Any:
    """The spec a command on ``--metamodel`` (or ``--analytic``) will run, read from the
    metamodel file without loading its models (the analytic stand-in: the demonstrator)."""
    from formtwin.spec import load_spec, parse_spec

    if args.analytic or not args.metamodel or Path(args.metamodel).is_dir():
        return load_spec()
    try:
        with np.load(args.metamodel, allow_pickle=False) as z:
            return parse_spec(str(z["spec_text"]), str(args.metamodel))
    except (OSError, ValueError, KeyError):
        return load_spec()  # the processor reports the file's problem when it loads it
