"""The student variants: their sizes, ufm_small's encoder loading from facebook/dinov2-small's
files, and ufm_small / ufm_tiny exporting to official snapshots that load back to the same model
and parameters, as tests/test_to_official.py checks the others. (A distilled workdir through
every tool: tests/test_distill_train.py.)"""

import json

import jax
import numpy as np
import pytest

import ufm_jax
from ufm_jax import testing
from ufm_jax.training import model_init, optim
from ufm_jax.models import ufm, variants
from ufm_jax.official import config as official_config
from ufm_jax.official import snapshot
from ufm_jax.testing import param_counts as pc


def _count(name):
  return optim.count_params(ufm.param_shapes(variants.build_model(name)))["total"]


def _synth_count(mlp_hidden, covis_dims, covis_f):
  """synth's structure (7 px patches on an 8 x 8 grid, 2 encoder and 3 fusion blocks 64 wide,
  16-wide flow DPT) with the given MLP width and covisibility head, in closed form."""
  return (pc.dinov2_count(64, 2, patch=7, grid=8, hidden=mlp_hidden)
          + pc.fusion_count(64, 64, 3, mlp_hidden)
          + pc.dpt_count((64,) * 4, (16, 16, 32, 32), 16, 2)
          + pc.dpt_count((64,) * 4, covis_dims, covis_f, 1))


def _student_count(dim, depth, layer_dims, f):
  """ViT-S/14 whole, a `depth` x `dim` fusion (MLP ratio 4), two DPT heads (flow, covisibility)."""
  return (pc.dinov2_count(384, 12) + pc.fusion_count(384, dim, depth, 4 * dim)
          + sum(pc.dpt_count((384, dim, dim, dim), layer_dims, f, out) for out in (2, 1)))


def test_student_sizes():
  """synth_small at most half of synth (the demonstration's bound); the real students well
  below UFM-Base, their encoder the whole ViT-S/14. Each count against the closed form of its
  structure (ufm_jax.testing.param_counts), as in the docstrings: synth_small is synth with MLPs
  of ratio 1/4 (16 wide) and a covisibility head of layer dims [8, 8, 16, 16], feature dim 8."""
  synth, small = _synth_count(256, (16, 16, 32, 32), 16), _synth_count(16, (8, 8, 16, 16), 8)
  assert _count("synth") == synth and _count("synth_small") == small and 2 * small <= synth
  assert _count("ufm_small") == _student_count(384, 6, (48, 96, 192, 384), 128)
  assert _count("ufm_tiny") == _student_count(256, 4, (24, 48, 96, 192), 64)
  for name in ("ufm_small", "ufm_tiny"):
    cfg = variants.get(name)
    assert cfg.encoder.embed_dim == 384 and cfg.encoder.depth == 12 and cfg.encoder.num_heads == 6
    assert official_config.official_limits(cfg) == []   # nothing the official format drops


def test_ufm_small_encoder_initialises_from_dinov2_small(tmp_path):
  """model_init=dinov2:DIR with facebook/dinov2-small's file layout (transformers naming, 12 x
  384, a 37 x 37 position table): every encoder parameter is loaded, nothing else is."""
  from safetensors.numpy import save_file
  folder = tmp_path / "dinov2-small"
  folder.mkdir()
  save_file(testing.hf_dinov2(depth=12, dim=384, grid=37), str(folder / "model.safetensors"))
  (folder / "config.json").write_text(json.dumps({"model_type": "dinov2", "hidden_size": 384}))
  model = variants.build_model("ufm_small")
  template = jax.tree.map(lambda a: np.zeros(a.shape, a.dtype), ufm.variable_shapes(model))
  _, report = model_init.load_init_variables(f"dinov2:{folder}", template, model.config)
  encoder = [k for k in model_init.flatten(template["params"]) if k.startswith("encoder/")]
  assert sorted(report.loaded) == sorted(encoder)
  assert not [k for k in report.left_at_init if k.startswith("encoder/")]


