"""Track a simulated production run, product by product, the way formtwin runs beside a press.

The offline half (design of experiments -> metamodel -> measurement model) and the online
half (one particle-filter step per measured force curve) on the fast analytic stand-in, so
that it runs in seconds. Swap ``AnalyticBending`` for ``formtwin.physics.bending.BendingModel``
(and a bigger design) for the physics model.

Run: ``python examples/track_a_production_run.py``
"""

from __future__ import annotations

from pathlib import Path
from tempfile import TemporaryDirectory

import numpy as np

from formtwin.doe import latin_hypercube, run_design
from formtwin.measurement import MeasurementModel
from formtwin.metamodel import Metamodel
from formtwin.physics.analytic import AnalyticBending
from formtwin.spec import load_spec
from formtwin.study.metrics import normalised_rmse
from formtwin.tracker import TrackerConfig, build_tracker


def main(n_products: int = 300, n_particles: int = 300, seed: int = 0) -> dict[str, float]:
    """Returns the normalised RMSE over the last half of the run, per component, and for the
    two angles also that of a twin without measurements (``<angle>_no_measurement``: the
    prior predictive mean, the same for every product)."""
    spec = load_spec()
    rng = np.random.default_rng(seed)
    with TemporaryDirectory() as tmp:  # offline: DOE and metamodel
        doe = run_design(AnalyticBending(spec), latin_hypercube(spec, 800, seed),
                         Path(tmp) / "doe.h5", executor="serial")
    metamodel = Metamodel().fit(doe)
    measurement = MeasurementModel.from_monte_carlo(metamodel, rng=rng)

    # a production run with hidden truth: state drifts (eq. 4), machine parameters fixed
    config = TrackerConfig(n_particles=n_particles, estimate_deviation=False, seed=seed)
    tracker = build_tracker(metamodel, config, measurement)
    run, curves = tracker.ssm.simulate(n_products, rng)  # mu mid-range, theta_d = 0
    angles = metamodel.predict_angles(run.inputs)

    # online: one step per product
    est = tracker.run(curves)
    truth = run.truth
    score = normalised_rmse(spec, est.mean, truth, est.angles_mean, angles,
                            window=n_products // 2)
    names = list(spec.augmented.names) + ["angle_stage1", "angle_stage2"]
    result = {n: float(v) for n, v in zip(names, score, strict=True) if np.isfinite(v)
              and not n.startswith(("force_scaling", "speed_scaling"))}

    # the baseline that uses no measurement: the prior's predictive mean of the angles
    prior = tracker.ssm.sample_initial(4000, rng)
    prior_angles = np.broadcast_to(tracker.ssm.predict_angles(prior).mean(axis=0), angles.shape)
    baseline = normalised_rmse(spec, est.mean, truth, prior_angles, angles,
                               window=n_products // 2)[-2:]
    result.update({f"{n}_no_measurement": float(v) for n, v in zip(names[-2:], baseline,
                                                                      strict=True)})
    return result


if __name__ == "__main__":
    for name, value in main().items():
        print(f"{name:<22} normalised RMSE {value:6.2f}")
