"""The embedded default: process models by name, and the metamodel the demo and study use.

``physics_model("bending")`` is formtwin's corotational-beam flap-bending model,
``physics_model("analytic")`` the closed-form stand-in, ``physics_model("calculix")``
the plane-strain CalculiX model (needs ``ccx``). :func:`default_metamodel` loads a
given metamodel file, or the fitted metamodel bundled with the package for that model
(``formtwin/data/metamodel_<name>.npz``: the same file, so the same fit and interval
calibration, on every machine), or fits one from the bundled DOE dataset
(``formtwin/data/doe_<name>.h5``, made by ``formtwin doe run``) and caches the fit.
The analytic model's DOE is cheap and is made on first use instead of being bundled.

The bundled metamodel is the default fit of the bundled DOE with its held-out residual
statistics, written by ``formtwin metamodel fit src/formtwin/data/doe_bending.h5 --out
src/formtwin/data/metamodel_bending.npz``; its interval calibration is
``formtwin/data/interval_calibration.json`` (:mod:`formtwin.tracker.intervals`).

This is the one module (with the command line) that names physics modules; everything
else reaches a process model through :class:`~formtwin.simulator.Simulator` or a model
loaded by :func:`load_model`.

>>> data = analytic_dataset(50, seed=0)
>>> data.inputs.shape, data.curves.shape, int(data.ok.sum())
((50, 11), (50, 101), 50)
"""

from __future__ import annotations

import logging
from importlib import resources
from pathlib import Path

import numpy as np

from formtwin.dataset import DoeDataset
from formtwin.measurement import ProcessModel
from formtwin.metamodel import RESIDUAL_RULE, Metamodel, calibrate
from formtwin.simulator import Simulator, SimulatorModel
from formtwin.spec import ProcessSpec, load_spec

log = logging.getLogger(__name__)
PHYSICS = ("bending", "analytic", "calculix")


def physics_model(name: str, spec: ProcessSpec | None = None) -> Simulator:
    """A process model by name (:data:`PHYSICS`)."""
    spec = spec or load_spec()
    if name == "bending":
        from formtwin.physics.bending import BendingModel

        return BendingModel(spec)
    if name == "analytic":
        from formtwin.physics.analytic import AnalyticBending

        return AnalyticBending(spec)
    if name == "calculix":
        from formtwin.physics.calculix import CalculixModel

        return CalculixModel(spec)
    raise ValueError(f"physics model {name!r} unknown; known: {', '.join(PHYSICS)}")


class AnalyticModel(SimulatorModel):
    """The closed-form stand-in :class:`~formtwin.physics.analytic.AnalyticBending` as a
    process model (for tests, benchmarks and development; not the metamodel)."""

    def __init__(self, spec: ProcessSpec | None = None) -> None:
        super().__init__(physics_model("analytic", spec))


def analytic_model(spec: ProcessSpec | None = None) -> AnalyticModel:
    """The analytic stand-in as a process model (default spec: the demonstrator)."""
    return AnalyticModel(spec)


def load_model(name: str | Path) -> ProcessModel:
    """A process model by name: ``"analytic"`` (the stand-in) or a metamodel file."""
    if str(name) == "analytic":
        return analytic_model()
    if not Path(name).exists():
        raise ValueError(f"metamodel {name}: no such file")
    return Metamodel.load(name)


def analytic_dataset(n: int, seed: int = 0, spec: ProcessSpec | None = None,
                     failure_clearance: float | None = None) -> DoeDataset:
    """A seeded Latin hypercube of ``n`` points in the spec's box, run on the stand-in
    (small DOE datasets for tests, doctests and benchmarks).

    ``failure_clearance`` (mm) makes some runs fail (see
    :class:`~formtwin.physics.analytic.AnalyticBending`); they are kept with ``ok=False``.
    """
    from formtwin.physics.analytic import AnalyticBending

    spec = spec or load_spec()
    sim = AnalyticBending(spec, failure_clearance=failure_clearance)
    from scipy.stats import qmc  # on use: ~1.3 s CPU to import

    box = spec.run_inputs
    U = qmc.LatinHypercube(d=len(box), rng=np.random.default_rng(seed)).random(n)
    X = qmc.scale(U, box.lo, box.hi)
    curves, angles = sim.run_batch(X)
    ok = np.all(np.isfinite(curves), axis=1)
    reason = np.array(["" if good else sim.failure_reason(x)
                       for x, good in zip(X, ok, strict=True)])
    return DoeDataset(spec=spec, inputs=X, curves=curves, angles=angles, ok=ok,
                      reason=reason, model_version=sim.version)


def bundled_doe(name: str) -> Path:
    """Path of the DOE dataset bundled for process model ``name``."""
    return Path(str(resources.files("formtwin") / "data" / f"doe_{name}.h5"))


def bundled_metamodel(name: str) -> Path:
    """Path of the fitted metamodel bundled for process model ``name``."""
    return Path(str(resources.files("formtwin") / "data" / f"metamodel_{name}.npz"))


def default_doe(name: str, cache: Path) -> DoeDataset:
    """The DOE of model ``name``: the bundled file, or (analytic only) made in ``cache``."""
    path = bundled_doe(name)
    if name == "analytic" and not path.exists():
        from formtwin.doe import paper_design, run_design

        sim = physics_model(name)
        return run_design(sim, paper_design(sim.spec), cache / "doe_analytic.h5",
                          executor="serial")
    if not path.exists():
        raise FileNotFoundError(f"no bundled DOE for {name!r} at {path}; make one with "
                                f"`formtwin doe run --physics {name} --out {path}`")
    data = DoeDataset.load(path)
    current = physics_model(name, data.spec).version
    if data.model_version != current:
        raise ValueError(f"{path}: made with model version {data.model_version!r}, the "
                         f"{name} model is now {current!r}; regenerate it with `formtwin doe "
                         f"run --physics {name} --out {path}`")
    return data


def default_metamodel(cache: Path, physics: str = "bending",
                      path: str | Path | None = None) -> tuple[Metamodel, Path]:
    """Load the metamodel at ``path``, or the one bundled for ``physics``
    (:func:`bundled_metamodel`) if it is of the model's current version, or fit (once,
    cached in ``cache``) the default one with the statistics of its 5-fold held-out
    residuals (:func:`~formtwin.metamodel.calibrate`). A cached file of another model
    version, without residuals or with residuals of another rule than
    :data:`~formtwin.metamodel.RESIDUAL_RULE` is refitted (a loaded metamodel keeps its
    fitted length scales, not the default's settings to refit them)."""
    if path is not None:
        return Metamodel.load(path), Path(path)
    bundled = bundled_metamodel(physics)
    if bundled.exists():
        mm = Metamodel.load(bundled)
        if mm.model_version == physics_model(physics, mm.spec).version \
                and mm.residuals is not None and mm.residuals.rows == RESIDUAL_RULE:
            return mm, bundled
        log.warning("%s is of model version %s, not the current one: fitting the "
                    "metamodel instead", bundled, mm.model_version)
    data = default_doe(physics, cache)
    out = cache / f"metamodel_{physics}.npz"
    if out.exists():
        mm = Metamodel.load(out)
        if mm.model_version == data.model_version and mm.residuals is not None \
                and mm.residuals.rows == RESIDUAL_RULE:
            return mm, out
        log.info("%s is of another model version or residual rule: refitting", out)
    log.info("fitting the metamodel on %d runs of the %s model", data.n, physics)
    cache.mkdir(parents=True, exist_ok=True)
    mm = calibrate(Metamodel().fit(data), data)
    mm.save(out)
    return mm, out
