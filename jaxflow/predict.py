r"""Scene flow of your own point files (jaxflow-predict): the flow of every point of PC1.

    python -m jaxflow.predict SWEEP1 SWEEP2 --lidar [--up z] [--max_range 35] --out FLOW.npy
        [--method.lidar.objects.max_yaw_deg_per_s=100 ...]
    python -m jaxflow.predict S0 S1 ... SN --lidar --out DIR   # a log: DIR/NAME.npy each pair
    python -m jaxflow.predict PC1 PC2 --out FLOW.npy [--method optimise|network|nsfp]
        [--checkpoint PATH] [--config CONFIG] [--iters 32] [--max_points 8192 | --full
        [--corr_chunk N]] [--seed 0] [--steps N] [--objective exact|grid] [--render VIEW.png]
        [--save_flows DIR] [--method.optimise.descent.steps=300 ...]

From Python: `jaxflow.inference.predict_flow(pc1_Nx3, pc2_Mx3, method=...)`, the same defaults.

PC1 and PC2 are any file `jaxflow.data.read_points` reads (.npy, .ply, .pcd, KITTI .bin, .xyz/.txt),
in metres, in the models' frame (x left, y up, z forward; jaxflow.geometry.frames), or with --up z
(the default with --lidar) or x: then rotated into it and the flow back. Without --up, a cloud flat
along one axis (a street scene: metres high, tens of metres across) is read with that axis up and a
note says so (and that a raw 360-degree sweep is --lidar's); an --up that contradicts it is refused
(--noground_limits: taken as given). The output is float32 N x 3 (.npy; --out FLOW.txt or FLOW.csv
writes the same rows as text), one row per row of PC1's file, in file order: row i is the flow of
PC1's i-th point. A row with a non-finite coordinate is left out of the estimate (the count is
printed on stderr) and gets a NaN flow.

Method (--method, jaxflow.methods.registry, docs/methods.md): `optimise` (the default, also the
Python API's) refines the network's flow against the whole clouds; `network` is the network alone
(the paper's protocol, evaluate.py's default); `nsfp` is the NSFP baseline (no checkpoint;
--objective exact or grid). --steps N caps the optimisation steps; --method.METHOD.FIELD=V sets
any of the method's settings (e.g. --method.optimise.bodies.inlier=0.1; --print_config lists
them). An optimisation that did not converge says so on stderr. Long work shows progress, whatever
the method: a bar on a terminal (the stage, the time so far), with stderr in a log file a line
whenever 10 s passed without one (jaxflow.refine.progress); an optimisation driven step by step
(NSFP: minutes) also writes its expected time and a line every 10% of its steps. A raw 360-degree
sweep given without --lidar gets a first, short note, before the work, naming --lidar.

Cloud size (jaxflow.inference): clouds above --max_points (config.eval.num_points, 8192) are sampled
and the flow mapped back to every PC1 point; --full (or --max_points 0) uses whole clouds, the
correlation built config.model.corr_chunk rows at a time (--corr_chunk N sets it; the checkpoint's
0: as many as the clouds' sizes and the memory allow). --seed seeds the sampling.

Raw sweeps (--lidar, the spelling of --method lidar: jaxflow.methods.lidar,
jaxflow.lidar.sweep): the ground if the sweep has one (local planes along --up: z, the LiDAR
convention; y for a camera frame such as KITTI's), the sensor's ego-motion (GICP of the two sweeps)
and one rigid motion per moving object, sought in the whole sweep (beyond --max_range too); every
point on no moving object, ground included, moves with the ego-motion. A note says what was found.
The lidar method runs a method of its own (--method.lidar.method: here --method's, default
optimise) on a camera's view (under half the azimuth: its non-ground points within --max_range,
35 m, the others getting the rigid motion of its static part) and, on a 360-degree sweep, only when
--method is given (--method.lidar.start=True): its flow is then one more start of the fits (slow;
benchmarks/REAL_SWEEPS.md). Otherwise no checkpoint is loaded. --max_range is
--method.lidar.max_range; --noground_limits skips the up-axis check. --method.lidar.FIELD=V sets
the pipeline's settings (jaxflow.lidar.settings; --print_config lists them with their units).

Model. The checkpoint (default: the shipped jaxflow/checkpoints/jaxflow_synthetic/) carries its
config: the model is built from it. --config (default configs/default.py:eval) only sets evaluation
settings; a model field of an explicit --config file that contradicts the checkpoint is an error,
except the runtime fields of jaxflow.network.model_fields (corr_chunk, infer_truncate_k, precision,
...), which stay the checkpoint's unless given as --config.model.FIELD=V (e.g.
--config.model.infer_truncate_k=64: faster with --full). A stage-2 checkpoint gives the refined
flow, a stage-1 one the last iteration's.

A log (three or more files): the flow of each consecutive pair as DIR/NAME.npy (NAME: the
pair's first file's stem), in one process, the method loaded once (jaxflow.predict_log: the
order, the checks).

Outputs, every path checked before any work (a wrong suffix or an unwritable place: one line, exit
2; a missing folder is made, with a note): --out FILE; --save_flows DIR writes DIR/NAME.npy, NAME made from "PC1,PC2" as evaluate.py
--save_flows names its pairs (jaxflow.evaluation.export); --render FILE.png a top view of this pair
in its up axis, FILE.html a 3D viewer (jaxflow.viz.viewer; evaluate.py's --render_dir DIR: pictures
of every pair).

Broken input (a missing or unreadable file, a wrong number of columns, no finite point, fewer points
than the model's neighbourhood config.model.knn or, with --lidar, than the pipeline's 90 points a
sweep, jaxflow.lidar.sweep.min_points) prints one line naming the file and the problem and exits
with code 2; a missing or empty file, or a folder, before jax loads (in a fraction of a second).
"""

