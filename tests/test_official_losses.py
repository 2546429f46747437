"""The training losses against the official training code (fixtures in UFM_TRAINING_FIXTURES,
`losses/`): every case that `cases.json` lists, each loss file's term and every recipe's whole
`train_loss` run in config order.

Values within 1e-5 relative, gradients (jax.grad of our loss w.r.t. the same inputs) within 1e-4
of each gradient's largest magnitude, and every logged scalar the official code logs.
"""

import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ufm_jax import testing
from ufm_jax.training import losses

pytestmark = pytest.mark.official_training

NON_CASE_KEYS = ("generator", "provenance", "recipe_totals")


def _discover():
  path = testing.training_fixtures_root() / "losses" / "cases.json"
  try:
    spec = json.loads(path.read_text())
  except OSError:
    return [pytest.param(None, None, id="fixtures-missing")]
  out = [pytest.param(k, c, id=f"{k}-{c}") for k, v in spec.items() if k not in NON_CASE_KEYS
         for c in v["cases"]]
  out += [pytest.param("recipe_totals", r, id=f"recipe_totals-{r}")
          for r in spec.get("recipe_totals", {})]
  return out


def _nhwc(x):
  return jnp.asarray(np.moveaxis(x, 1, -1))


def _official_key(ours: str) -> str:
  """Our log key in the fixtures' spelling ('@' -> '_at_', '/' and '[' -> '_', ']' dropped)."""
  return ours.replace("@", "_at_").replace("/", "_").replace("[", "_").replace("]", "")


def _inputs(z, pre):
  """(differentiable outputs, batch, suitable_rows) from the fixture arrays of one case."""
  g = lambda k: z[pre + k] if pre + k in z.files else None  # noqa: E731
  outputs = {}
  flow = g("pred_flow") if g("pred_flow") is not None else g("regression_flow")
  if flow is not None:
    outputs["flow"] = _nhwc(flow)
  if g("covis_logits") is not None:
    outputs["covisibility_logits"] = jnp.asarray(g("covis_logits")[:, 0])
  gt = g("gt_flow")
  if gt is None:                      # the BCE cases hold no flow
    logits = g("covis_logits")
    gt = np.zeros((logits.shape[0], 2) + logits.shape[2:], np.float32)
  for k in ("feature_map_0", "feature_map_1"):
    if g(k) is not None:
      outputs[k] = _nhwc(g(k))
  if g("attention_bias") is not None:
    outputs["attention_bias"] = jnp.asarray(g("attention_bias"))
  if g("log_softmax") is not None:
    outputs["log_softmax"] = jnp.asarray(g("log_softmax"))
  covis = g("non_occluded_mask")
  if covis is None:                   # the 'all' range reads no mask
    covis = np.zeros(gt.shape[:1] + gt.shape[2:], bool)
  batch = {"flow": _nhwc(gt), "covisibility": jnp.asarray(covis)}
  sup = g("occlusion_supervision_mask")
  batch["covis_valid"] = jnp.asarray(sup if sup is not None else np.zeros_like(covis))
  rows = g("suitable_for_refinement")
  return outputs, batch, None if rows is None else jnp.asarray(rows)


def _grad_keys(name):
  """Fixture names of the gradient w.r.t. one of our outputs."""
  return {"flow": ("pred_flow", "regression_flow"),
          "covisibility_logits": ("covis_logits",)}.get(name, (name,))


def _close(ours, ref, what):
  ours, ref = float(ours), float(ref)
  if math.isnan(ref):
    assert math.isnan(ours), f"{what}: {ours} vs NaN"
    return
  tol = 1e-5 * abs(ref) if ref != 0 else 1e-7
  assert abs(ours - ref) <= tol, f"{what}: ours {ours!r} vs official {ref!r}"


