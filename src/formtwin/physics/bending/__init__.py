"""Two-stage flap bending model: corotational layered beams, rigid tools, crank and press.

:class:`BendingModel` is the :class:`~formtwin.simulator.Simulator`; see ``docs/physics.md``.
"""

from formtwin.physics.bending.geometry import FlapGeometry
from formtwin.physics.bending.material import Material
from formtwin.physics.bending.model import VERSION, BendingModel, Discretisation

__all__ = ["VERSION", "BendingModel", "Discretisation", "FlapGeometry", "Material"]
