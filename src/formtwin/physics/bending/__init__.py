"""Two-stage flap bending model: corotational layered beams, rigid tools, crank and press.

:class:`BendingModel` is the :class:`~formtwin.simulator.Simulator`; see
``docs/explanation/physics.md``.
"""

from formtwin.physics.bending._cache import sync_cache

sync_cache()  # before the kernels load: a stale cached solver would run old kernels

from formtwin.physics.bending.geometry import FlapGeometry  # noqa: E402
from formtwin.physics.bending.material import Material  # noqa: E402
from formtwin.physics.bending.model import VERSION, BendingModel, Discretisation  # noqa: E402

__all__ = ["VERSION", "BendingModel", "Discretisation", "FlapGeometry", "Material"]
