"""The process definition's values: variables, groups, deviation layout and the spec.

Units: see :mod:`formtwin.spec`.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

if TYPE_CHECKING:
    from formtwin.spec.sensors import Sensor

#: unit as written in a spec -> (internal unit, factor to multiply by)
UNITS: dict[str, tuple[str, float]] = {
    "MPa": ("MPa", 1.0),
    "GPa": ("MPa", 1e3),
    "mm": ("mm", 1.0),
    "um": ("mm", 1e-3),
    "N": ("N", 1.0),
    "kN": ("N", 1e3),
    "N/mm": ("N/mm", 1.0),
    "kN/mm": ("N/mm", 1e3),
    "s": ("s", 1.0),
    "ms": ("s", 1e-3),
    "%": ("-", 1e-2),
    "-": ("-", 1.0),
    "log10(1/s)": ("log10(1/s)", 1.0),
}

DEMONSTRATOR = "demonstrator"


class SpecError(ValueError):
    """A process spec is malformed; the message names the file, the field and the value."""


@dataclass(frozen=True)
class Variable:
    """One named scalar of the process, bounds in internal units.

    ``mu_min, mu_max, sigma, rho`` are set for state variables only, ``nominal`` for
    control inputs only (NaN otherwise).
    """

    name: str
    label: str
    unit: str
    internal_unit: str
    scale: float
    lo: float
    hi: float
    mu_min: float = math.nan
    mu_max: float = math.nan
    sigma: float = math.nan
    rho: float = math.nan
    nominal: float = math.nan
    note: str = ""

    @property
    def width(self) -> float:
        """``hi - lo`` in internal units."""
        return self.hi - self.lo


@dataclass(frozen=True)
class Group:
    """An ordered set of variables with a name -> column map.

    ``group["name"]`` is the :class:`Variable`, ``group.index["name"]`` its column.
    """

    variables: tuple[Variable, ...]
    index: Mapping[str, int] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "index", {v.name: i for i, v in enumerate(self.variables)})

    def __getitem__(self, name: str) -> Variable:
        try:
            return self.variables[self.index[name]]
        except KeyError:
            raise KeyError(f"no variable {name!r}; known: {', '.join(self.names)}") from None

    def __iter__(self) -> Iterator[Variable]:
        return iter(self.variables)

    def __len__(self) -> int:
        return len(self.variables)

    def __add__(self, other: Group) -> Group:
        return Group(self.variables + other.variables)

    @property
    def names(self) -> tuple[str, ...]:
        """Names of the variables, in order."""
        return tuple(v.name for v in self.variables)

    def _col(self, attr: str) -> FloatArray:
        return np.array([getattr(v, attr) for v in self.variables], dtype=np.float64)

    @property
    def lo(self) -> FloatArray:
        """Lower bounds, shape ``(d,)``."""
        return self._col("lo")

    @property
    def hi(self) -> FloatArray:
        """Upper bounds, shape ``(d,)``."""
        return self._col("hi")

    @property
    def mu_min(self) -> FloatArray:
        """(d,) lower bounds of the statistics mu, internal units."""
        return self._col("mu_min")

    @property
    def mu_max(self) -> FloatArray:
        """(d,) upper bounds of the statistics mu, internal units."""
        return self._col("mu_max")

    @property
    def mu_mid(self) -> FloatArray:
        """``(mu_min + mu_max) / 2``: the mean assumed when mu is unknown (series 4, 6)."""
        return 0.5 * (self.mu_min + self.mu_max)

    @property
    def sigma(self) -> FloatArray:
        """(d,) standard deviations of the state variables, internal units."""
        return self._col("sigma")

    @property
    def nominal(self) -> FloatArray:
        """(d,) nominal values of control inputs, internal units."""
        return self._col("nominal")

    @property
    def rho(self) -> FloatArray:
        """(d,) autocorrelations of the state variables (eq. 4-5)."""
        return self._col("rho")


#: deviation kinds a spec may choose (``[deviation] kinds``), in the order of ``theta_d``
DEVIATION_KINDS = ("force_scaling", "speed_scaling")


@dataclass(frozen=True)
class Output:
    """One named scalar output of the process model (e.g. a bend angle), predicted per product.

    ``uses_controls``: the output depends on the press settings ``u`` (happens after
    they act, as the demonstrator's final angle); otherwise it is a function of ``(x,
    theta)`` only, like the force curve.
    """

    name: str
    label: str
    unit: str
    uses_controls: bool = True
    note: str = ""


#: the outputs of a spec without ``[[output]]`` entries: the demonstrator's two bend angles
DEFAULT_OUTPUTS = (
    Output("angle_stage1", "angle after stage 1", "deg", uses_controls=False),
    Output("angle_stage2", "angle after stage 2", "deg", uses_controls=True))


@dataclass(frozen=True)
class Deviation:
    """Layout of ``theta_d``: for each of ``kinds`` (in :data:`DEVIATION_KINDS` order) its
    values at ``knots`` knots (curve-axis units). No kinds: ``g`` is the identity and
    ``theta_d`` is empty."""

    group: Group
    knots: FloatArray
    kinds: tuple[str, ...] = DEVIATION_KINDS

    @property
    def n_knots(self) -> int:
        """Number of deviation knots (the dimension of theta_d)."""
        return int(self.knots.size)

    @property
    def names(self) -> tuple[str, ...]:
        """Names of the deviation parameters theta_d."""
        return self.group.names


@dataclass(frozen=True)
class ProcessSpec:
    """A process: state ``x``, parameters ``theta``, controls ``u``, deviation ``theta_d``
    and time grid.

    ``inputs`` (state then parameters) are what the tracker estimates, ``controls`` the
    press settings the line sets per product (known, never estimated; ``[[control]]`` in
    the TOML, optional), ``run_inputs`` (inputs then controls) the columns of a model run
    and of a DOE, ``augmented`` (inputs then deviation) the particle filter's state.
    ``time`` is the force-curve grid in internal units of its ``axis``: s for ``"time"``,
    mm for ``"stroke"`` (``axis_unit``/``axis_scale``: the spec file's unit and its factor
    to the internal one). ``noise_sd`` is the force sensor's std, N (0: not given).
    ``outputs`` the named scalar outputs (``[[output]]``; the demonstrator's two angles when
    none are given). ``text`` is the TOML the spec was parsed from, so that files can carry
    their spec.
    """

    name: str
    description: str
    state: Group
    params: Group
    deviation: Deviation
    time: FloatArray
    source: str
    text: str = field(default="", repr=False, compare=False)
    controls: Group = field(default_factory=lambda: Group(()))
    #: the line's sensors besides the curve (``[[sensor]]``, :mod:`formtwin.spec.sensors`)
    sensors: tuple[Sensor, ...] = ()

    def sensor(self, name: str) -> Sensor:
        """The sensor called ``name``; ``KeyError`` naming the known ones."""
        from formtwin.spec.sensors import sensor_by_name
        return sensor_by_name(self.sensors, name)

    outputs: tuple[Output, ...] = DEFAULT_OUTPUTS
    axis: str = "time"
    axis_unit: str = "ms"
    axis_scale: float = 1e-3
    noise_sd: float = 0.0

    @property
    def output_names(self) -> tuple[str, ...]:
        """Names of the scalar outputs, in the order of the model's output columns."""
        return tuple(o.name for o in self.outputs)

    @property
    def n_outputs(self) -> int:
        """Number of scalar outputs (columns of ``angles``)."""
        return len(self.outputs)

    def output(self, name: str) -> Output:
        """The output called ``name``; ``KeyError`` naming the known ones."""
        for o in self.outputs:
            if o.name == name:
                return o
        raise KeyError(f"no output {name!r}; known: {', '.join(self.output_names)}")

    @property
    def axis_label(self) -> str:
        """The curve axis with the spec file's unit, e.g. ``"time (ms)"``."""
        return f"{self.axis} ({self.axis_unit})"

    @property
    def inputs(self) -> Group:
        """State then parameters: the 10 inputs of the process model."""
        return self.state + self.params

    @property
    def augmented(self) -> Group:
        """State, parameters, deviation: the particle filter's augmented state."""
        return self.inputs + self.deviation.group

    @property
    def n_inputs(self) -> int:
        """Number of model inputs ``[x, theta]`` (10 for Table 1)."""
        return len(self.state) + len(self.params)

    @property
    def run_inputs(self) -> Group:
        """State, parameters, controls: the columns of a model run ``(x, theta, u)``."""
        return self.inputs + self.controls

    @property
    def n_run_inputs(self) -> int:
        """Number of columns of a model run ``[x, theta, u]`` (11 for the demonstrator)."""
        return self.n_inputs + len(self.controls)

    def run_columns(self, X: FloatArray, u: FloatArray | float | None = None) -> FloatArray:
        """Model-run inputs ``(N, n_run_inputs)`` from ``X``.

        ``X (N, n_inputs)`` gets the control columns appended: ``u`` a scalar or ``(N,)``
        (one control) or ``(N, n_controls)``; ``None`` the nominal settings. ``X (N,
        n_run_inputs)`` already holds them and is returned as is (``u`` must be None). A
        1-D ``X`` is one row.
        """
        X = np.asarray(X, dtype=np.float64)
        if X.ndim == 1:
            X = X[None, :]
        nc = len(self.controls)
        if X.ndim == 2 and X.shape[1] == self.n_run_inputs and (u is None or nc == 0):
            return X
        if X.ndim != 2 or X.shape[1] != self.n_inputs:
            raise ValueError(f"inputs of shape {X.shape}, expected (N, {self.n_inputs}) "
                             f"[x, theta] or (N, {self.n_run_inputs}) with the controls "
                             f"({', '.join(self.run_inputs.names)})")
        if nc == 0:
            if u is not None:
                raise ValueError(f"spec {self.name!r} has no control inputs; got u = {u!r}")
            return X
        uu = self.controls.nominal if u is None else np.asarray(u, dtype=np.float64)
        if uu.ndim == 1 and nc == 1 and uu.size != 1:
            uu = uu[:, None]
        try:
            cols = np.broadcast_to(uu, (X.shape[0], nc))
        except ValueError:
            raise ValueError(f"controls u of shape {np.shape(uu)}, expected a scalar, "
                             f"({X.shape[0]},) or ({X.shape[0]}, {nc})") from None
        if not np.all(np.isfinite(cols)):
            raise ValueError("controls u must be finite")
        return np.hstack([X, cols])

    @property
    def n_t(self) -> int:
        """Samples per force curve on the time grid."""
        return int(self.time.size)

    @property
    def dt(self) -> float:
        """Time step of the uniform curve grid, s."""
        return float(self.time[1] - self.time[0])
