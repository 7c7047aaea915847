"""The metamodel: POD of the force curves plus RBF interpolation (paper, "Metamodel").

Composed like an estimator: ``Metamodel(reduction=POD(...), approximation=RBF(...))``
``.fit(dataset)`` returns itself and ``.predict(X)`` evaluates it. The curves of the
dataset's successful runs are reduced to mode coefficients; one approximation (a copy of
``approximation``) interpolates all coefficients, and one more copy per scalar output of the
spec (``spec.outputs``; the demonstrator's two bend angles) interpolates it separately (as
the paper does for its angles). Inputs are first mapped per dimension to the
unit design box ``(x - lo) / (hi - lo)`` of the spec (the scaler); the approximation may
then learn its own per-dimension length scales.

The DOE spans the run inputs ``(x, theta, u)`` (``spec.run_inputs``; ``u`` the press
settings, e.g. the stage-2 depth). The curves and the outputs with ``uses_controls =
false`` (the stage-1 angle) happen before the settings act, so their models take ``(x,
theta)`` only; the other outputs' models (the final angle) take ``(x, theta, u)``.
:meth:`Metamodel.final_angle` evaluates the last output (the final angle) of a cloud of
particles at several settings at once (for a controller choosing ``u``).

The file format (:meth:`Metamodel.save`) is a numpy ``.npz`` readable with
``allow_pickle=False``: the spec's TOML text, the scaler, the source dataset's model
version, the fit's identity (:attr:`Metamodel.fit_id`, :mod:`.identity`), the arrays of
every fitted part and, once learned, its interval calibration as JSON text
(:attr:`Metamodel.calibration`, ``formtwin metamodel calibrate``).
"""

from __future__ import annotations

import copy
import json
import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
from numpy.typing import NDArray

from formtwin._threads import single_blas_thread
from formtwin.metamodel.gradient import Gradients
from formtwin.metamodel.identity import data_digest, fit_id
from formtwin.metamodel.pod import POD
from formtwin.metamodel.protocols import Approximation, Dataset, Reduction
from formtwin.metamodel.rbf import RBF
from formtwin.metamodel.residuals import ResidualModel
from formtwin.spec import ProcessSpec, parse_spec

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

log = logging.getLogger(__name__)

FORMAT = "formtwin.metamodel/1"

_T = TypeVar("_T")

#: tolerance of the outside-box flag, as a fraction of each input's range
_BOX_TOL = 1e-9

#: kernel and RBF centres of the default curve model and of each default angle model
DEFAULT_KERNEL = "cubic"
DEFAULT_CENTRES = 1000
DEFAULT_ANGLE_CENTRES = 500


#: kinds that :meth:`Metamodel.load` can rebuild
REDUCTIONS: dict[str, type[POD]] = {"POD": POD}
APPROXIMATIONS: dict[str, type[RBF]] = {"RBF": RBF}


@dataclass(frozen=True)
class Prediction:
    """Metamodel outputs for a batch of N input points.

    Attributes
    ----------
    curves : ndarray, shape (N, n_t)
        Stage-1 force curves on ``spec.time``, N.
    angles : ndarray, shape (N, n_outputs)
        The spec's scalar outputs (the demonstrator: bend angles after stage 1 and 2, degrees).
    outside : ndarray of bool, shape (N,)
        True where the input lies outside the DOE box (the metamodel extrapolates there).
    """

    curves: FloatArray
    angles: FloatArray
    outside: BoolArray


