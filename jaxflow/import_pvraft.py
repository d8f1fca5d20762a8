"""Convert PV-RAFT PyTorch weights into jaxflow parameters for `configs/pvraft.py`.

    python -m jaxflow.import_pvraft WEIGHTS.pth|WEIGHTS.npz --out DIR

WEIGHTS is a PyTorch state_dict of the official RSF (stage 1) or RSF_refine (stage 2) network
(read with torch, an optional dependency), or an .npz of the same arrays: plain PyTorch names, or
names prefixed `rsf/` and `refine/` as in the project's reference file. PyTorch 1x1 convolutions
(`out x in x 1 [x 1]`) become dense kernels (`in x out`). The refinement is imported when its
weights are present: the checkpoint is then a trained stage 2 (config `configs/pvraft.py:stage2`),
so evaluate.py and jaxflow.predict return the refined flow; else the stage-1 network alone
(`configs/pvraft.py`), whose last iteration they return. WORKDIR/NOTE.txt records which.
"""

import argparse
import pathlib
import re

import numpy as np

from jaxflow.errors import CheckpointError, DataError

# (PyTorch module path regex, jaxflow module path template); parameters map by kind below.
_MODULES = [
  (r"(feature|context)_extractor\.feat_conv(\d)\.(fc|gn)(\d)", r"\1_encoder/feat_conv\2/\3\4"),
  (r"corr_block\.out_conv\.0", "correlation/voxel_conv"),
  (r"corr_block\.out_conv\.1", "correlation/voxel_norm"),
  (r"corr_block\.out_conv\.2", "correlation/voxel_act"),
  (r"corr_block\.out_conv\.3", "correlation/voxel_out"),
  (r"corr_block\.knn_conv\.0", "correlation/knn_conv"),
  (r"corr_block\.knn_conv\.1", "correlation/knn_norm"),
  (r"corr_block\.knn_conv\.2", "correlation/knn_act"),
  (r"corr_block\.knn_out", "correlation/knn_out"),
  (r"update_block\.motion_encoder\.(conv_corr|conv_flow|conv)", r"update/motion_encoder/\1"),
  (r"update_block\.gru\.(conv[zrq])", r"update/gru/\1"),
  (r"update_block\.flow_head\.conv1", "update/flow_head/conv1"),
  (r"update_block\.flow_head\.setconv\.(fc|gn)(\d)", r"update/flow_head/setconv/\1\2"),
  (r"update_block\.flow_head\.out_conv\.([02])", r"update/flow_head/out_conv\1"),
  (r"refine(?:_block)?\.ref_conv(\d)\.(fc|gn)(\d)", r"refine/ref_conv\1/\2\3"),
  (r"refine(?:_block)?\.fc", "refine/fc"),
]


def _canonical(name: str) -> str:
  """Strips DataParallel's `module.` and the reference file's `rsf/` / `refine/` prefixes."""
  name = name.removeprefix("module.")
  if name.startswith("rsf/"):
    return name[len("rsf/"):]
  if name.startswith("refine/"):
    return "refine." + name[len("refine/"):]
  return name


def _convert_one(module_path: str, kind: str, value: np.ndarray):
  """(jaxflow path, array) for one PyTorch tensor."""
  leaf = module_path.rsplit("/", 1)[-1]
  if leaf.endswith("_act"):
    return f"{module_path}/negative_slope", value.reshape(())
  is_norm = leaf.startswith("gn") or leaf.endswith("_norm")
  if kind == "weight":
    if is_norm:
      return f"{module_path}/scale", value
    return f"{module_path}/kernel", value.reshape(value.shape[0], -1).T
  return f"{module_path}/bias", value