@pytest.mark.parametrize("kind,case", _discover())
def test_loss_matches_official(kind, case):
  folder = testing.training_fixtures("losses")
  spec = json.loads((folder / "cases.json").read_text())
  if kind == "recipe_totals":
    entry = spec["recipe_totals"][case]
    configs = entry["term_configs"]
    names = entry["terms_in_order"]
  else:
    entry = spec[kind]["cases"][case]
    configs = None
  z = np.load(folder / f"{kind}.npz")
  pre = f"{case}_"
  if configs is None:
    names = [k[len(pre) + 5:] for k in z.files
             if k.startswith(pre + "loss_") and k != pre + "loss_total"]
    assert len(names) == 1, names
    configs = {names[0]: spec[kind]["config"]}
  temperature = float(z[pre + "temperature"]) if pre + "temperature" in z.files else None
  recipe = losses.Recipe(
      tuple((n, losses.make_term(losses.from_official(configs[n]["class"], configs[n]["kwargs"]),
                                 n)) for n in names), temperature=temperature)
  outputs, batch, rows = _inputs(z, pre)

  def total(out):
    return recipe(out, batch, suitable_rows=rows)

  (loss, aux), grads = jax.value_and_grad(total, has_aux=True)(outputs)
  _close(loss, z[pre + "loss_total"], f"{kind}/{case} total")
  for n in names:
    _close(aux[f"loss_{n}"], z[pre + f"loss_{n}"], f"{kind}/{case} {n}")
    ours = {f"{pre}log_{n}__{_official_key(k[len(n) + 1:])}": v for k, v in aux.items()
            if k.startswith(n + "/")}
    logged = [k for k in z.files if k.startswith(f"{pre}log_{n}__")]
    assert logged and set(logged) <= set(ours), sorted(set(logged) - set(ours))
    for k in logged:
      _close(ours[k], z[k], f"{kind}/{case} log {k[len(pre):]}")
  checked = 0
  for name, g in grads.items():
    key = next((pre + "grad_" + k for k in _grad_keys(name) if pre + "grad_" + k in z.files), None)
    if key is None:
      continue
    checked += 1
    ref = z[key]
    ours = np.asarray(g)
    if ref.ndim == 4 and ours.ndim == 4 and name != "log_softmax":
      ours = np.moveaxis(ours, -1, 1)
    elif name == "covisibility_logits":
      ours = ours[:, None]
    scale = float(np.abs(ref).max())
    err = float(np.abs(ours - ref).max())
    assert err <= 1e-4 * scale + (0.0 if scale else 1e-12), \
        f"{kind}/{case} d/d{name}: max error {err:.3g} vs max |grad| {scale:.3g}"
  assert checked == len([k for k in z.files if k.startswith(pre + "grad_")]), "gradient not compared"


def _all_range_cases():
  """The cases whose every term is an 'all'-range regression (robust_epe_all_pixels, the 980
  recipe's total)."""
  path = testing.training_fixtures_root() / "losses" / "cases.json"
  try:
    spec = json.loads(path.read_text())
  except OSError:
    return [pytest.param(None, None, id="fixtures-missing")]
  out = []
  for kind, v in spec.items():
    if kind in NON_CASE_KEYS:
      continue
    if v["config"]["kwargs"].get("supervision_range") == "all":
      out += [pytest.param(kind, c, id=f"{kind}-{c}") for c in v["cases"]]
  for r, e in spec.get("recipe_totals", {}).items():
    if all(c["kwargs"].get("supervision_range") == "all" for c in e["term_configs"].values()):
      out.append(pytest.param("recipe_totals", r, id=f"recipe_totals-{r}"))
  return out


