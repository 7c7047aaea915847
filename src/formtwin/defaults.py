"""The embedded default: process models by name, and the metamodel the demo and study use.

``physics_model("bending")`` is formtwin's corotational-beam flap-bending model,
``physics_model("analytic")`` the closed-form stand-in. :func:`default_metamodel` loads a
given metamodel file or fits one from the DOE dataset bundled with the package for that
model (``formtwin/data/doe_<name>.h5``, made by ``formtwin doe run``), caching the fit.
The analytic model's DOE is cheap and is made on first use instead of being bundled.
"""

from __future__ import annotations

import logging
from importlib import resources
from pathlib import Path

from formtwin.dataset import DoeDataset
from formtwin.metamodel import Metamodel
from formtwin.simulator import Simulator
from formtwin.spec import ProcessSpec, load_spec

log = logging.getLogger(__name__)
PHYSICS = ("bending", "analytic")


def physics_model(name: str, spec: ProcessSpec | None = None) -> Simulator:
    """A process model by name (:data:`PHYSICS`)."""
    spec = spec or load_spec()
    if name == "bending":
        from formtwin.physics.bending import BendingModel

        return BendingModel(spec)
    if name == "analytic":
        from formtwin.physics.analytic import AnalyticBending

        return AnalyticBending(spec)
    raise ValueError(f"physics model {name!r} unknown; known: {', '.join(PHYSICS)}")


def bundled_doe(name: str) -> Path:
    """Path of the DOE dataset bundled for process model ``name``."""
    return Path(str(resources.files("formtwin") / "data" / f"doe_{name}.h5"))


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
    """Load the metamodel at ``path``, or fit (once, cached in ``cache``) the default one."""
    if path is not None:
        return Metamodel.load(path), Path(path)
    data = default_doe(physics, cache)
    out = cache / f"metamodel_{physics}.npz"
    if out.exists():
        mm = Metamodel.load(out)
        if mm.model_version == data.model_version:
            return mm, out
    log.info("fitting the metamodel on %d runs of the %s model", data.n, physics)
    cache.mkdir(parents=True, exist_ok=True)
    mm = Metamodel().fit(data)
    mm.save(out)
    return mm, out
