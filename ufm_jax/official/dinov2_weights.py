"""Released DINOv2 weights (facebook/dinov2-* on the Hub in transformers' naming, or the original
facebookresearch/dinov2 .pth files) as parameters of UFM's encoder (`models/dinov2.py`), through
the official key map: what `model_init: dinov2:PATH` starts a run from. The model package itself
reads no files and knows no official names.
"""

from __future__ import annotations

import pathlib
import re

import numpy as np

from ufm_jax.data import io
from ufm_jax.official import keymap



def _hf_to_original(sd: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
  """transformers Dinov2Model names -> the original facebookresearch/dinov2 names."""
  out: dict[str, np.ndarray] = {}
  qkv: dict[str, dict[str, np.ndarray]] = {}
  simple = {
      "embeddings.cls_token": "cls_token",
      "embeddings.mask_token": "mask_token",
      "embeddings.position_embeddings": "pos_embed",
      "embeddings.register_tokens": "register_tokens",
      "embeddings.patch_embeddings.projection.weight": "patch_embed.proj.weight",
      "embeddings.patch_embeddings.projection.bias": "patch_embed.proj.bias",
      "layernorm.weight": "norm.weight",
      "layernorm.bias": "norm.bias",
  }
  layer = {
      "norm1": "norm1", "norm2": "norm2",
      "attention.output.dense": "attn.proj",
      "layer_scale1.lambda1": "ls1.gamma", "layer_scale2.lambda1": "ls2.gamma",
      "mlp.fc1": "mlp.fc1", "mlp.fc2": "mlp.fc2",
      "mlp.weights_in": "mlp.w12", "mlp.weights_out": "mlp.w3",  # SwiGLU (ViT-g)
  }
  for key, val in sd.items():
    k = key[len("dinov2."):] if key.startswith("dinov2.") else key
    if k in simple:
      out[simple[k]] = val
      continue
    m = re.fullmatch(r"encoder\.layer\.(\d+)\.(.+)", k)
    if not m:
      out[f"unmapped:{key}"] = val
      continue
    i, rest = m.groups()
    a = re.fullmatch(r"attention\.attention\.(query|key|value)\.(weight|bias)", rest)
    if a:
      qkv.setdefault(f"blocks.{i}.attn.qkv.{a.group(2)}", {})[a.group(1)] = val
      continue
    for src, dst in layer.items():
      if rest.startswith(src + ".") or rest == src:
        out[f"blocks.{i}.{dst}{rest[len(src):]}"] = val
        break
    else:
      out[f"unmapped:{key}"] = val
  for name, parts in qkv.items():
    if set(parts) != {"query", "key", "value"}:
      raise ValueError(f"DINOv2 checkpoint: incomplete q/k/v for {name}: has {sorted(parts)}")
    out[name] = np.concatenate([parts["query"], parts["key"], parts["value"]], axis=0)
  return out


def _flatten_chunks(sd):
  """Chunked checkpoints ("blocks.<chunk>.<i>.") -> flat block indices."""
  if not any(re.match(r"blocks\.\d+\.\d+\.", k) for k in sd):
    return sd
  return {re.sub(r"^blocks\.\d+\.(\d+)\.", r"blocks.\1.", k): v for k, v in sd.items()}


def read_weights(path) -> dict[str, np.ndarray]:
  """DINOv2 weights in the original naming (numpy), from HF safetensors or an original .pth."""
  path = pathlib.Path(path)
  if path.is_dir():
    cands = sorted(path.glob("*.safetensors")) + sorted(path.glob("*.pth"))
    if not cands:
      raise FileNotFoundError(f"no *.safetensors or *.pth DINOv2 weights in {path}")
    path = cands[0]
  if path.suffix == ".safetensors":
    sd = io.read_safetensors(path)
    if any(k.startswith(("embeddings.", "dinov2.embeddings.")) for k in sd):
      sd = _hf_to_original(sd)
  elif path.suffix in (".pth", ".pt"):
    try:
      import torch
    except ImportError as e:
      raise ImportError(f"reading {path} needs torch (pip install 'ufm_jax[torch]'); or use the "
                        "Hugging Face facebook/dinov2-* model.safetensors instead") from e
    obj = torch.load(str(path), map_location="cpu", weights_only=True)
    obj = obj.get("model", obj) if isinstance(obj, dict) else obj
    sd = {k: v.float().numpy() if v.is_floating_point() else v.numpy() for k, v in obj.items()}
  else:
    raise ValueError(f"unknown DINOv2 checkpoint format: {path} (want .safetensors or .pth)")
  sd = _flatten_chunks(sd)
  unmapped = [k for k in sd if k.startswith("unmapped:")]
  if unmapped:
    raise ValueError(f"{path}: keys with no DINOv2 counterpart: {unmapped[:10]}")
  return sd


def load(path) -> dict[str, np.ndarray]:
  """Released DINOv2 weights (`read_weights`) as flat "encoder/a/b" paths of UFM's encoder, through
  the official key map (UniCeption registers the hub model as `encoder.model`): the encoder part
  of `model_init: dinov2:PATH`."""
  out = {}
  for k, v in read_weights(path).items():
    if k == "mask_token":  # deleted by UniCeption: UFM has no masked-token path
      continue
    key = f"encoder.model.{k}"
    out["/".join(keymap.torch_key_to_path(key, v.ndim))] = keymap.torch_to_flax_array(key, v)
  return out