import pathlib
import sys

import numpy as np

from jaxflow import cli
from jaxflow.data import pointfiles
from jaxflow.errors import ConfigError
from jaxflow.evaluation import export

# The output paths of one pair (--out: _outputs), checked before any work: (suffixes, a folder).
OUTPUTS = {"render": ((".png", ".html"), False), "ego_out": ((), False),
           "save_flows": ((), True), "submission": ((), True)}
# The flags of predict that take no value (the others take the argument after them).
SWITCHES = ("lidar", "ground_limits", "full", "print_config", "deterministic", "help", "helpfull",
            "helpshort")
READ_NO_FILES = ("--print_config", "--help", "--helpfull", "--helpshort")  # (given files or not)


def _check_paths_first(argv):
  """The output paths and the point files named in argv, checked before jax loads (seconds on a
  CPU; imports below are in the functions that need them for that reason): a wrong path is said at
  once, one line and exit 2 (after a renamed flag's)."""
  cli.check_renamed(argv, cli.RENAMED)
  cli.guard(export.check_outputs, export.outputs_in_argv(argv, OUTPUTS), make=False)
  if any(a.split("=")[0] in READ_NO_FILES for a in argv):
    return
  for path in cli.positionals(argv, SWITCHES):  # a missing, empty or not a file
    cli.guard(pointfiles.check_file, path)


def _define_flags(default_method: str):
  from absl import flags  # pylint: disable=import-outside-toplevel
  from ml_collections import config_flags  # pylint: disable=import-outside-toplevel

  config_flags.DEFINE_config_file(
    "config", cli.EVAL_CONFIG, "Evaluation settings (config.eval.num_points, "
    "config.eval.num_iters); the model comes from the checkpoint.", lock_config=True)
  flags.DEFINE_string("checkpoint", None, "Workdir, checkpoints folder or step folder (default: the "
                      "shipped jaxflow/checkpoints/jaxflow_synthetic/).")
  flags.DEFINE_string("out", None, "Write the flow here, one row per point of PC1: .npy "
                      "(float32) or text, .txt (x y z per line) or .csv.")
  cli.define_run_flags(default_method)
  flags.DEFINE_integer("columns", None, ".bin files: float32 values a point (default 4, KITTI's x y "
                       "z intensity; 5: nuScenes' x y z intensity ring; 3: x y z).")
  flags.DEFINE_string("render", None, "Also draw the flow of this pair: FILE.png a top view in --up "
                      "(speed relative to the ego-motion), FILE.html a 3D viewer (extra 'viewer').")
  flags.DEFINE_bool("lidar", False, "Raw sweeps, the lidar method (jaxflow.lidar.sweep): the "
                    "ground (local planes along --up), the sensor's ego-motion (GICP) and one rigid "
                    "motion per moving object; --method's method runs on a camera's view (the "
                    "points within --max_range off the ground), on a sweep only when --method is "
                    "given (a start). --method lidar is the same.")
  flags.DEFINE_bool("ground_limits", True, "Refuse an --up along which PC1 is not flat while "
                    "another axis is (a street scene is flat along its up axis) and, with --lidar, "
                    "one under which the sweep's largest plane stands upright near the origin; "
                    "--noground_limits skips both.")
  flags.DEFINE_enum("up", None, ["x", "y", "z"], "The clouds' up axis (z: LiDAR; y: the models' "
                    "frame): rotated into the models' frame, the flow back. Default: the axis PC1 "
                    "is flat along (a note says so), else z with --lidar, y without.")
  flags.DEFINE_float("max_range", None, "--lidar: sets --method.lidar.max_range (default 35; 0: "
                     "all), the horizontal distance (m) from the sensor within which the method "
                     "sees the non-ground points (a camera's view, or --method's start on a sweep) "
                     "and --render draws; a sweep's moving objects are sought beyond it too.")
  flags.DEFINE_string("submission", None, "--lidar: also write DIR/<log>/<ts>.feather (AV2).")
  flags.DEFINE_string("ego_out", None, "--lidar: also write the sensor's estimated motion here, "
                      "a 4 x 4 matrix as text (x2 = R x1 + t, in the clouds' axes): the flow minus "
                      "its flow R x + t - x is the world's own motion.")