def convert_state_dict(tensors: dict) -> tuple[dict, bool]:
  """PyTorch tensors by name -> (nested jaxflow params, whether refinement weights were present)."""
  flat = {}
  for raw_name, value in tensors.items():
    name = _canonical(raw_name)
    if name.endswith("num_batches_tracked"):
      continue
    module, _, kind = name.rpartition(".")
    for pattern, template in _MODULES:
      if re.fullmatch(pattern, module):
        path, array = _convert_one(re.sub(pattern, template, module), kind,
                                   np.asarray(value, np.float32))
        flat[path] = array
        break
    else:
      raise CheckpointError(f"PV-RAFT weight {raw_name!r} matches no jaxflow parameter")
  params: dict = {}
  for path, array in flat.items():
    node = params
    *parents, leaf = path.split("/")
    for key in parents:
      node = node.setdefault(key, {})
    node[leaf] = array
  return params, "refine" in params


def load_weights(path) -> dict:
  """Tensors by name from a .pth state_dict (needs torch) or an .npz."""
  path = pathlib.Path(path)
  if not path.is_file():
    raise DataError(path, "no such weights file")
  if path.suffix == ".npz":
    try:
      with np.load(path) as data:
        return {k: data[k] for k in data.files if k.startswith(("rsf/", "refine/")) or "." in k}
    except Exception as e:  # zipfile / pickle errors say little about the file
      raise DataError(path, f"not a readable .npz ({e})") from e
  try:
    import torch
  except ImportError as e:
    raise DataError(path, "reading .pth weights needs PyTorch: pip install 'jaxflow[torch]'") from e
  state = torch.load(path, map_location="cpu", weights_only=True)
  if isinstance(state, dict) and "state_dict" in state:
    state = state["state_dict"]
  return {k: v.detach().numpy() for k, v in state.items()}


def import_into(params: dict, imported: dict) -> dict:
  """`params` (a fresh init of the PV-RAFT config) with every imported array put in place.

  Shapes must agree leaf by leaf; a missing or extra leaf is an error naming it.
  """
  def merge(node, new, prefix):
    out = dict(node)
    for key, value in new.items():
      where = f"{prefix}/{key}" if prefix else key
      if key not in node:
        raise CheckpointError(f"imported weight {where} has no place in the PV-RAFT model")
      if isinstance(value, dict):
        out[key] = merge(node[key], value, where)
      else:
        if tuple(np.shape(node[key])) != tuple(value.shape):
          raise CheckpointError(
            f"imported weight {where} has shape {value.shape}, the model expects "
            f"{tuple(np.shape(node[key]))}"
          )
        out[key] = np.asarray(value, np.float32)
    return out

  merged = merge(params, imported, "")
  for module in ("feature_encoder", "context_encoder", "correlation", "update"):
    _check_complete(params[module], imported.get(module, {}), module)
  return merged


def _check_complete(expected: dict, got: dict, prefix: str):
  for key, value in expected.items():
    if key not in got:
      raise CheckpointError(f"the weights lack {prefix}/{key}")
    if isinstance(value, dict):
      _check_complete(value, got[key], f"{prefix}/{key}")


def main(argv=None):
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("weights", help="PV-RAFT weights: a .pth state_dict or an .npz")
  parser.add_argument("--out", required=True, help="checkpoint folder to write")
  args = parser.parse_args(argv)

  import jax
  import jax.numpy as jnp
  from jaxflow.configs import pvraft
  from jaxflow.network import checkpointing
  from jaxflow.network.model import build_model

  imported, has_refine = convert_state_dict(load_weights(args.weights))
  # The official RSF_refine (with refinement: a stage-2 run, which evaluates refined) or RSF.
  config = pvraft.get_config("stage2" if has_refine else "")
  model = build_model(config.model)
  dummy = jnp.zeros((1, 64, 3), jnp.float32) + jnp.linspace(0, 1, 64)[None, :, None]
  fresh = model.init(jax.random.PRNGKey(0), dummy, dummy, num_iters=1)["params"]
  fresh = jax.tree_util.tree_map(np.asarray, fresh)
  params = import_into(fresh, imported)
  checkpointing.save_params(args.out, params, config, note=(
    f"imported from {args.weights} with" + ("" if has_refine else "out") + " PV-RAFT's refinement"
  ))
  print(f"wrote {args.out} (refinement {'imported' if has_refine else 'not in the weights'})")


if __name__ == "__main__":
  import sys

  from jaxflow.cli import guard
  sys.exit(guard(main))
