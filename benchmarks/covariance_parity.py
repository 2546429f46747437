"""Prints how far ufm_jax's flow covariance is from the official outputs, per case of the
flow covariance fixtures (UFM_COV_FIXTURES, else UFM_FIXTURES/ufm_reference_cov): the largest
relative error of the variances, of cov_xy against sqrt(var_x var_y), of the log-determinant and
the inverse (with the smallest 1 - rho^2, where the official float32 cancels), through the
forward and through predict. The bounds the tests hold: tests/test_official_covariance.py.

  python benchmarks/covariance_parity.py
"""

import jax
import numpy as np

import ufm_jax
from ufm_jax import testing
from ufm_jax.models import ufm


def errors(got, want) -> tuple[float, float]:
  got, want = np.asarray(got, np.float64), np.asarray(want, np.float64)
  var = np.abs(got[..., :2] / want[..., :2] - 1).max()
  cov = (np.abs(got[..., 2] - want[..., 2]) / np.sqrt(want[..., 0] * want[..., 1])).max()
  return float(var), float(cov)


def main():
  root, cases = testing.reference_cases("ufm_reference_cov", "UFM_COV_FIXTURES")
  if not cases:
    raise SystemExit(f"no cases under {root} (set UFM_COV_FIXTURES or UFM_FIXTURES)")
  for name in cases:
    model, params = ufm_jax.load_official(root / name)
    io = dict(np.load(root / name / "io.npz"))
    out = jax.jit(model.apply)(ufm.variables(params), io["img1_uint8"], io["img2_uint8"])
    print(f"{name}: {type(model).__name__}, adaptors {model.config.flow_head_adaptors} / "
          f"{model.config.uncertainty_head_adaptors}, {model.config.flow_covariance}")
    if "flow_covariance" not in io:
      print("  io.npz has no flow_covariance")
      continue
    want = io["flow_covariance"].transpose(0, 2, 3, 1)
    var, cov = errors(out["flow_covariance"], want)
    w = want.astype(np.float64)
    g = 1 - w[..., 2] ** 2 / (w[..., 0] * w[..., 1])
    ld = np.abs(np.asarray(out["flow_covariance_log_det"]) - io["flow_covariance_log_det"][:, 0])
    ivar, icov = errors(out["flow_covariance_inv"], io["flow_covariance_inv"].transpose(0, 2, 3, 1))
    print(f"  forward: var {var:.2e}, cov_xy {cov:.2e} of sqrt(var_x var_y); log det {ld.max():.2e}"
          f" (at 1 - rho^2 = {g.flat[ld.argmax()]:.1e}; {ld[g > 1e-2].max():.2e} where > 0.01);"
          f" inverse var {ivar:.2e}, cov_xy {icov:.2e}")
    for pair in ("hl0", "hl1", "hl2"):
      if f"{pair}_flow_covariance" in io:
        got = ufm_jax.predict(model, params, io[f"{pair}_src_uint8"], io[f"{pair}_tgt_uint8"])
        want = io[f"{pair}_flow_covariance"][0].transpose(1, 2, 0)
        var, cov = errors(got["flow_covariance"], want)
        print(f"  predict {pair}: var {var:.2e}, cov_xy {cov:.2e}")


if __name__ == "__main__":
  main()