@pytest.mark.slow
@pytest.mark.parametrize("name", ["ufm_small", "ufm_tiny"])
def test_students_export_to_official_and_load_back(tmp_path, name):
  cfg = variants.get(name)
  model = ufm.model_from_config(cfg)
  params = testing.perturbed_params(model, 1)
  ufm_jax.save_official(model, {"params": params}, tmp_path / "snap")
  conf = json.loads((tmp_path / "snap" / "config.json").read_text())
  assert conf["encoder_kwargs"]["name"] == "dinov2_small"
  back_model, back_variables = snapshot.load_official(tmp_path / "snap")
  assert back_model.config == cfg
  jax.tree.map(np.testing.assert_array_equal, back_variables["params"], params)
  from safetensors import safe_open
  with safe_open(str(tmp_path / "snap" / "model.safetensors"), "np") as f:
    shapes = {k: tuple(f.get_slice(k).get_shape()) for k in f.keys()}
  depth, dim = cfg.info_sharing.depth, cfg.info_sharing.dim
  # official names and torch layouts, from the module definitions (timm / UniCeption)
  assert shapes["encoder.model.blocks.11.mlp.fc1.weight"] == (1536, 384)
  assert shapes[f"info_sharing.self_attention_blocks.{depth - 1}.attn.qkv.weight"] == (3 * dim,
                                                                                        dim)
  assert ("info_sharing.proj_embed.weight" in shapes) == (dim != 384)
  assert shapes["head1.0.1.conv1.weight"][1] == cfg.flow_head.feature_dim


def test_synth_small_starts_from_its_teacher(tmp_path):
  """model_init=teacher:SRC (configs/distill.py init=teacher; the default is init=fresh):
  every parameter synth_small shares with synth by path and shape comes from the teacher (the
  attention and the flow head), the narrower MLPs and covisibility head stay at init and are
  listed with both shapes; a plain ckpt: source of
  the other structure is still refused."""
  from flax import traverse_util
  from ufm_jax.runtime import model_io
  from ufm_jax.training import teacher as teacher_lib
  teacher = variants.build_model("synth")
  tv = teacher_lib.random_variables(teacher, seed=3)
  model_io.save(tmp_path / "teacher", teacher, tv)
  student = variants.build_model("synth_small")
  template = jax.tree.map(lambda a: np.zeros(a.shape, a.dtype), ufm.variable_shapes(student))
  out, report = model_init.load_init_variables(f"teacher:{tmp_path / 'teacher'}", template,
                                               student.config)
  flat_t = traverse_util.flatten_dict(tv["params"], sep="/")
  flat_o = traverse_util.flatten_dict(out["params"], sep="/")
  assert report.loaded and report.left_at_init
  for k in report.loaded:
    np.testing.assert_array_equal(flat_o[k], flat_t[k], err_msg=k)
  left = [k.split(" ")[0] for k in report.left_at_init]
  assert any("mlp" in k for k in left) and any(k.startswith("uncertainty_head") for k in left)
  # the attention and the flow head (head1) are the teacher's
  assert not any("attn" in k or k.startswith("head1") for k in left)
  assert any(k.startswith("head1") for k in report.loaded)
  for k in left:
    assert not np.any(np.asarray(flat_o[k])), k       # the template's (zeros here)
  # Copied: everything but the 5 blocks' 16-wide MLPs and the 8-wide covisibility head, except
  # the arrays whose shape does not depend on those widths (fc2's bias, 64; the head's last
  # bias, 1): the figure the training log prints.
  mlp_kernels = pc.mlp(64, 16) - 64
  covis = pc.dpt_count((64,) * 4, (8, 8, 16, 16), 8, 1) - 1
  small = _count("synth_small")
  assert report.copied_values == small - 5 * mlp_kernels - covis
  assert report.total_values == small
  assert f"{small - 5 * mlp_kernels - covis:,} of the model's {small:,}" in report.summary()
  with pytest.raises(ValueError):
    model_init.load_init_variables(f"ckpt:{tmp_path / 'teacher'}", template, student.config)
