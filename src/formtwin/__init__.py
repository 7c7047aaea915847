"""formtwin: a hybrid twin for metal-forming mass production.

Offline, a physics-based process model is run over a design of experiments and condensed
into a POD + RBF metamodel; online, a particle filter tracks the hidden process state,
the machine parameters and the model deviation product by product (Havinga, Mandal and
van den Boogaard, "Exploiting data in smart factories").
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("formtwin")
except PackageNotFoundError:  # running from a source tree that was not installed
    __version__ = "0+unknown"
