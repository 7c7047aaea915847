"""Two-stage flap bending as a plane-strain CalculiX model (CPE8R sheet, rigid tools,
node-to-surface contact with friction, press spring): a continuum-FE reference for the
beam model :mod:`formtwin.physics.bending`, behind the same simulator seam.

:class:`CalculixModel` is the :class:`~formtwin.simulator.Simulator`; it needs the
``ccx`` executable (Debian package ``calculix-ccx``; ``make fe-deps``). See
``docs/explanation/physics.md``.
"""

from formtwin.physics.calculix.deck import FeSettings, ProcessPoint
from formtwin.physics.calculix.model import VERSION, CalculixModel, CcxError, ccx_version

__all__ = ["VERSION", "CalculixModel", "CcxError", "FeSettings", "ProcessPoint", "ccx_version"]
