"""metrics.sample_matches: the near-linear KDE keeps RoMa's KDE-balanced sampling distribution.

RoMa's `sample` draws 4 num candidates by certainty, then num of them proportional to
1 / (1 + density), density[i] = sum_j exp(-|x_i - x_j|^2 / (2 sigma^2)) over the candidates in
the normalised 4-D match space (1e-7 where density < 10). The grid KDE must give the same
densities (its documented bound: 1% where density >= 10) and the same sampling distribution as
the exact pairwise sum, which is the sampler as it was before the grid.
"""

import statistics

import numpy as np
import pytest

from ufm_jax.evaluators import metrics


def _definition(x, sigma):
  """The density from its definition: all pairs, float64."""
  x = np.asarray(x, np.float64)
  return np.concatenate([np.exp(-((x[i:i + 500, None] - x[None]) ** 2).sum(-1)
                                / (2 * sigma**2)).sum(1) for i in range(0, len(x), 500)])


def _match_space(n, seed=0, h=420, w=560):
  """n candidates as sample_matches builds them: source pixels and pixel + a smooth flow that
  folds part of the image onto a narrow band (a dense cluster), normalised to [-1, 1]."""
  rng = np.random.default_rng(seed)
  ys, xs = rng.integers(0, h, n), rng.integers(0, w, n)
  k0 = np.stack([xs, ys], 1).astype(np.float64)
  x1 = np.where(xs < w / 2, 0.2 * xs, xs) + 6 * np.sin(ys / 50.0)
  k1 = np.stack([np.clip(x1, 0, w - 1), ys + 5 * np.cos(xs / 70.0)], 1)
  return np.concatenate([(k0 + 0.5) / [w, h] * 2 - 1, (k1 + 0.5) / [w, h] * 2 - 1],
                        1).astype(np.float32)


def test_exact_kde_is_the_definition():
  x = _match_space(700)
  np.testing.assert_allclose(metrics.kde_density(x, 0.1, "exact"), _definition(x, 0.1),
                             rtol=1e-4)
  # auto keeps the exact sum for small draws
  assert np.array_equal(metrics.kde_density(x, 0.1), metrics.kde_density(x, 0.1, "exact"))


@pytest.mark.parametrize("sigma", [0.1, 0.25])
def test_grid_kde_within_its_bound(sigma):
  x = _match_space(5000, seed=1)
  exact = _definition(x, sigma)
  grid = metrics.kde_density(x, sigma, "grid")
  counted = exact >= 10            # below 10 the sampler uses the constant 1e-7 instead
  assert counted.mean() > 0.9
  rel = np.abs(grid / exact - 1)[counted]
  assert rel.max() < 0.01, rel.max()


def _scene(h=20, w=30):
  """A flow whose left half is squeezed onto a fifth of the target width (candidates there are
  dense in match space, so balancing changes their share) and a graded covisibility with a
  zero band."""
  ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
  x1 = np.where(xs < w / 2, 0.2 * xs, xs)
  flow = np.stack([x1 - xs, np.zeros_like(xs)], -1)
  covis = np.clip((ys + 1) / h + 0.3 * np.sin(xs / 3.0), 0, 1)
  covis[:, w // 2 - 2:w // 2 + 2] = 0
  return flow, covis


def _counts(flow, covis, seeds, **kw):
  """How often each source pixel is drawn over one sample_matches call per seed."""
  counts = np.zeros(flow.shape[0] * flow.shape[1])
  for seed in seeds:
    _, _, idx = metrics.sample_matches(flow, covis, 100, np.random.default_rng(seed),
                                       return_index=True, **kw)
    np.add.at(counts, idx, 1)
  return counts


def _chi2_critical(dof, alpha):
  """Upper alpha point of chi-square(dof) (Wilson-Hilferty; within 1% for dof >= 30)."""
  z = statistics.NormalDist().inv_cdf(1 - alpha)
  return dof * (1 - 2 / (9 * dof) + z * (2 / (9 * dof)) ** 0.5) ** 3


def _homogeneity(a, b):
  """Two-sample chi-square over the pixels (equal totals): (statistic, degrees of freedom)."""
  assert a.sum() == b.sum()
  used = (a + b) > 0
  return float((((a - b) ** 2)[used] / (a + b)[used]).sum()), int(used.sum()) - 1


def test_grid_sampler_has_the_exact_samplers_distribution():
  flow, covis = _scene()
  runs = 200    # 20000 draws per sampler over ~560 drawable pixels (~35 per pixel)
  # sigma 0.25 keeps the grid small (20^4 nodes) for these calls; its relative spacing is the same
  grid = _counts(flow, covis, range(runs), kde="grid", kde_sigma=0.25)
  exact = _counts(flow, covis, range(runs, 2 * runs), kde="exact", kde_sigma=0.25)
  stat, dof = _homogeneity(grid, exact)
  # Draws without replacement are negatively correlated within a call, which only lowers the
  # statistic: the multinomial critical value is conservative.
  assert stat < _chi2_critical(dof, 1e-3), (stat, dof)
  # The test has the power to see the balancing: certainty-only sampling is rejected.
  plain = _counts(flow, covis, range(2 * runs, 3 * runs), balanced=False)
  stat, dof = _homogeneity(plain, exact)
  assert stat > _chi2_critical(dof, 1e-3), (stat, dof)


def test_unknown_kde_method():
  with pytest.raises(ValueError, match="kde method 'fast'"):
    metrics.kde_density(np.zeros((3, 4), np.float32), 0.1, "fast")
