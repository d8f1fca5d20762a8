r"""Converts a dataset to one HDF5 file (see `jaxflow.data.hdf5` for the layout).

    python -m jaxflow.data.convert --dataset ft3d:/data/FlyingThings3D_subset_processed_35m \
        --split train --out ft3d_train.h5

The file is written as OUT.tmp and renamed at the end, so an interrupted conversion never leaves a
partial file under OUT. A bad argument or data file prints one line on stderr and exits with 2.
"""

import argparse
import os
import pathlib
import sys
import warnings

import h5py
import numpy as np
import tqdm

from jaxflow.data import open_dataset
from jaxflow.data.hdf5 import H5Writer
from jaxflow.errors import ConfigError, DataError, JaxflowError


def convert(spec: str, split: str | None, out, limit: int | None = None, skip_broken: bool = False,
            progress: bool = True) -> list[str]:
  """Writes the pairs of `spec` (the first `limit`) to `out`; returns the skipped broken pairs."""
  out = pathlib.Path(out)
  if out.suffix != ".h5":
    raise ConfigError(f"--out {out}: expected a FILE.h5 name")
  if not out.parent.is_dir():
    raise DataError(out.parent, "missing output folder")
  dataset = open_dataset(spec, split)
  count = len(dataset) if limit is None else min(limit, len(dataset))
  tmp = out.with_name(out.name + ".tmp")
  skipped = []
  try:
    stored_split = getattr(dataset, "split", None) or split or ""
    with H5Writer(tmp, source=spec, split=stored_split, description=dataset.describe(),
                  up=dataset.up) as writer:
      for i in tqdm.trange(count, desc=f"converting {dataset.name}", unit="pair", disable=not progress):
        try:
          writer.append(dataset[i])
        except DataError as e:
          if not skip_broken:
            raise
          warnings.warn(f"skipping broken pair {i}: {e}", stacklevel=1)
          skipped.append(str(e))
      writer.file.attrs["skipped"] = np.array(skipped, dtype=h5py.string_dtype())
    os.replace(tmp, out)
  finally:
    if tmp.exists():
      tmp.unlink()
  return skipped


class _Parser(argparse.ArgumentParser):
  def error(self, message):
    raise ConfigError(message)


def main(argv=None) -> int:
  parser = _Parser(prog="python -m jaxflow.data.convert", description=__doc__.split("\n")[0])
  parser.add_argument("--dataset", required=True,
                      help="FORMAT:ROOT, e.g. ft3d:/data/FT3D or synthetic_things:100")
  parser.add_argument("--split", default=None, help="train | val | test | train_all (reader dependent)")
  parser.add_argument("--out", required=True, help="output FILE.h5")
  parser.add_argument("--limit", type=int, default=None, help="convert only the first LIMIT pairs")
  parser.add_argument("--skip_broken", action="store_true",
                      help="skip unreadable pairs instead of stopping")
  try:
    args = parser.parse_args(argv)
    skipped = convert(args.dataset, args.split, args.out, args.limit, args.skip_broken)
  except JaxflowError as e:
    print("convert: error: " + " ".join(str(e).split()), file=sys.stderr)  # one line
    return 2
  if skipped:
    print(f"convert: skipped {len(skipped)} broken pairs", file=sys.stderr)
  return 0


if __name__ == "__main__":
  sys.exit(main())
