"""The dataset interface (`Pair`, `Dataset`) and the registry of formats behind `open_dataset`.

Reader modules register their formats here (`register("ft3d", FT3D)`); `jaxflow.data` imports every
reader module, so `open_dataset` knows them all. This module imports no reader: data flows one way,
readers -> registry.
"""

import dataclasses
from typing import Callable

import numpy as np

from jaxflow.errors import DataError

@dataclasses.dataclass(frozen=True)
class Pair:
  """One scene-flow pair; everything float32 except mask (bool: flow valid / evaluated).

  LiDAR datasets with ego-motion and labels (opensf) also give, for the three-way EPE
  (`jaxflow.evaluation.metrics.three_way_epe`), `rigid_flow` (the ego-motion flow of each pc1 point)
  and `foreground` (bool: the point is on an object); other readers leave them None. Datasets with
  Argoverse 2 labels also give `category` (N uint8, av2's CATEGORY_TO_INDEX, 0 = background) and
  `ego_xy` (N x 2: each pc1 point's x, y in its ego frame), for the official breakdown
  (`jaxflow.evaluation.av2_eval`); both or neither, and only with rigid_flow.
  """
  pc1: np.ndarray  # N x 3
  pc2: np.ndarray  # M x 3
  flow: np.ndarray  # N x 3
  mask: np.ndarray  # N
  name: str  # source: file or folder path, or e.g. "synthetic_things/train/3"
  rigid_flow: np.ndarray | None = None  # N x 3
  foreground: np.ndarray | None = None  # N bool
  category: np.ndarray | None = None  # N uint8 (av2 category index)
  ego_xy: np.ndarray | None = None  # N x 2

  def __post_init__(self):
    n = len(self.pc1)
    if (self.pc1.shape != (n, 3) or self.flow.shape != (n, 3) or self.mask.shape != (n,)
        or self.pc2.ndim != 2 or self.pc2.shape[1] != 3):
      raise ValueError(f"{self.name}: inconsistent shapes pc1 {self.pc1.shape}, pc2 {self.pc2.shape}, "
                       f"flow {self.flow.shape}, mask {self.mask.shape}")
    if ((self.rigid_flow is None) != (self.foreground is None)
        or (self.rigid_flow is not None and (self.rigid_flow.shape != (n, 3)
                                             or self.foreground.shape != (n,)))):
      raise ValueError(f"{self.name}: rigid_flow and foreground must both be given, N x 3 and N "
                       f"(pc1 has {n} points)")
    if ((self.category is None) != (self.ego_xy is None)
        or (self.category is not None and (self.rigid_flow is None or self.category.shape != (n,)
                                           or self.ego_xy.shape != (n, 2)))):
      raise ValueError(f"{self.name}: category and ego_xy must both be given with rigid_flow, N "
                       f"and N x 2 (pc1 has {n} points)")

  @property
  def has_labels(self) -> bool:
    """Whether the pair carries ego-motion flow and foreground labels (three-way EPE)."""
    return self.rigid_flow is not None


class Dataset:
  """A sequence of Pairs: len(ds), ds[i], iteration, ds.name, ds.up and ds.describe().

  `up` is the up axis of the clouds, "x", "y" or "z" (jaxflow.geometry.frames), and every reader
  says it: "y" is the models' frame (x left, y up, z forward), "z" a LiDAR's (x forward, y left,
  z up). Evaluation rotates the clouds into a method's frame and the flow back by it.
  """
  name: str = ""
  up: str  # set by each reader (a class attribute, or in __init__ when an option decides it)

  def __len__(self) -> int:
    raise NotImplementedError

  def load(self, i: int) -> Pair:
    raise NotImplementedError

  def describe(self) -> str:
    return f"{self.name}: {len(self)} pairs"

  def __getitem__(self, i: int) -> Pair:
    n = len(self)
    if not -n <= i < n:
      raise IndexError(f"{self.name}: index {i} out of range for {n} pairs")
    return self.load(i % n)

  def __iter__(self):
    return (self.load(i) for i in range(len(self)))

  def __repr__(self):
    return f"<{type(self).__name__} {self.describe()}>"


# format name -> (opener(arg, split) -> Dataset, whether ARG is required)
_FORMATS: dict[str, tuple[Callable[[str, str | None], Dataset], bool]] = {}


def register(name: str, opener: Callable[[str, str | None], Dataset], needs_root: bool = False):
  """Makes "NAME[:ARG]" open `opener(ARG, split)`; needs_root: ARG may not be empty."""
  if name in _FORMATS:
    raise ValueError(f"dataset format {name!r} is registered twice")
  _FORMATS[name] = (opener, needs_root)


def formats() -> tuple[str, ...]:
  return tuple(_FORMATS)


# What follows each reader's format name in a spec, and what it reads: --dataset's help (`usage`;
# tests/test_newcomer.py checks that every registered format has its entry here).
USAGE = {
  "ft3d": (":DIR", "HPLFlowNet's FlyingThings3D_subset_processed_35m"),
  "kitti": (":DIR", "HPLFlowNet's KITTI_processed_occ_final"),
  "argoverse": (":DIR", "NSFP's Argoverse .npz pairs"),
  "flownet3d": (":DIR", "FlowNet3D's FT3Do or KITTIo .npz pairs"),
  "files": (":PC1,PC2", "two point files"),
  "h5": (":FILE.h5", "pairs converted by jaxflow.data.convert"),
  "opensf": (":DIR[,KEY=VALUE,...]", "OpenSceneFlow's h5 logs, DIR/SPLIT/LOG.h5; keys: "
             "ground=remove|keep, max_range=R, frame=ego|camera, region=disc|challenge|sweep, "
             "lidar=auto|ego|sensor, calibration=AV2_DIR"),
  "synthetic_things": ("[:N]", "N generated FT3D-like pairs"),
  "synthetic_lidar": ("[:N]", "N generated LiDAR-like pairs, KITTI's cut"),
  "synthetic_mix": ("[:N]", "N generated pairs of both kinds"),
  "synthetic_sweep": (":N[,form=generated|city|noground][,reverse=1]",
                      "N generated raw 360-degree sweep pairs, z up"),
}


def usage() -> str:
  """Every registered format as "FORMAT:SPEC (what it reads)", in registration order (a format
  without a USAGE entry: FORMAT:ROOT, or FORMAT[:ARG])."""
  return "; ".join(
    name + (f"{USAGE[name][0]} ({USAGE[name][1]})" if name in USAGE else
            ":ROOT" if needs_root else "[:ARG]")
    for name, (_, needs_root) in _FORMATS.items())


def open_dataset(spec: str, split: str | None = None) -> Dataset:
  """Opens "FORMAT:ARG" (a registered format); unknown format or missing root -> DataError."""
  fmt, _, arg = spec.partition(":")
  if fmt not in _FORMATS:
    raise DataError(spec, f"unknown dataset format {fmt!r}; expected FORMAT:ROOT with FORMAT one of "
                    + ", ".join(_FORMATS))
  opener, needs_root = _FORMATS[fmt]
  if needs_root and not arg:
    raise DataError(spec, f"missing root: expected {fmt}:ROOT")
  return opener(arg, split)
