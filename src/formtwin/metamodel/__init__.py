"""POD + RBF metamodel of the process model (paper, section "Metamodel").

``Metamodel(reduction=POD(...), approximation=RBF(...)).fit(dataset).predict(X)``; see
:mod:`formtwin.metamodel.model`. :func:`validate` reports k-fold errors,
:func:`calibrate` stores the statistics of k-fold residuals with the metamodel.
"""

from formtwin.metamodel.model import Metamodel, Prediction
from formtwin.metamodel.pod import POD
from formtwin.metamodel.protocols import Approximation, Dataset, Reduction
from formtwin.metamodel.rbf import KERNELS, RBF, loo_objective, loo_residuals
from formtwin.metamodel.residuals import ResidualModel
from formtwin.metamodel.validate import (
    RESIDUAL_RULE,
    CrossValidation,
    calibrate,
    cross_validate,
    plot_validation,
    validate,
)

__all__ = ["KERNELS", "POD", "RBF", "RESIDUAL_RULE", "Approximation", "CrossValidation",
           "Dataset", "Metamodel", "Prediction", "Reduction", "ResidualModel", "calibrate",
           "cross_validate", "loo_objective", "loo_residuals", "plot_validation", "validate"]
