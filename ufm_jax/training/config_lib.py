"""Building blocks of the training configs in configs/ (plain functions returning ConfigDicts),
and `load_config`, which reads a config file the way train.py's --config flag does.

Configs import this package, never the reverse; each config file stands alone (no config imports
another), so any of them loads from its path alone.
"""

from __future__ import annotations

import importlib.util
import pathlib

import ml_collections

from ufm_jax.data import mixture


class ConfigArgError(ValueError):
  """A bad `config.py:key=value` argument; its message is one line naming the valid keys or
  values (train.py prints it alone, without a traceback)."""


def parse_arg(arg: str | None, **defaults) -> ml_collections.ConfigDict:
  """big_vision-style `get_config(arg)` parsing: "data=of,res=980" -> ConfigDict over defaults.

  Values are converted to the type of their default (bool accepts true/false/1/0). A malformed
  item, an unknown key or a value of the wrong type raises ConfigArgError.
  """
  out = ml_collections.ConfigDict(defaults)
  for item in filter(None, (arg or "").split(",")):
    if "=" not in item:
      raise ConfigArgError(f"config arg {item!r} is not key=value; valid keys: "
                           f"{', '.join(sorted(defaults))}")
    key, value = item.split("=", 1)
    if key not in defaults:
      raise ConfigArgError(f"unknown config arg {key!r}; valid keys: {', '.join(sorted(defaults))}")
    default = defaults[key]
    if isinstance(default, bool):
      if value.lower() not in ("true", "false", "1", "0"):
        raise ConfigArgError(f"config arg {key}={value!r} is not a bool; valid values: true, "
                             "false, 1, 0")
      value = value.lower() in ("true", "1")
    elif default is not None:
      try:
        value = type(default)(value)
      except ValueError:
        raise ConfigArgError(f"config arg {key}={value!r} is not {type(default).__name__} "
                             f"(default {default!r})") from None
    out[key] = value
  return out


def unset(field_type) -> ml_collections.FieldReference:
  """A None default that `--config.KEY=VALUE` can still set: ml_collections refuses to override
  a plain None field from the command line, since it cannot tell the value's type."""
  return ml_collections.FieldReference(None, field_type=field_type)


def training_defaults(c: ml_collections.ConfigDict) -> ml_collections.ConfigDict:
  """The machinery keys every UFM training config shares (mesh, sharding, checkpoints, logging);
  the recipe itself (optim, loss, model, input) is written out in each config file."""
  c.seed = 0
  c.total_steps = unset(int)    # None: num_epochs * (pairs per epoch // batch size)
  # FSDP over every device: the train state (params, AdamW moments) sharded, the batch split over
  # all of them; the sharding the planner sizes (docs/scale.md). "data:-1,fsdp:1" replicates the
  # state on every device; "data:2,fsdp:-1" shards it within each half (e.g. within the nodes of
  # a multi-node GPU run, where gathers over the slower inter-node network would cost more).
  c.mesh = "data:1,fsdp:-1"
  # FSDP over the largest divisible dimension; tensors under `sharding_min_size` entries (biases,
  # norms, layer scales) stay replicated.
  c.sharding_rules = [(r".*", "fsdp")]
  c.sharding_min_size = 2 ** 14
  # "layer": the scanned blocks are gathered a layer at a time inside the scan; "step": every
  # param is gathered at the start of the step (ufm_jax.training.sharding.fsdp_gathers).
  c.fsdp_gather = "layer"
  # Microbatches per optimizer step (gradient accumulation, ufm_jax.training.accumulation): the recipe's
  # batch on a slice whose chips hold only a 1/grad_accum share of it. 1: the whole batch at once.
  c.grad_accum = 1
  c.ckpt_steps = 1000
  c.keep_ckpt = 3
  c.async_checkpoint = True
  c.log_training_steps = 50
  c.device_prefetch = 2         # global batches transferred ahead of the step (1: none ahead)
  # Consecutive updates skipped for a non-finite loss or gradient before the run stops with exit
  # status 1 (a diverged run; restarting it would only replay the divergence). 0: never stop.
  c.max_nonfinite_steps = 100
  c.apply_kwargs = {"symmetrized": True}  # rows (2i, 2i+1) are (a, b), (b, a): encode once
  c.matmul_precision = unset(str)  # e.g. "highest": float32 matmuls in full float32 on GPU
  # "A:B": a jax.profiler trace of steps A..B-1 under WORKDIR/profile (training/profiling.py).
  c.profile_steps = unset(str)
  return c


