"""Each reader says the up axis of its clouds (`Dataset.up`); jaxflow.geometry knows no dataset.

A new reader is a module in jaxflow.data: its `up` is all evaluation needs to rotate its clouds
into a method's frame. Every registered format is opened here on a tiny fixture (a format without
one fails `test_every_registered_format_says_its_up_axis`), and h5 files keep their source's.
"""

import inspect
import pathlib
import re
import warnings

import h5py
import numpy as np
import pytest

from jaxflow import data
from jaxflow.data import open_dataset, registry
from jaxflow.data.hdf5 import H5Writer
from jaxflow.geometry import frames

ROOT = pathlib.Path(__file__).resolve().parents[1]
# Dataset names a reader's docstring speaks of, beside the registered formats.
SOURCES = ("flyingthings", "hplflownet", "argoverse", "av2", "openscene", "waymo", "nuscenes")


def _cloud(seed, n=64):
  return (np.random.default_rng(seed).normal(size=(n, 3)) * 5).astype(np.float32)


def _write_opensf(root):
  """One OpenSceneFlow log of one pair, ego frame (z up)."""
  (root / "val").mkdir(parents=True)
  pc1 = _cloud(0)
  with h5py.File(root / "val" / "log.h5", "w") as f:
    for key, p in (("0", pc1), ("1", pc1 + 0.1)):
      g = f.create_group(key)
      g.create_dataset("lidar", data=p)
      g.create_dataset("ground_mask", data=np.zeros(len(p), bool))
      g.create_dataset("pose", data=np.eye(4))
    g = f["0"]
    g.create_dataset("flow", data=np.full_like(pc1, 0.1))
    g.create_dataset("flow_is_valid", data=np.ones(len(pc1), bool))
    g.create_dataset("flow_category_indices", data=np.zeros(len(pc1), np.uint8))
    g.create_dataset("ego_motion", data=np.eye(4))


def _write_h5(path, source, up=None):
  """A pairs file of one pair converted from `source`; `up` None: a file from before it was kept."""
  with H5Writer(path, source=source, split="val", up=up or "y") as writer:
    pc1 = _cloud(1)
    writer.append(registry.Pair(pc1, pc1 + 0.1, np.full_like(pc1, 0.1), np.ones(len(pc1), bool),
                                "p"))
  if up is None:
    with h5py.File(path, "a") as f:
      del f.attrs["up"]


@pytest.fixture(scope="module")
def specs(tmp_path_factory):
  """(format, spec, split, the up axis its clouds have): at least one for every registered format."""
  tmp = tmp_path_factory.mktemp("readers")
  for n in (4, 8):
    folder = tmp / "ft3d" / "train" / f"{n:07d}"
    folder.mkdir(parents=True)
    for name in ("pc1", "pc2"):
      np.save(folder / f"{name}.npy", _cloud(n) - np.float32([0, 0, 20]))
  (tmp / "kitti" / "000002").mkdir(parents=True)
  for name in ("pc1", "pc2"):
    np.save(tmp / "kitti" / "000002" / f"{name}.npy", _cloud(2) + np.float32([0, 0, 10]))
  (tmp / "argo").mkdir()
  np.savez(tmp / "argo" / "a.npz", pc1=_cloud(3), pc2=_cloud(4), flow=_cloud(5))
  (tmp / "fn3d").mkdir()
  np.savez(tmp / "fn3d" / "TEST_a.npz", points1=_cloud(3), points2=_cloud(4), flow=_cloud(5))
  np.save(tmp / "a.npy", _cloud(6))
  _write_opensf(tmp / "av2")
  av2 = tmp / "av2"
  _write_h5(tmp / "z.h5", f"opensf:{av2}", up="z")
  _write_h5(tmp / "sweep.h5", "synthetic_sweep:1", up="z")
  _write_h5(tmp / "old_ego.h5", f"opensf:{av2},lidar=ego")
  _write_h5(tmp / "old_camera.h5", f"opensf:{av2},frame=camera")
  _write_h5(tmp / "old_kitti.h5", "kitti:/data/kitti")
  return [
    ("ft3d", f"ft3d:{tmp / 'ft3d'}", "train", "y"),
    ("kitti", f"kitti:{tmp / 'kitti'}", None, "y"),
    ("argoverse", f"argoverse:{tmp / 'argo'}", None, "y"),
    ("flownet3d", f"flownet3d:{tmp / 'fn3d'}", "test", "y"),
    ("files", f"files:{tmp / 'a.npy'},{tmp / 'a.npy'}", None, "y"),
    ("synthetic_things", "synthetic_things:1", "val", "y"),
    ("synthetic_lidar", "synthetic_lidar:1", "test", "y"),
    ("synthetic_mix", "synthetic_mix:2", "train", "y"),
    ("synthetic_sweep", "synthetic_sweep:1", "val", "z"),
    ("opensf", f"opensf:{av2},lidar=ego", "val", "z"),  # the ego frame as stored
    ("opensf", f"opensf:{av2},lidar=ego,frame=camera", "val", "y"),
    ("h5", f"h5:{tmp / 'z.h5'}", None, "z"),  # the `up` attribute convert writes
    ("h5", f"h5:{tmp / 'sweep.h5'}", None, "z"),
    # Files converted before `up` was kept: read as they were then.
    ("h5", f"h5:{tmp / 'old_ego.h5'}", None, "z"),
    ("h5", f"h5:{tmp / 'old_camera.h5'}", None, "y"),
    ("h5", f"h5:{tmp / 'old_kitti.h5'}", None, "y"),
  ]


def test_every_registered_format_says_its_up_axis(specs):
  assert {fmt for fmt, *_ in specs} == set(data.formats())  # a new format: add its fixture here
  with warnings.catch_warnings():
    warnings.simplefilter("ignore")  # kitti: 1 of the 142 benchmark frames
    for _, spec, split, up in specs:
      assert open_dataset(spec, split).up == up, spec


def test_every_reader_class_states_up_and_the_interface_gives_no_default():
  """`Dataset` leaves `up` to its readers: a reader that forgot it fails, never reads as y up."""
  data.formats()  # imports every reader module
  assert "up" not in vars(registry.Dataset)
  found = []
  todo = list(registry.Dataset.__subclasses__())
  while todo:
    cls = todo.pop()
    todo.extend(cls.__subclasses__())
    if cls.__module__.startswith("jaxflow.data."):
      found.append(cls.__name__)
      states = vars(cls).get("up") in frames.UP_AXES or "self.up = " in inspect.getsource(cls)
      assert states, f"{cls.__module__}.{cls.__name__} does not say its up axis"
  assert len(found) >= 9


def test_convert_keeps_the_source_frame(tmp_path):
  """A converted file is read in its source's frame: a z-up sweep stays z up."""
  from jaxflow.data.convert import convert  # pylint: disable=import-outside-toplevel

  convert("synthetic_things:1", "val", tmp_path / "a.h5", progress=False)
  assert open_dataset(f"h5:{tmp_path / 'a.h5'}").up == "y"
  with h5py.File(tmp_path / "a.h5") as f:
    assert f.attrs["up"] == "y"


def test_geometry_knows_no_dataset_name():
  """jaxflow.geometry is geometry: no registered format and no dataset is named in it."""
  names = [*(f for f in data.formats() if f != "files"), "files:", *SOURCES]
  for path in sorted((ROOT / "jaxflow" / "geometry").glob("*.py")):
    text = path.read_text().lower()
    for name in names:
      assert not re.search(rf"\b{re.escape(name)}(?!\w)", text), f"{path.name} names {name}"