def sweep_hint(pc1_Nx3, up: str | None, method: str) -> str | None:
  """A first, short note when pc1 looks like a raw 360-degree sweep (flat along an axis, points all
  around it) and `method` is not the raw-sweep one (None otherwise): said before the work."""
  from jaxflow.geometry import frames  # pylint: disable=import-outside-toplevel
  from jaxflow.lidar import sweep  # pylint: disable=import-outside-toplevel
  from jaxflow.methods import registry  # pylint: disable=import-outside-toplevel

  if registry.get(method).raw_sweeps:
    return None
  axis = up or frames.flat_axis(pc1_Nx3)[0]
  if axis is None or axis == registry.get(method).up:
    return None
  k = frames.up_index(axis)
  around = np.asarray(pc1_Nx3)[:, [i for i in range(3) if i != k] + [k]]
  if sweep.azimuth_coverage(around[np.isfinite(around).all(1)]) < 0.9:  # a camera's view
    return None
  return (f"this looks like a raw 360-degree sweep ({axis} up, points all around): --lidar is the "
          "method for raw sweeps")


def _used(name: str, n: int, max_points: int | None) -> str:
  """How a cloud of n points went into the method, for the closing message."""
  if not max_points or n <= max_points:
    return f"{name}: all {n} points used"
  return (f"{name}: sampled to {max_points} of {n} points"
          + (", flow mapped back to every point" if name == "PC1" else ""))


def _how(prediction, methods, num_iters: int, max_points: int | None) -> str:
  """What ran, for the closing message; `methods`: cli.run_methods's (a raw-sweep method first)."""
  from jaxflow.methods import registry  # pylint: disable=import-outside-toplevel

  name, chosen = methods[-1]
  found = prediction.sweep
  if found is not None and found.ego.start != "flow_fn":  # a 360-degree sweep: the pipeline's fits
    return (f"ground, ego-motion and {len(found.objects.moved)} moving objects "
            "(jaxflow.lidar.sweep)" + (f"; method {name}'s flow a start" if found.used_network
                                       else "; no method run"))
  how = "ground and far points removed; " if found is not None else ""
  how += "; ".join(_used(cloud, n, max_points) for cloud, n in zip(("PC1", "PC2"), prediction.used))
  method = registry.get(name)
  if method.needs_network:
    iters = (registry.network_asked(name, chosen) or (None,))[0] or num_iters
    how += f"; {iters} network iterations" if method.refines_start else f"; {iters} iterations"
  how += f"; method {name}" + (" at every point" if method.refines_start else "")
  return how + (f" ({chosen.objective} objective)" if method.objectives else "")


def _outputs(FLAGS, raw_sweeps: bool) -> pathlib.Path:
  """--out's path, every output flag checked before the work."""
  if not FLAGS.out and not FLAGS.save_flows and not FLAGS.submission:
    raise ConfigError("give --out FLOW.npy, --save_flows DIR or --submission DIR")
  if FLAGS.ego_out and not raw_sweeps:
    raise ConfigError("--ego_out writes the sweep pipeline's ego-motion: it needs --lidar")
  if FLAGS.out:
    export.check_flow_path(pathlib.Path(FLAGS.out))
  outputs = {"out": (export.FLOW_SUFFIXES, False), **OUTPUTS}
  notes = export.check_outputs([(f"--{flag}", FLAGS[flag].value, *kind)
                                for flag, kind in outputs.items()])
  if FLAGS.render and FLAGS.render.endswith(".html"):  # its extra checked before the work
    from jaxflow.viz import viewer  # pylint: disable=import-outside-toplevel
    viewer.require_plotly()
  for note in notes:  # a missing folder is made, and said (docs/users.md)
    print(f"note: {note}", file=sys.stderr)
  return pathlib.Path(FLAGS.out or "")


def _write(FLAGS, out, paths, pc1, rows1, prediction) -> list:
  """Writes the flow (--out, --save_flows, --submission, --ego_out): the files written."""
  from jaxflow import inference  # pylint: disable=import-outside-toplevel
  from jaxflow.evaluation import submission  # pylint: disable=import-outside-toplevel

  flow_rows = inference.file_rows(prediction.flow, rows1)  # one row per row of PC1's file
  written = []
  if FLAGS.out:
    export.save_flow(out, flow_rows)
    written.append(out)
  if FLAGS.save_flows:
    written.append(export.FlowSaver(FLAGS.save_flows).save(",".join(paths), flow_rows))
  written += submission.user_pair(FLAGS.submission, paths[0], pc1, prediction.flow,
                                  prediction.sweep)
  if FLAGS.ego_out:
    written.append(export.save_motion(FLAGS.ego_out, prediction.sweep.motion))
  return written


