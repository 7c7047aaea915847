"""Child of ``bench_filter.py``: the tracker's model through ``particles``' bootstrap filter.

Runs inside ``benchmarks/.venv-particles`` (``particles`` 0.4 needs ``numpy < 2``). The
model is formtwin's own :class:`~formtwin.tracker.BendingSSM` (same transition, same
``g^-1`` and likelihood code, imported from ``--src``), wrapped as a
``particles.state_space_models.StateSpaceModel``; ``particles.SMC`` with the ``Bootstrap``
Feynman-Kac model, systematic resampling at every step (``ESSrmin=1``), N particles. Each
timed step also computes what the tracker's step does: weighted mean and std (eq. 13-14)
and the predicted angles. Writes the median step time and the means as JSON.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from typing import Any


def main() -> None:
    ap = argparse.ArgumentParser()
    for a in ("--model", "--measurement", "--data", "--out", "--src"):
        ap.add_argument(a, required=True)
    ap.add_argument("--particles", type=int, default=500)
    ap.add_argument("--products", type=int, default=1000)
    args = ap.parse_args()
    sys.path.insert(0, args.src)

    import numpy as np
    import particles
    from particles import distributions as dists
    from particles import state_space_models as ssms
    from threadpoolctl import threadpool_limits

    from formtwin._threads import single_blas_thread
    from formtwin.measurement import MeasurementModel
    from formtwin.tracker import BendingSSM, TrackerConfig

    # this venv has no h5py/xarray: build the model without formtwin.defaults
    if args.model == "analytic":
        from formtwin.physics.analytic import AnalyticBending
        from formtwin.simulator import SimulatorModel
        from formtwin.spec import load_spec

        model: Any = SimulatorModel(AnalyticBending(load_spec()))
    else:
        from formtwin.metamodel import Metamodel

        model = Metamodel.load(args.model)
    mm = MeasurementModel.load(args.measurement)
    with np.load(args.data, allow_pickle=False) as z:
        curves, mu = z["curves"][: args.products], z["mu"]
    bssm = BendingSSM(model, mm, TrackerConfig(mu=tuple(mu)))
    rng = np.random.default_rng(3)
    n_in = model.spec.n_inputs
    d = len(model.spec.augmented)

    class Initial(dists.ProbDist):
        dim = d

        def rvs(self, size=None):
            return bssm.sample_initial(size, rng)

    class Transition(dists.ProbDist):
        dim = d

        def __init__(self, xp):
            self.xp = xp

        def rvs(self, size=None):
            return bssm.sample_transition(self.xp, rng)

    class Likelihood(dists.ProbDist):
        dim = model.spec.n_t

        def __init__(self, x):
            self.x = x

        def logpdf(self, y):
            return bssm.loglik(self.x, y)

    class Bending(ssms.StateSpaceModel):
        def PX0(self):
            return Initial()

        def PX(self, t, xp):
            return Transition(xp)

        def PY(self, t, xp, x):
            return Likelihood(x)

    fk = ssms.Bootstrap(ssm=Bending(), data=list(curves))
    alg = particles.SMC(fk=fk, N=args.particles, resampling="systematic", ESSrmin=1.0,
                        store_history=False)
    # formtwin's own tracker on the same data, in this same process and numpy version,
    # interleaved product by product with particles so that load from other processes
    # on the machine hits both alike
    from formtwin.tracker import Tracker

    tracker = Tracker(model, mm, TrackerConfig(n_particles=args.particles, mu=tuple(mu),
                                               seed=3))
    times, cpu, own, means = [], [], [], []
    # formtwin's own one-thread limit around the loop, as bench_filter.py has around the
    # tracker's run: the model's evaluations inside it then skip setting the limit per
    # call (~0.1 ms per entry and exit), for both filters alike
    with threadpool_limits(limits=1, user_api="blas"), single_blas_thread():
        for c in curves:
            t0, c0 = time.perf_counter(), time.thread_time()
            next(alg)
            w, x = alg.wgts.W, alg.X
            m = w @ x
            s = np.sqrt(np.maximum(w @ (x - m) ** 2, 0.0))
            a = model.predict_angles(x[:, :n_in])
            am = w @ a
            _ = (s, np.sqrt(np.maximum(w @ (a - am) ** 2, 0.0)))
            t1, c1 = time.perf_counter(), time.thread_time()
            tracker.step(c)
            own.append(time.thread_time() - c1)
            times.append(t1 - t0)
            cpu.append(c1 - c0)
            means.append(m.tolist())
    overhead = filter_overhead(args.particles)
    overhead["formtwin_step_cpu_ms_same_numpy"] = float(np.median(own) * 1e3)
    with open(args.out, "w", encoding="utf-8") as fh:
        from importlib.metadata import version

        json.dump({"step_ms": float(np.median(times) * 1e3),
                   "step_cpu_ms": float(np.median(cpu) * 1e3), "version": version("particles"),
                   "numpy": np.__version__, "mean": means, **overhead}, fh)


def filter_overhead(n: int, steps: int = 1000) -> dict[str, float]:
    """Median ms per step of formtwin's SIR and of particles' SMC on a trivial model
    (18-d random walk, scalar Gaussian observation of the first component), in this same
    process and numpy: the cost of the filter machinery itself."""
    import numpy as np
    import particles
    from particles import distributions as dists
    from particles import state_space_models as ssms

    from formtwin.filters import SIR

    d = 18
    rng = np.random.default_rng(0)
    ys = np.cumsum(0.1 * rng.standard_normal(steps)) + rng.standard_normal(steps)

    class RW:
        def sample_initial(self, n, rng):
            return rng.standard_normal((n, d))

        def sample_transition(self, x, rng):
            return x + 0.1 * rng.standard_normal(x.shape)

        def loglik(self, x, y):
            return -0.5 * (y - x[:, 0]) ** 2

    rw, grng = RW(), np.random.default_rng(1)

    class P0(dists.ProbDist):
        dim = d

        def rvs(self, size=None):
            return rw.sample_initial(size, grng)

    class PX(dists.ProbDist):
        dim = d

        def __init__(self, xp):
            self.xp = xp

        def rvs(self, size=None):
            return rw.sample_transition(self.xp, grng)

    class PY(dists.ProbDist):
        def __init__(self, x):
            self.x = x

        def logpdf(self, y):
            return rw.loglik(self.x, y)

    class M(ssms.StateSpaceModel):
        def PX0(self):
            return P0()

        def PX(self, t, xp):
            return PX(xp)

        def PY(self, t, xp, x):
            return PY(x)

    def moments(w, x):
        m = w @ x
        return m, np.sqrt(np.maximum(w @ (x - m) ** 2, 0.0))

    alg = particles.SMC(fk=ssms.Bootstrap(ssm=M(), data=list(ys)), N=n,
                        resampling="systematic", ESSrmin=1.0, store_history=False)
    f = SIR(rw, n, np.random.default_rng(2))
    t_p, t_f = [], []
    for y in ys:  # interleaved, as above
        t0 = time.thread_time()
        next(alg)
        moments(alg.wgts.W, alg.X)
        t1 = time.thread_time()
        st = f.step(y)
        st.mean(), st.std()
        t_f.append(time.thread_time() - t1)
        t_p.append(t1 - t0)
    return {"overhead_formtwin_ms": float(np.median(t_f) * 1e3),
            "overhead_particles_ms": float(np.median(t_p) * 1e3)}


if __name__ == "__main__":
    main()
