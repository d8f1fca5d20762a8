"""`predict` on a list of sweeps (a log): the flow of each consecutive pair, in one process.

    python -m jaxflow.predict s0.bin s1.bin ... sN.bin --lidar --out DIR

writes DIR/NAME.npy for each pair (NAME: the stem of the pair's first sweep), the method loaded
(and compiled) once; each sweep is read once and kept as the next pair's first. The sweeps are
taken in the order given, and that order is printed. Checked before any work, each as one line
naming the file: a sweep missing, unreadable or too small; two sweeps of the same name (their
flows would share a file); an --out that is not a folder, or a folder that holds files other than
this log's. The outputs of one pair only (--render, --ego_out, --submission, --save_flows) need the
two-sweep form.
"""

import pathlib
import sys
import time

from jaxflow import inference
from jaxflow.errors import ConfigError, DataError
from jaxflow.evaluation import export

ONE_PAIR_FLAGS = ("render", "ego_out", "submission", "save_flows")


def output_names(paths) -> list[str]:
  """NAME.npy of each pair's first sweep; a ConfigError naming the two files of a repeated name
  (every sweep counts: a repeated last sweep is as wrong as a repeated first)."""
  seen = {}
  for path in paths:
    stem = pathlib.Path(path).stem
    if stem in seen:
      raise ConfigError(f"{path}: two sweeps of the same name ({seen[stem]} and {path}); each "
                        "pair's flow is written as DIR/NAME.npy, NAME its first sweep's")
    seen[stem] = path
  return [pathlib.Path(p).stem + ".npy" for p in paths[:-1]]


def check_folder(out, names) -> pathlib.Path:
  """--out as the log's folder: a ConfigError unless it is a folder (or a new name without a
  suffix) holding no file but this log's own outputs (a rerun overwrites them)."""
  if not out:
    raise ConfigError("give --out DIR: a list of sweeps writes DIR/NAME.npy for each pair")
  folder = pathlib.Path(out)
  if folder.exists() and not folder.is_dir():
    raise ConfigError(f"--out {folder}: is a file; with a list of sweeps --out is a folder "
                      "(DIR/NAME.npy for each pair)")
  if not folder.exists() and folder.suffix:
    raise ConfigError(f"--out {folder}: with a list of sweeps --out is a folder (DIR/NAME.npy "
                      "for each pair), not a file name")
  if folder.is_dir():
    others = sorted(p.name for p in folder.iterdir() if p.name not in set(names))
    if others:
      raise ConfigError(f"--out {folder}: the folder holds other files ({', '.join(others[:3])}"
                        f"{', ...' if len(others) > 3 else ''}); give an empty or new folder")
  return folder


def check_sweeps(paths, columns, least: int, too_few: str):
  """Reads every sweep once before the work: a DataError naming the first missing, unreadable or
  too small one."""
  for path in paths:
    points, _, _ = inference.read_cloud(path, columns)
    if len(points) < least:
      raise DataError(path, f"has {len(points)} finite points; {too_few}")


def run(FLAGS, paths, config, model_fields, methods, how) -> list[pathlib.Path]:
  """The flow of each consecutive pair of `paths` into FLAGS.out's folder; `how(prediction)`: what
  ran, for each pair's line. Returns the files written."""
  given = [f"--{flag}" for flag in ONE_PAIR_FLAGS if getattr(FLAGS, flag)]
  if given:
    raise ConfigError(f"{', '.join(given)}: one pair's outputs; with a list of sweeps give --out "
                      "DIR only (or two sweeps)")
  names = output_names(paths)
  folder = check_folder(FLAGS.out, names)
  (name, chosen), *nested = methods
  predictor = inference.load_predictor(FLAGS.checkpoint, config, model_fields, name,
                                       method_settings=chosen,
                                       nested_settings=nested[0][1] if nested else None)
  check_sweeps(paths, FLAGS.columns, predictor.min_points, _too_few(predictor))
  print(f"{len(paths)} sweeps in the order given ({len(names)} pairs): "
        + ", ".join(map(str, paths)), file=sys.stderr)
  folder.mkdir(parents=True, exist_ok=True)
  max_points, num_iters = config.eval.num_points, config.eval.num_iters
  start = time.perf_counter()
  pc2, note, rows2 = inference.read_cloud(paths[0], FLAGS.columns)
  written = []
  for i, out_name in enumerate(names):
    if note:  # non-finite rows dropped: their flow rows are NaN
      print(f"note: {note}; {out_name} has one row per row of {paths[i]}, NaN where the point "
            "was dropped", file=sys.stderr)
    pc1, rows1 = pc2, rows2  # each sweep read once: the next pair's first
    pc2, note, rows2 = inference.read_cloud(paths[i + 1], FLAGS.columns)
    pair_start = time.perf_counter()
    prediction = predictor.predict(pc1, pc2, num_iters=num_iters, max_points=max_points,
                                   full=not max_points, seed=config.eval.seed,
                                   names=(paths[i], paths[i + 1]), up=FLAGS.up,
                                   ground_limits=FLAGS.ground_limits)
    out = folder / out_name
    export.save_flow(out, inference.file_rows(prediction.flow, rows1))
    written.append(out)
    print(f"[{i + 1}/{len(names)}] {out}: flow of {len(pc1)} points, {paths[i]} -> "
          f"{paths[i + 1]} ({how(prediction)}; {time.perf_counter() - pair_start:.1f} s)",
          file=sys.stderr)
    for note in prediction.notes:
      if note:
        print(f"note: {note}", file=sys.stderr)
  seconds = time.perf_counter() - start
  print(f"{folder}: {len(written)} flows of {len(paths)} sweeps in {seconds:.1f} s "
        f"({seconds / len(paths):.1f} s a sweep; {predictor.source})", file=sys.stderr)
  return written


def _too_few(predictor) -> str:
  """Why a sweep needs predictor.min_points points."""
  from jaxflow.lidar import sweep  # pylint: disable=import-outside-toplevel
  from jaxflow.methods import registry  # pylint: disable=import-outside-toplevel
  if registry.get(predictor.method).raw_sweeps:
    return sweep.too_few(predictor.method_settings)
  return f"the method needs at least {predictor.min_points} points a cloud"