def main(argv):
  from absl import flags  # pylint: disable=import-outside-toplevel
  from absl import logging as absl_logging  # pylint: disable=import-outside-toplevel
  from jaxflow import inference  # pylint: disable=import-outside-toplevel
  from jaxflow.methods import registry  # pylint: disable=import-outside-toplevel

  FLAGS = flags.FLAGS
  if not FLAGS["verbosity"].present:  # orbax warns that a read-only checkpoint is read-only
    absl_logging.set_verbosity(absl_logging.ERROR)
  if len(argv) == 2:
    cli.fail(f"{argv[1]}: one sweep alone; give two point files PC1 PC2 (a pair) or more sweeps "
             "(a log: --out DIR)")
  if len(argv) < 2:
    cli.fail("expected two point files PC1 PC2 (or more sweeps, a log), got none")
  paths = argv[1:]
  config, model_fields = cli.run_settings(FLAGS.config)
  methods = cli.run_methods()  # a wrong --method.X.FIELD is said now, not when (if) it loads
  if len(paths) > 2:  # a log: the flow of each consecutive pair (jaxflow.predict_log)
    from jaxflow import predict_log  # pylint: disable=import-outside-toplevel
    predict_log.run(FLAGS, paths, config, model_fields, methods,
                    lambda prediction: _how(prediction, methods, config.eval.num_iters,
                                            config.eval.num_points))
    return
  (name, chosen), *nested = methods
  out = _outputs(FLAGS, registry.get(name).raw_sweeps)
  pc1, note1, rows1 = inference.read_cloud(paths[0], FLAGS.columns)
  pc2, note2, _ = inference.read_cloud(paths[1], FLAGS.columns)
  hint = sweep_hint(pc1, FLAGS.up, name)  # first, before the work (minutes on a sweep)
  if hint:
    print(f"note: {paths[0]}: {hint}", file=sys.stderr)
  # A raw-sweep method loads its method's checkpoint when that runs (a camera's view, a start).
  predictor = inference.load_predictor(FLAGS.checkpoint, config, model_fields, name,
                                       method_settings=chosen,
                                       nested_settings=nested[0][1] if nested else None)
  max_points, num_iters = config.eval.num_points, config.eval.num_iters
  prediction = predictor.predict(pc1, pc2, num_iters=num_iters, max_points=max_points,
                                 full=not max_points, seed=config.eval.seed, names=tuple(paths),
                                 up=FLAGS.up, ground_limits=FLAGS.ground_limits)
  if prediction.sweep is not None:
    print(f"note: {prediction.sweep.note()}", file=sys.stderr)
  written = _write(FLAGS, out, paths, pc1, rows1, prediction)
  if note1:
    print(f"note: {note1}; {written[0]} has one row per PC1 row, in file order, NaN where the "
          "point was dropped", file=sys.stderr)
  warnings = [n for n in prediction.notes if n.startswith("PC1 has")]
  for note in [note2, *(n for n in prediction.notes if n not in warnings)]:
    if note:
      print(f"note: {note.replace(inference.LIDAR_HINT, '') if hint else note}", file=sys.stderr)
  print(f"{', '.join(map(str, written))}: flow of {len(pc1)} points "
        f"({_how(prediction, methods, num_iters, max_points)}; {predictor.source})",
        file=sys.stderr)
  for warning in warnings:
    print(f"warning: {warning}", file=sys.stderr)
  if FLAGS.render:
    from jaxflow.viz import viewer  # pylint: disable=import-outside-toplevel  (matplotlib: only here)
    viewer.render(FLAGS.render, pc1, pc2, prediction.flow, up=prediction.up, sweep=prediction.sweep,
                  title=f"{pathlib.Path(paths[0]).name} -> {pathlib.Path(paths[1]).name}")
    what = "3D viewer (jaxflow.viz.viewer)" if FLAGS.render.endswith(".html") else "top view"
    print(f"{FLAGS.render}: {what} of the pair and its flow", file=sys.stderr)


def run(default_method: str | None = None, description: str | None = None):
  """The console script `jaxflow-predict` (`python -m jaxflow.nsfp`: default_method nsfp; None:
  inference.DEFAULT_METHOD, optimise)."""
  _check_paths_first(sys.argv)
  from jaxflow import inference  # pylint: disable=import-outside-toplevel

  cli.run(main, lambda: _define_flags(default_method or inference.DEFAULT_METHOD),
          {"config": cli.EVAL_CONFIG}, description=description)

if __name__ == "__main__":
  run()