class Metamodel(Gradients):
    """POD + RBF metamodel of a process model, fitted to a DOE dataset.

    Parameters
    ----------
    reduction : Reduction
        Reduction of the curves; default ``POD(n_modes=40)`` (paper).
    approximation : Approximation
        Template for the interpolation of the mode coefficients; default
        ``RBF("cubic", n_centres=1000)`` (per-dimension length scales by leave-one-out,
        least squares on 1000 centres; see ``docs/explanation/metamodel.md`` for the accuracy/speed
        trade-off that chose it). It is copied, never fitted itself.
    angle_approximation : Approximation or None
        Template for each of the two angle models. ``None``: ``RBF("cubic",
        n_centres=500)`` if ``approximation`` is also ``None``, else ``approximation``.

    Examples
    --------
    >>> from formtwin.defaults import analytic_dataset
    >>> data = analytic_dataset(300, seed=1)
    >>> mm = Metamodel(POD(n_modes=10), RBF(length_scales="box")).fit(data)
    >>> p = mm.predict(data.inputs[:5])
    >>> p.curves.shape, p.angles.shape, p.outside.tolist()
    ((5, 101), (5, 2), [False, False, False, False, False])
    """

    def __init__(self, reduction: Reduction | None = None,
                 approximation: Approximation | None = None,
                 angle_approximation: Approximation | None = None) -> None:
        self.reduction: Reduction = reduction if reduction is not None else POD()
        if angle_approximation is None:
            angle_approximation = RBF(DEFAULT_KERNEL, n_centres=DEFAULT_ANGLE_CENTRES) \
                if approximation is None else approximation
        self.approximation: Approximation = approximation if approximation is not None \
            else RBF(DEFAULT_KERNEL, n_centres=DEFAULT_CENTRES)
        self.angle_approximation: Approximation = angle_approximation
        self.curve_model: Approximation | None = None
        self.angle_models: tuple[Approximation, ...] = ()
        #: the input columns of each angle model (:meth:`_output_dims`), set with them
        self._angle_dims: tuple[int, ...] = ()
        self._spec: ProcessSpec | None = None
        self.spec_text = ""
        self.lo = np.zeros(0)
        self.hi = np.zeros(0)
        self._model_version = ""
        self.n_train = 0
        self.fit_seconds = float("nan")
        #: statistics of held-out residuals (:func:`~formtwin.metamodel.calibrate`), or None
        self.residuals: ResidualModel | None = None
        #: identity of the fit (:func:`~formtwin.metamodel.identity.fit_id`; "" for a file
        #: written before it was stored)
        self.fit_id = ""
        #: the interval calibration learned for this fit (JSON-safe dict, see
        #: :mod:`formtwin.tracker.intervals`), or None
        self.calibration: dict[str, Any] | None = None

    def __repr__(self) -> str:
        return (f"Metamodel(reduction={self.reduction!r}, approximation={self.approximation!r},"
                f" angle_approximation={self.angle_approximation!r})")

    # --------------------------------------------------------------- properties
    @property
    def spec(self) -> ProcessSpec:
        """The process spec of the source dataset."""
        if self._spec is None:
            raise RuntimeError("Metamodel is not fitted: call fit(dataset) or Metamodel.load")
        return self._spec

    @property
    def n_modes(self) -> int:
        """Number of POD modes interpolated."""
        return self.reduction.n_modes

    @property
    def model_version(self) -> str:
        """Version of the process model that produced the source dataset."""
        return self._model_version

    # ------------------------------------------------------------------ fitting
    def fit(self, dataset: Dataset) -> Metamodel:
        """Fit to the successful runs (``dataset.ok``) of a DOE dataset; returns ``self``."""
        with single_blas_thread():
            return self._fit(dataset)

    def _fit(self, dataset: Dataset) -> Metamodel:
        t0 = time.perf_counter()
        spec = dataset.spec
        ok = np.asarray(dataset.ok, dtype=bool)
        X = np.asarray(dataset.inputs, dtype=np.float64)[ok]
        curves = np.asarray(dataset.curves, dtype=np.float64)[ok]
        angles = np.asarray(dataset.angles, dtype=np.float64)[ok]
        n_run, n_in = spec.n_run_inputs, spec.n_inputs
        if X.shape[0] < n_run + 2:
            raise ValueError(f"Metamodel.fit: {X.shape[0]} successful runs, expected at "
                             f"least {n_run + 2}")
        n_out = spec.n_outputs
        if X.shape[1] != n_run or curves.shape[1] != spec.n_t or angles.shape[1] != n_out:
            raise ValueError(f"Metamodel.fit: inputs {X.shape}, curves {curves.shape}, angles "
                             f"{angles.shape}; expected (n, {n_run}), (n, {spec.n_t}), "
                             f"(n, {n_out}) (outputs {', '.join(spec.output_names)})")
        self._spec, self.spec_text = spec, dataset.spec_text or spec.text
        self.fit_id = self.identity(dataset)
        self._model_version = str(dataset.model_version)
        self.lo, self.hi = spec.run_inputs.lo, spec.run_inputs.hi
        U = self.scale(X)
        coeffs = self.reduction.fit(curves).transform(curves)
        self.curve_model = copy.deepcopy(self.approximation).fit(U[:, :n_in], coeffs)
        # outputs before the press settings act take (x, theta); those after, (x, theta, u)
        self._angle_dims = self._output_dims(spec)
        self.angle_models = tuple(
            copy.deepcopy(self.angle_approximation).fit(U[:, :n], angles[:, j:j + 1])
            for j, n in enumerate(self._angle_dims))
        self.n_train = X.shape[0]
        self.residuals = None  # they and the calibration described the previous fit
        self.calibration = None
        self.fit_seconds = time.perf_counter() - t0
        log.info("Metamodel fitted to %d runs (%d excluded) in %.1f s, %d modes",
                 self.n_train, int((~ok).sum()), self.fit_seconds, self.n_modes)
        return self

    def identity(self, dataset: Dataset) -> str:
        """The :attr:`fit_id` a fit of ``dataset`` with this metamodel's settings has
        (computed without fitting): the successful runs' bytes, the templates' settings
        and the file format, nothing the machine's rounding can change."""
        ok = np.asarray(dataset.ok, dtype=bool)
        digest = data_digest(np.asarray(dataset.inputs)[ok], np.asarray(dataset.curves)[ok],
                             np.asarray(dataset.angles)[ok])
        return fit_id(digest, FORMAT, {"reduction": self.reduction,
                                       "curves": self.approximation,
                                       "angles": self.angle_approximation})

    # --------------------------------------------------------------- evaluation
    def scale(self, X: FloatArray) -> FloatArray:
        """Inputs (N, d), internal units -> the unit design box (N, d); ``d`` the first
        ``d`` run inputs (10 ``[x, theta]`` or 11 ``[x, theta, u]``)."""
        d = X.shape[-1]
        out: FloatArray = (X - self.lo[:d]) / (self.hi[:d] - self.lo[:d])
        return out

    def _inputs(self, X: FloatArray, u: FloatArray | float | None = None) -> FloatArray:
        return self.spec.run_columns(X, u)

    def _unit_in(self, X: FloatArray) -> FloatArray:
        """Unit-box ``(x, theta)`` (N, 10) of inputs (N, 10) or (N, 11) (controls unused)."""
        X = np.asarray(X, dtype=np.float64)
        if X.ndim == 1:
            X = X[None, :]
        sp = self.spec
        if X.ndim != 2 or X.shape[1] not in (sp.n_inputs, sp.n_run_inputs):
            raise ValueError(f"Metamodel inputs of shape {X.shape}, expected (N, {sp.n_inputs})"
                             f" or (N, {sp.n_run_inputs}) with columns "
                             f"{', '.join(sp.run_inputs.names)}")
        return self.scale(X[:, :sp.n_inputs])

    def outside(self, X: FloatArray, u: FloatArray | float | None = None) -> BoolArray:
        """True (N,) where an input (with its controls) lies outside the DOE box."""
        U = self.scale(self._inputs(X, u))
        out: BoolArray = np.any((U < -_BOX_TOL) | (U > 1.0 + _BOX_TOL), axis=1)
        return out

    def _curves(self, U: FloatArray) -> FloatArray:
        assert self.curve_model is not None
        return self.reduction.inverse_transform(self.curve_model.predict(U[:, :self.spec.n_inputs]))

    @staticmethod
    def _output_dims(spec: ProcessSpec) -> tuple[int, ...]:
        """Input columns of each output's model: ``n_run_inputs`` if it uses the controls."""
        return tuple(spec.n_run_inputs if o.uses_controls else spec.n_inputs
                     for o in spec.outputs)

    def _angles(self, U: FloatArray) -> FloatArray:
        if not self.angle_models:
            return np.empty((U.shape[0], 0))
        # the spec builds its outputs on every access: their input widths were kept when
        # the angle models were made
        return np.hstack([m.predict(U[:, :n]) for m, n in
                          zip(self.angle_models, self._angle_dims, strict=True)])

    def predict_curves(self, X: FloatArray) -> FloatArray:
        """Force curves (N, n_t), N, at inputs ``X`` (N, 10) ``[x, theta]`` or (N, 11)
        (the controls act after stage 1), internal units."""
        U = self._unit_in(X)
        assert self.curve_model is not None
        with single_blas_thread():
            return self.reduction.inverse_transform(self.curve_model.predict(U))

    def predict_angles(self, X: FloatArray, u: FloatArray | float | None = None) -> FloatArray:
        """Scalar outputs (N, n_outputs) (the demonstrator: bend angles, degrees) at inputs
        ``X`` (N, 10) and controls ``u`` (scalar, (N,) or (N, n_controls); None: nominal),
        or at ``X`` (N, 11) with ``u`` None."""
        U = self.scale(self._inputs(X, u))
        with single_blas_thread():
            return self._angles(U)

    def final_angle(self, X: FloatArray, u: FloatArray) -> FloatArray:
        """Final bend angle (N, n_u), degrees, of each input ``X`` (N, 10) ``[x, theta]`` at
        each setting of the one control ``u`` (n_u,), in one evaluation of its model.

        >>> from formtwin.defaults import analytic_dataset
        >>> mm = Metamodel(POD(n_modes=5), RBF(length_scales="box")).fit(
        ...     analytic_dataset(200, seed=1))
        >>> X = analytic_dataset(3, seed=2).inputs[:, :10]
        >>> a = mm.final_angle(X, np.array([-0.05, 0.0, 0.05]))
        >>> a.shape, bool(np.allclose(a[:, 1], mm.predict_angles(X, 0.0)[:, 1]))
        ((3, 3), True)
        """
        Xi = np.asarray(X, dtype=np.float64)
        uu = np.asarray(u, dtype=np.float64).reshape(-1)
        if len(self.spec.controls) != 1 or not self.spec.outputs[-1].uses_controls:
            raise ValueError(f"final_angle needs exactly one control input and a last output "
                             f"that uses it; the spec has {len(self.spec.controls)} control(s)"
                             f" and outputs {', '.join(self.spec.output_names)}")
        if Xi.ndim != 2 or Xi.shape[1] != self.spec.n_inputs:
            raise ValueError(f"X of shape {Xi.shape}, expected (N, {self.spec.n_inputs})")
        n, k = Xi.shape[0], uu.size
        full = np.empty((n * k, Xi.shape[1] + 1))
        full[:, :-1] = np.repeat(Xi, k, axis=0)
        full[:, -1] = np.tile(uu, n)
        with single_blas_thread():
            out: FloatArray = self.angle_models[-1].predict(self.scale(full)).reshape(n, k)
        return out

    def predict(self, X: FloatArray, u: FloatArray | float | None = None) -> Prediction:
        """Curves, angles and the outside-box flag at inputs ``X`` (N, 10) with controls
        ``u`` (None: nominal) or at ``X`` (N, 11)."""
        U = self.scale(self._inputs(X, u))
        with single_blas_thread():
            curves, angles = self._curves(U), self._angles(U)
        outside: BoolArray = np.any((U < -_BOX_TOL) | (U > 1.0 + _BOX_TOL), axis=1)
        return Prediction(curves, angles, outside)

    # ------------------------------------------------------------------ storage
    def save(self, path: str | Path) -> Path:
        """Write the fitted metamodel to ``path`` (``.npz``, no pickle); returns the path."""
        if self.curve_model is None:
            raise RuntimeError("Metamodel.save: not fitted")
        arrays: dict[str, Any] = {
            "format": np.array(FORMAT), "spec_text": np.array(self.spec_text),
            "spec_source": np.array(self.spec.source),
            "model_version": np.array(self._model_version), "scaler_lo": self.lo,
            "scaler_hi": self.hi, "n_train": np.array(self.n_train),
            "fit_id": np.array(self.fit_id),
            "reduction.kind": np.array(self.reduction.kind),
            "curves.kind": np.array(self.curve_model.kind)}
        arrays.update({f"reduction.{k}": v for k, v in self.reduction.state().items()})
        arrays.update({f"curves.{k}": v for k, v in self.curve_model.state().items()})
        for j, m in enumerate(self.angle_models):
            arrays[f"angle{j}.kind"] = np.array(m.kind)
            arrays.update({f"angle{j}.{k}": v for k, v in m.state().items()})
        if self.residuals is not None:
            arrays.update({f"residuals.{k}": v for k, v in self.residuals.state().items()})
        if self.calibration is not None:
            arrays["calibration"] = np.array(json.dumps(self.calibration))
        p = Path(path)
        with open(p, "wb") as fh:
            np.savez_compressed(fh, **arrays)
        return p

    @classmethod
    def load(cls, path: str | Path) -> Metamodel:
        """Read a metamodel written by :meth:`save`."""
        p = Path(path)
        try:
            with np.load(p, allow_pickle=False) as npz:
                arrays = {k: npz[k] for k in npz.files}
        except (OSError, ValueError) as exc:
            raise ValueError(f"{p}: not a formtwin metamodel file ({exc})") from exc
        if str(arrays.get("format", "")) != FORMAT:
            raise ValueError(f"{p}: format {str(arrays.get('format', '?'))!r}, "
                             f"expected {FORMAT!r}")

        def part(prefix: str) -> dict[str, np.ndarray]:
            return {k[len(prefix) + 1:]: v for k, v in arrays.items()
                    if k.startswith(prefix + ".") and k != prefix + ".kind"}

        def kind(prefix: str, registry: dict[str, type[_T]]) -> type[_T]:
            name = str(arrays[f"{prefix}.kind"])
            if name not in registry:
                raise ValueError(f"{p}: {prefix}.kind = {name!r}, known: {', '.join(registry)}")
            return registry[name]

        mm = cls()
        try:
            mm.reduction = kind("reduction", REDUCTIONS).from_state(part("reduction"))
            mm.curve_model = kind("curves", APPROXIMATIONS).from_state(part("curves"))
            mm.spec_text = str(arrays["spec_text"])
            source = str(arrays["spec_source"])
            mm._spec = parse_spec(mm.spec_text, source)
            mm._angle_dims = mm._output_dims(mm._spec)
            mm.angle_models = tuple(kind(f"angle{j}", APPROXIMATIONS).from_state(
                part(f"angle{j}")) for j in range(mm._spec.n_outputs))
            mm._model_version = str(arrays["model_version"])
            mm.lo = np.asarray(arrays["scaler_lo"], dtype=np.float64)
            mm.hi = np.asarray(arrays["scaler_hi"], dtype=np.float64)
            mm.n_train = int(arrays["n_train"])
            if "residuals.curve_cov" in arrays:
                mm.residuals = ResidualModel.from_state(part("residuals"))
            mm.fit_id = str(arrays.get("fit_id", ""))
            if "calibration" in arrays:
                mm.calibration = json.loads(str(arrays["calibration"]))
        except KeyError as exc:
            raise ValueError(f"{p}: incomplete metamodel file, no array {exc}") from None
        # the fitted parts stand in for the templates (repr, validate(), refitting)
        mm.approximation = mm.curve_model
        mm.angle_approximation = mm.angle_models[0] if mm.angle_models else mm.curve_model
        return mm
