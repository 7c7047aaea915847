"""Command-line options shared by the commands that run a tracker (serve, track, study).

The tracker's flags are generated from the fields of
:class:`~formtwin.tracker.TrackerConfig` (:mod:`formtwin._config`); ``--config FILE.toml``
reads its ``[tracker]`` table; flags given on the command line win over the file.
"""

from __future__ import annotations

import argparse
from collections.abc import Mapping
from typing import Any

from formtwin._config import add_arguments, resolve
from formtwin.tracker import TrackerConfig


def add_tracker_options(p: argparse.ArgumentParser, exclude: tuple[str, ...] = ()) -> None:
    """``--config`` and one flag per :class:`TrackerConfig` field (except ``exclude``)."""
    p.add_argument("--config", metavar="FILE.toml",
                   help="settings file; its [tracker] table sets the tracker (flags win)")
    group = p.add_argument_group("tracker", "settings of the particle-filter tracker "
                                 "(TrackerConfig; also the [tracker] table of --config)")
    add_arguments(group, TrackerConfig, exclude=exclude)


def tracker_config(args: argparse.Namespace, base: Mapping[str, Any] | None = None
                   ) -> TrackerConfig:
    """The :class:`TrackerConfig` of defaults < ``base`` < ``--config`` < flags; given the
    line's means (``mu``), ``mu_known`` defaults to True (``--no-mu-known``: a guess)."""
    config = resolve(TrackerConfig, args, getattr(args, "config", None), "tracker", base)
    if config.mu is None or config.mu_known:
        return config
    known = {**(base or {}), "mu_known": True}
    return resolve(TrackerConfig, args, getattr(args, "config", None), "tracker", known)