@pytest.mark.parametrize("kind,case", _all_range_cases())
def test_all_range_reads_no_mask(kind, case):
  """The 'all' range on a row whose masks are all False, as the official FlyingChairs second
  view (zero flow, every mask False: `backward_zero_flow`): the official test reads the flow
  alone (loss/epe.py:63-69), so the official loss and gradient come out with covisibility and
  covis_valid all False, and the pixels our term supervises are the official mask
  (`all_pixels_fov_mask`, what the official loss used)."""
  folder = testing.training_fixtures("losses")
  spec = json.loads((folder / "cases.json").read_text())
  z = np.load(folder / f"{kind}.npz")
  pre = f"{case}_"
  configs = (spec["recipe_totals"][case]["term_configs"] if kind == "recipe_totals" else
             {k[len(pre) + 5:]: spec[kind]["config"] for k in z.files
              if k.startswith(pre + "loss_") and k != pre + "loss_total"})
  recipe = losses.Recipe(tuple(
      (n, losses.make_term(losses.from_official(c["class"], c["kwargs"]), n))
      for n, c in configs.items()))
  outputs, batch, _ = _inputs(z, pre)
  off = jnp.zeros(batch["flow"].shape[:3], bool)
  batch = dict(batch, covisibility=off, covis_valid=off, flow_valid=~off)
  (loss, _), grads = jax.value_and_grad(lambda o: recipe(o, batch), has_aux=True)(outputs)
  _close(loss, z[pre + "loss_total"], f"{kind}/{case} total with every mask False")
  ref = z[pre + "grad_pred_flow"]
  err = float(np.abs(np.moveaxis(np.asarray(grads["flow"]), -1, 1) - ref).max())
  assert err <= 1e-4 * float(np.abs(ref).max()), err
  if pre + "all_pixels_fov_mask" in z.files:
    mask, _ = recipe.terms[0][1].mask(batch, batch["flow"])
    np.testing.assert_array_equal(np.asarray(mask), z[pre + "all_pixels_fov_mask"])


def _refinement_cases():
  """The cases with the efficient refinement loss (its own file and the refine recipes' totals)."""
  path = testing.training_fixtures_root() / "losses" / "cases.json"
  try:
    spec = json.loads(path.read_text())
  except OSError:
    return [pytest.param(None, None, id="fixtures-missing")]
  cls = "RefinementCrossEntropyLossEfficient"
  out = [pytest.param(k, c, id=f"{k}-{c}") for k, v in spec.items() if k not in NON_CASE_KEYS
         and v["config"]["class"] == cls for c in v["cases"]]
  out += [pytest.param("recipe_totals", r, id=f"recipe_totals-{r}")
          for r, e in spec.get("recipe_totals", {}).items()
          if any(c["class"] == cls for c in e["term_configs"].values())]
  return out


@pytest.mark.parametrize("kind,case", _refinement_cases())
def test_refinement_gradient_in_the_jitted_step(kind, case):
  """The bfloat16 taps' gradient as the train step computes it (jitted: XLA may keep a fused sum
  of bfloat16 terms in float32, which the official autograd rounds after every term): the
  official value everywhere but at bfloat16 rounding ties (`refine_training._bf16_window_blend`):
  at most 0.1% of the nonzero entries beyond 1e-4 of the max, none beyond one bfloat16 ulp of it
  (2^-8). Summing the four terms in another order, or without the roundings, puts thousands of
  entries 1.7e-3 to 6.9e-3 of the max off."""
  folder = testing.training_fixtures("losses")
  spec = json.loads((folder / "cases.json").read_text())
  z = np.load(folder / f"{kind}.npz")
  pre = f"{case}_"
  if kind == "recipe_totals":
    configs = spec["recipe_totals"][case]["term_configs"]
    names = spec["recipe_totals"][case]["terms_in_order"]
  else:
    names = [k[len(pre) + 5:] for k in z.files
             if k.startswith(pre + "loss_") and k != pre + "loss_total"]
    configs = {names[0]: spec[kind]["config"]}
  recipe = losses.Recipe(
      tuple((n, losses.make_term(losses.from_official(configs[n]["class"], configs[n]["kwargs"]),
                                 n)) for n in names), temperature=float(z[pre + "temperature"]))
  outputs, batch, rows = _inputs(z, pre)
  step = jax.jit(jax.value_and_grad(lambda o: recipe(o, batch, suitable_rows=rows)[0]))
  loss, grads = step(outputs)
  _close(loss, z[pre + "loss_total"], f"{kind}/{case} total (jitted)")
  for name in ("feature_map_0", "feature_map_1"):
    ref = z[pre + "grad_" + name]
    scale = float(np.abs(ref).max())
    if not scale:
      continue
    err = np.abs(np.moveaxis(np.asarray(grads[name]), -1, 1) - ref)
    beyond = int((err > 1e-4 * scale).sum())
    assert beyond <= 0.001 * np.count_nonzero(ref), (name, beyond, float(err.max()) / scale)
    assert float(err.max()) <= 2.0 ** -8 * scale, (name, float(err.max()) / scale)