def model_options(dtype: str = "bfloat16", remat: bool = True, scan_blocks: bool = True,
                  head_dtype: str = "float32") -> ml_collections.ConfigDict:
  """The `model` block: UFMConfig compute options passed to the variant (trainer.build_model).

  Every option is present so each can be overridden from the command line (the block is locked):
  `--config.model.attention_impl=cudnn|xla|cpu` (typed None = auto: cuDNN on GPU for bf16,
  the cache-blocked loop on CPU, XLA elsewhere), `--config.model.scan_blocks=False` (unrolled blocks: slower compile, same numbers),
  `--config.model.head_dtype=bfloat16` (DPT heads in bf16; the official heads are float32).
  """
  return ml_collections.ConfigDict({
      "dtype": dtype, "remat": remat, "scan_blocks": scan_blocks, "head_dtype": head_dtype,
      "attention_impl": unset(str)})


def add_flow_covariance(c: ml_collections.ConfigDict, pixels: str, head: str = "uncertainty",
                        head_output_dim: int | None = None,
                        multiplier: float = 1.0) -> ml_collections.ConfigDict:
  """The `cov=True` switch of a recipe: a flow covariance adaptor (exp_tanh, low_confidence_init)
  in the uncertainty head before its covisibility channel, or with head="main" in the flow head
  after the flow (the sorted orders an official snapshot reloads in; the head's output_dim grows
  by 3 from `head_output_dim`, default 1 for the uncertainty head and 2 for the main), and the
  Gaussian NLL term `flow_nll` (ufm_jax.training.losses.FlowCovarianceNLL; `likelihood` "laplace" for
  the elliptical Laplace) on the pixels of the flow term `pixels`, added after the recipe's
  terms. Returns `c`."""
  if head == "uncertainty":
    c.model.covisibility_head = {"output_dim": (head_output_dim or 1) + 3}
    c.model.uncertainty_head_adaptors = ("flow_cov", "non_occluded_mask")
  elif head == "main":
    c.model.flow_head = {"output_dim": (head_output_dim or 2) + 3}
    c.model.flow_head_adaptors = ("flow", "flow_cov")
  else:
    raise ValueError(f"add_flow_covariance: head {head!r}; expected 'uncertainty' or 'main'")
  c.model.flow_covariance = {"parametrization": "exp_tanh", "low_confidence_init": True}
  c.loss.terms = tuple(c.loss.terms) + ("flow_nll",)
  c.loss.flow_nll = {"type": "flow_nll", "pixels": pixels, "multiplier": multiplier,
                     "detach_flow": True, "likelihood": "gaussian", "eps": 1e-4}
  return c


def bench_eval(bench="sintel", every=5000, max_pairs=200, resolution="560",
               data_root=mixture.DEFAULT_DATA_ROOT) -> ml_collections.ConfigDict:
  """An `evals` entry that runs a benchmark of ufm_jax.evaluators during training."""
  return ml_collections.ConfigDict({"type": "bench", "bench": bench, "every": every,
                                    "max_pairs": max_pairs, "resolution": resolution,
                                    "data_root": data_root})


def load_config(spec: str) -> ml_collections.ConfigDict:
  """`"configs/synthetic.py:steps=4"` -> get_config("steps=4") of that file (as --config does)."""
  path, _, arg = str(spec).partition(":")
  path = pathlib.Path(path)
  if not path.is_file():
    raise FileNotFoundError(f"config file not found: {path}")
  module_spec = importlib.util.spec_from_file_location(f"_ufm_config_{path.stem}", path)
  module = importlib.util.module_from_spec(module_spec)
  module_spec.loader.exec_module(module)
  return module.get_config(arg or None)
