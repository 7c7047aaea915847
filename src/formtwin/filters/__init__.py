"""Particle filters, generic over the state-space model; chosen by name.

:data:`FILTERS` maps a name to a filter class with the constructor signature of
:class:`SIR`; :func:`get_filter` resolves a name (or passes a class through) and lists the
known names on error. Later filters (auxiliary, regularised, ...) register here.
"""

from __future__ import annotations

from typing import Any

from formtwin.filters.guided import GuidedLinSIR, GuidedSIR
from formtwin.filters.move import ResampleMoveSIR
from formtwin.filters.regularised import RegularisedSIR
from formtwin.filters.resampling import (
    RESAMPLERS,
    Resampler,
    get_resampler,
    register_resampler,
)
from formtwin.filters.sir import SIR, StateSpaceModel, Step, log_normalise, logsumexp

#: filter name -> class (constructor ``(model, n_particles, rng, resampling, ess_threshold)``)
FILTERS: dict[str, type[SIR]] = {"sir": SIR, "regularised": RegularisedSIR,
                                  "move": ResampleMoveSIR, "guided": GuidedSIR,
                                  "guided_lin": GuidedLinSIR}


def get_filter(name: str | type[SIR]) -> type[SIR]:
    """The filter class called ``name``; raises ``ValueError`` listing the known names."""
    if isinstance(name, type):
        return name
    try:
        return FILTERS[name]
    except (KeyError, TypeError):
        raise ValueError(f"unknown filter {name!r}; known: {', '.join(sorted(FILTERS))}") \
            from None


def make_filter(name: str | type[SIR], *args: Any, **kwargs: Any) -> SIR:
    """Construct the filter called ``name`` with the given arguments."""
    return get_filter(name)(*args, **kwargs)


__all__ = ["FILTERS", "RESAMPLERS", "SIR", "GuidedLinSIR", "GuidedSIR", "RegularisedSIR",
           "ResampleMoveSIR", "Resampler", "StateSpaceModel", "Step", "get_filter", "get_resampler",
           "log_normalise", "logsumexp", "make_filter", "register_resampler"]
