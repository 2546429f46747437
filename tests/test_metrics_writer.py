"""trainer.Writer: metrics files stay standard JSON when a metric is undefined (NaN), and
TensorBoard gets only finite scalars (tensorboardX warns on every NaN event otherwise)."""

import json
import math

from ufm_jax.training import trainer


def _strict(line):
  def refuse(name):
    raise ValueError(f"non-standard JSON constant {name}")
  return json.loads(line, parse_constant=refuse)


class _TB:
  def __init__(self):
    self.scalars = {}

  def add_scalar(self, tag, value, step):
    self.scalars[tag] = value

  def flush(self):
    pass


def test_undefined_metrics_are_null_in_json_and_absent_from_tensorboard(tmp_path):
  w = trainer.Writer(tmp_path, active=True)
  w.close()
  w.tb = _TB()
  w.scalars("eval.jsonl", 5, {"step": 5, "epe": 1.5, "epe_occluded": math.nan,
                              "loss": math.inf, "num_pairs": 32}, "eval/heldout")
  rec = _strict((tmp_path / "eval.jsonl").read_text().splitlines()[-1])
  assert rec == {"step": 5, "epe": 1.5, "epe_occluded": None, "loss": None, "num_pairs": 32}
  assert w.tb.scalars == {"eval/heldout/epe": 1.5, "eval/heldout/num_pairs": 32}
