"""Make docs/figures/likelihood_covariance.png: the metamodel's residual covariance K_res
next to the paper's K_MC / 4 (docs/likelihood.md).

    python docs/figures/likelihood_covariance.py [METAMODEL.npz] [REALISATION.nc]

METAMODEL defaults to the study's cached metamodel of the bundled physics DOE (with its
5-fold residual statistics); REALISATION (optional, a study pseudo-data file) adds the
physics-minus-metamodel residuals along one production run.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import xarray as xr

from formtwin.figures import pyplot
from formtwin.measurement import monte_carlo_inputs
from formtwin.metamodel import Metamodel
from formtwin.study.pseudodata import Realisation

CACHE = "benchmarks/.cache/study"
mm_path = sys.argv[1] if len(sys.argv) > 1 else f"{CACHE}/model/metamodel_bending.npz"
real_path = sys.argv[2] if len(sys.argv) > 2 else f"{CACHE}/data/realisation_0.nc"
mm = Metamodel.load(mm_path)
assert mm.residuals is not None, "the metamodel has no residual statistics"
spec = mm.spec
t_ms = spec.time * 1e3
z = mm.predict_curves(monte_carlo_inputs(spec, 10_000, np.random.default_rng(0)))
k_mc4 = 0.25 * np.cov(z, rowvar=False)
k_res = mm.residuals.curve_cov
run_res = None
if Path(real_path).exists():
    with xr.open_dataset(real_path, engine="h5netcdf") as ds:
        real = Realisation.from_dataset(ds.load())
    ok = real.ok["FE"]
    r = real.curves["FE"][ok] - mm.predict_curves(real.inputs[ok])
    run_res = r.T @ r / len(r)

plt = pyplot()
fig, ax = plt.subplots(1, 3, figsize=(14, 4), layout="constrained")
ax[0].semilogy(t_ms, np.sqrt(np.diag(k_mc4)), label="sqrt diag K_MC / 4 (paper)")
ax[0].semilogy(t_ms, np.sqrt(np.diag(k_res)), label="sqrt diag K_res (5-fold CV on the DOE)")
if run_res is not None:
    ax[0].semilogy(t_ms, np.sqrt(np.diag(run_res)), "--",
                   label="rms physics - metamodel, one production run")
ax[0].set(xlabel="time, ms", ylabel="std, N", ylim=(1e-2, None),
          title="standard deviation per sample (no contact before -57 ms)")
ax[0].legend(fontsize=8)
for mat, label in ((k_mc4, "K_MC / 4"), (k_res, "K_res"), (k_mc4 + k_res, "K_MC / 4 + K_res")):
    ev = np.sort(np.linalg.eigvalsh(mat))[::-1]
    ax[1].semilogy(np.arange(1, ev.size + 1), np.maximum(ev, 1e-12), label=label)
ax[1].set(xlabel="principal direction", ylabel="variance, N^2", title="eigenvalues",
          ylim=(1e-6, None))
ax[1].legend(fontsize=8)
d = np.sqrt(np.diag(k_res))
d = np.where(d > 1e-6 * d.max(), d, np.nan)  # samples before contact: no force, no error
im = ax[2].imshow(k_res / np.outer(d, d), cmap="RdBu_r", vmin=-1, vmax=1,
                  extent=(t_ms[0], t_ms[-1], t_ms[-1], t_ms[0]))
ax[2].set(xlabel="time, ms", ylabel="time, ms", title="correlation of K_res")
fig.colorbar(im, ax=ax[2], shrink=0.8)
out = Path(__file__).with_suffix(".png")
fig.savefig(out, dpi=110)
print(f"wrote {out}")
print(f"trace K_MC/4 = {np.trace(k_mc4):.4g}, trace K_res = {np.trace(k_res):.4g} N^2")
if run_res is not None:
    print(f"trace of one run's residual second moment = {np.trace(run_res):.4g} N^2")
