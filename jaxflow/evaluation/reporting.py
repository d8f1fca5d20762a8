"""What evaluate.py and train.py print and write of an evaluation: the paper's table, the
official Argoverse 2 tables (or the local three-way one), convergence notes, the JSON file and the pictures of every pair."""

import json
import sys
from pathlib import Path

from jaxflow.errors import ConfigError
from jaxflow.evaluation import av2_eval, tables
from jaxflow.evaluation.metrics import format_three_way
from jaxflow.methods import registry


def _sweeps(r: dict) -> bool:
  """Results of a LiDAR sweep layout (ego-motion flow and labels: the three-way readings)."""
  return "three_way_local" in r or "av2" in r


def format_table(rows) -> str:
  """rows: (dataset name, results) -> the layout of the paper's Tables 2-3, then the two times
  (jaxflow.evaluation.evaluator): the first pair's with its compilation, the others' a pair
  ("ms/pair after"; "ms/pair rerun" when there was one batch: that batch again, compiled). On LiDAR
  sweeps the Outliers column (FT3D's rule: EPE > 0.3 m or over 10% of the flow, so that on points
  that barely move millimetres count) is left out: the three-way tables below read those pairs."""
  outliers = not all(_sweeps(r) for _, r in rows)
  rerun = any(r.get("steady") == "rerun" for _, r in rows)
  header = ("Dataset", "EPE(m)", "AccS(%)", "AccR(%)", *(("Outliers(%)",) if outliers else ()),
            "θε(rad)", "pairs", "first pair s", "ms/pair rerun" if rerun else "ms/pair after")
  first = lambda r: "-" if r.get("first_pair_s") is None else f"{r['first_pair_s']:.2f}"
  return tables.markdown_table(header, [(
    name, f"{r['epe']:.4f}", f"{r['acc_strict']:.2f}", f"{r['acc_relax']:.2f}",
    *((f"{r['outliers']:.2f}",) if outliers else ()), f"{r['angle']:.4f}", str(r["pairs"]),
    first(r), f"{r['ms_per_pair']:.1f}",
  ) for name, r in rows])


def report(results: dict, json_path=None):
  """Prints the table of `results` (evaluation.evaluate_checkpoint's; the three-way table when it
  has one, a convergence note on stderr) and writes them to `json_path` (JSON) when given."""
  name = f"{results['dataset']} ({results['split']})"
  print(format_table([(name, results)]))
  if "av2" in results:
    print(av2_eval.format_results(results))
  elif "three_way_local" in results:
    print(format_three_way([(name, results)]))
  if "submission" in results:
    for line in results["submission"].values():
      if line:
        print(line, file=sys.stderr)
  note = registry.evaluation_note(results["method"], results.get("convergence"))
  if note:
    print(f"note: {note}", file=sys.stderr)
  if json_path:
    Path(json_path).absolute().parent.mkdir(parents=True, exist_ok=True)
    Path(json_path).write_text(json.dumps(results, indent=2) + "\n")


def render_batch(render_dir, batch, pred_BxNx3):
  """The views of every real pair of a batch (jaxflow.viz.figures.render_batch: NAME.png and NAME_top.png
  in RENDER_DIR), in the batch's up axis ("up": evaluation gives it; y, the models', otherwise)."""
  try:
    from jaxflow.viz import figures  # pylint: disable=import-outside-toplevel  (matplotlib: only here)
  except ImportError as e:
    raise ConfigError(f"--render_dir needs the jaxflow.viz.figures module, which cannot be imported ({e})")
  Path(render_dir).mkdir(parents=True, exist_ok=True)
  figures.render_batch(render_dir, batch, pred_BxNx3, batch.get("up", "y"))
