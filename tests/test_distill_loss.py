"""The distillation terms (ufm_jax.training.distill_loss) by hand: the robust EPE against the teacher's
flow on its covisible pixels, weighted by its covariance where it has one; the soft-target BCE
with either rule for matches that leave the crop; both in a recipe whose batch holds no label."""

import jax.numpy as jnp
import numpy as np
import pytest

from ufm_jax.training import losses
from ufm_jax.training.distill_loss import TeacherCovisibility, TeacherFlow


def _robust(sq, alpha, c):
  b = abs(alpha - 2)
  return b / alpha * ((sq / c ** 2 / b + 1) ** (alpha / 2) - 1)


def _batch(seed=0, cov=False):
  rng = np.random.default_rng(seed)
  b, h, w = 2, 5, 6
  out = {"teacher_flow": rng.normal(0, 3, (b, h, w, 2)).astype(np.float32),
         "teacher_covisibility": rng.random((b, h, w)).astype(np.float32),
         "teacher_in_view": rng.random((b, h, w)) < 0.9,
         "teacher_in_crop": rng.random((b, h, w)) < 0.8}
  if cov:
    var = rng.uniform(0.1, 9.0, (b, h, w, 2)).astype(np.float32)
    out["teacher_flow_covariance"] = np.concatenate([var, 0.3 * var[..., :1]], -1)
  pred = rng.normal(0, 3, (b, h, w, 2)).astype(np.float32)
  logits = rng.normal(0, 2, (b, h, w)).astype(np.float32)
  return out, pred, logits


@pytest.mark.parametrize("cov", [False, True])
def test_teacher_flow_by_hand(cov):
  batch, pred, _ = _batch(1, cov)
  term = TeacherFlow()
  loss, logs, _ = term({}, {k: jnp.asarray(v) for k, v in batch.items()},
                       {"pred": jnp.asarray(pred)}, {})
  mask = batch["teacher_in_view"] & batch["teacher_in_crop"] & (batch["teacher_covisibility"] > 0.5)
  per = _robust(np.sum((pred - batch["teacher_flow"]) ** 2, -1), 0.5, 0.24)
  if cov:
    sigma2 = batch["teacher_flow_covariance"][..., :2].mean(-1)
    weight = np.where(mask, 1.0 / (1.0 + sigma2), 0.0)
    want = np.sum(per * weight) / (np.sum(weight) + 1e-4)
    assert "covariance_weight" in logs
  else:
    want = np.sum(per * mask) / (mask.sum() + 1e-4)
  np.testing.assert_allclose(float(loss), want, rtol=1e-5)
  epe = np.linalg.norm(pred - batch["teacher_flow"], axis=-1)
  np.testing.assert_allclose(float(logs["epe@teacher"]), epe[mask].mean(), rtol=1e-5)
  # "off" ignores the covariance
  off, _, _ = TeacherFlow(covariance="off")({}, {k: jnp.asarray(v) for k, v in batch.items()},
                                            {"pred": jnp.asarray(pred)}, {})
  np.testing.assert_allclose(float(off), np.sum(per * mask) / (mask.sum() + 1e-4), rtol=1e-5)


def test_an_uncertain_pixel_counts_less():
  """Two supervised pixels, equal error; the teacher unsure of one (sigma 3 px): the loss moves
  towards the sure pixel's term, weights 1 and 0.1."""
  batch = {"teacher_flow": jnp.zeros((1, 1, 2, 2)), "teacher_in_view": jnp.ones((1, 1, 2), bool),
           "teacher_in_crop": jnp.ones((1, 1, 2), bool),
           "teacher_flow_covariance": jnp.asarray([[[[0.0, 0.0, 0.0], [9.0, 9.0, 0.0]]]])}
  pred = jnp.asarray([[[[1.0, 0.0], [3.0, 0.0]]]])
  loss, logs, _ = TeacherFlow(eps=None)({}, batch, {"pred": pred}, {})
  per = _robust(np.array([1.0, 9.0]), 0.5, 0.24)
  np.testing.assert_allclose(float(loss), (per[0] + 0.1 * per[1]) / 1.1, rtol=1e-5)
  np.testing.assert_allclose(float(logs["covariance_weight"]), 0.55, rtol=1e-5)


@pytest.mark.parametrize("rule", ["not_covisible", "unsupervised"])
def test_teacher_covisibility_is_a_soft_target(rule):
  batch, _, logits = _batch(2)
  loss, logs, _ = TeacherCovisibility(out_of_crop=rule)(
      {"covisibility_logits": jnp.asarray(logits)},
      {k: jnp.asarray(v) for k, v in batch.items()}, {}, {})
  t = batch["teacher_covisibility"]
  p = 1 / (1 + np.exp(-logits.astype(np.float64)))
  ce = -(t * np.log(p) + (1 - t) * np.log(1 - p))
  valid = batch["teacher_in_view"] & (batch["teacher_in_crop"] | (rule == "not_covisible"))
  want = np.sum(ce * valid) / (valid.sum() + 1e-6)
  np.testing.assert_allclose(float(loss), 10 * want, rtol=1e-5)
  entropy = -(t * np.log(t) + (1 - t) * np.log(1 - t))
  np.testing.assert_allclose(float(logs["kl@teacher"]),
                             want - np.sum(entropy * valid) / (valid.sum() + 1e-6), rtol=1e-4,
                             atol=1e-6)


def test_a_recipe_of_teacher_terms_reads_no_label():
  batch, pred, logits = _batch(3)
  recipe = losses.recipe_from_config({"terms": ("teacher_robust", "teacher_bce"),
                                      "teacher_robust": {"type": "teacher_robust"},
                                      "teacher_bce": {"type": "teacher_bce"}})
  out = {"flow": jnp.asarray(pred), "covisibility_logits": jnp.asarray(logits)}
  total, aux = recipe(out, {k: jnp.asarray(v) for k, v in batch.items()})   # no flow, no masks
  assert float(total) == pytest.approx(float(aux["loss_teacher_robust"] + aux["loss_teacher_bce"]))
  with pytest.raises(ValueError, match="no teacher_flow"):
    recipe(out, {"flow": jnp.zeros_like(out["flow"])})
  with pytest.raises(ValueError, match="covariance"):
    TeacherFlow(covariance="maybe")
