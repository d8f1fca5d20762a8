r"""Every figure a user reads, rerun: benchmarks/readme_figures.json records each accuracy and
speed figure of README.md and docs/ (its file, the command that produces it, the machine, the
value, its noise), and this tool reruns them, records them and writes README.md's table.

    python -m benchmarks.readme --list                 # every figure, its command and minutes
    python -m benchmarks.readme --check [--only ID,ID] # rerun, compare, exit 1 naming what moved
    python -m benchmarks.readme --record --only ID     # write the measured values (and --write)
    python -m benchmarks.readme --write                # README.md's figures block from the record

--check reruns every command estimated at --max-minutes (10) or less, once however many figures
it gives (`--only` runs the figures named, whatever their minutes); the others are listed with
their command. A command writes under `{out}` (a fresh folder) and runs once per seed of a figure
measured over seeds (`{seed}`); a figure is read from a JSON file it writes or by a regex of its
output. A figure moved when it lies farther from its recorded value (or range) than its noise:
the larger of `abs` and `rel` x the value. --check also fails when README.md's block is not what
--write makes or a doc no longer holds a figure's text (with its recorded value).
"""

import argparse
import json
import os
import pathlib
import platform
import re
import shlex
import statistics
import subprocess
import sys
import tempfile
import time

ROOT = pathlib.Path(__file__).absolute().parent.parent
RECORD = ROOT / "benchmarks" / "readme_figures.json"
BEGIN = "<!-- figures:begin: python -m benchmarks.readme --write makes this block -->"
END = "<!-- figures:end -->"
MAX_MINUTES = 10.0  # --check's default: what a 2-core machine reruns without a long wait
HEADER = ["| figure | value | pairs | machine, measured | rerun by |", "|---|---|---|---|---|"]
STALE_NOTE = ["(stale): measured before the code under it changed; `python -m benchmarks.readme",
              "--list` names it, `--record --only ID` measures it again."]
STATS = {"mean": statistics.fmean, "median": statistics.median, "min": min, "max": max,
         "range": lambda v: [min(v), max(v)]}


def load(path: pathlib.Path) -> dict:
  return json.loads(path.read_text())


def save(record: dict, path: pathlib.Path):
  path.write_text(json.dumps(record, indent=2, ensure_ascii=False) + "\n")


def number(value: float, form: str) -> str:
  """One value as the docs write it ("min s": 227 -> "3 min 47 s")."""
  if form == "min s":
    return f"{int(value // 60)} min {round(value % 60)} s"
  return form.format(value)


def shown(figure: dict) -> str:
  """The recorded value as the docs write it: a number, a range or a spread over seeds."""
  value, form = figure.get("value"), figure.get("format", "{:.3f}")
  if value is None:
    return "not measured yet"
  if isinstance(value, dict):
    return f"median {number(value['median'], form)}, worst {number(value['worst'], form)}"
  if isinstance(value, list):
    return "-".join(number(v, form) for v in value)
  return number(value, form)


def dig(data, key: list):
  """data[key[0]][key[1]]...; "*" maps the rest over a list's or dict's items, {"name": X} picks
  the list item whose "name" is X."""
  for i, part in enumerate(key):
    if part == "*":
      items = data.values() if isinstance(data, dict) else data
      return [dig(item, key[i + 1:]) for item in items]
    if isinstance(part, dict):
      (field, want), = part.items()
      data = next(item for item in data if item[field] == want)
    else:
      data = data[part] if isinstance(data, dict) else data[int(part)]
  return data


def read(reader: dict, out: pathlib.Path, output: str):
  """A figure from a command's run: its JSON file or a regex of its output (or of a file)."""
  if "json" in reader:
    values = dig(json.loads((out / reader["json"]).read_text()), reader["key"])
  else:
    text = (out / reader["file"]).read_text() if "file" in reader else output
    match = re.search(reader["regex"], text)
    if match is None:
      raise ValueError(f"no match of {reader['regex']!r} in its output")
    weights = reader.get("weights", [1.0] * len(match.groups()))  # e.g. m:ss -> [60, 1]
    values = sum(float(g.replace(",", "")) * w for g, w in zip(match.groups(), weights))
  if isinstance(values, dict):  # per-pair figures: the pairs named (by their name's last part)
    keep = lambda name: (name.rsplit("/", 1)[-1] in reader["select"] if "select" in reader
                         else name.rsplit("/", 1)[-1] not in reader.get("exclude", ()))
    values = [v for name, v in values.items() if keep(name)]
  if isinstance(values, list):
    values = STATS[reader.get("stat", "mean")](values)
  scale = reader.get("scale", 1.0)
  return [v * scale for v in values] if isinstance(values, list) else values * scale


def runnable(figure: dict, max_minutes: float, named: bool) -> str | None:
  """Why --check does not rerun this figure, or None."""
  if figure.get("command") is None:
    return f"no command: {figure.get('why', '?')}"
  if figure.get("read") is None:
    return f"no reader (read by hand): {figure['command']}"
  if figure.get("device") == "gpu":
    return f"needs a GPU: {figure['command']}"
  missing = [p for p in figure.get("needs", ()) if not (ROOT / p).exists()]
  if missing:
    return f"needs {', '.join(missing)}"
  if not named and figure["minutes"] > max_minutes:
    return f"not rerun by --check ({figure['minutes']} min): {figure['command']}"
  return None


def run(command: str, out: pathlib.Path, seed, minutes: float) -> str:
  """Runs one command (bash, in the repository, this interpreter first on PATH); its output."""
  text = command.replace("{out}", str(out)).replace("{seed}", str(seed))
  env = {**os.environ, "PATH": f"{pathlib.Path(sys.executable).parent}{os.pathsep}"
                               f"{os.environ.get('PATH', '')}",
         "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
  done = subprocess.run(["bash", "-c", text], cwd=ROOT, env=env, capture_output=True, text=True,
                        timeout=max(120, 180 * minutes))  # 3x its estimate: it hangs, or more
  if done.returncode:
    raise RuntimeError(f"exit {done.returncode}: {text}\n{done.stderr[-2000:]}")
  return done.stdout + done.stderr


def measure(figures: list[dict]) -> tuple[dict, dict]:
  """({figure id: measured value}, {figure id: why it could not be measured}), each command run
  once per seed, whatever figures it gives; a figure over seeds gets {"median", "worst",
  "per_seed"} (worst: the largest)."""
  runs, measured, errors = {}, {}, {}
  for figure in figures:
    runs.setdefault((figure["command"], tuple(figure.get("seeds") or [None])), []).append(figure)
  for (command, seeds), group in runs.items():
    per_seed = {}
    try:
      for seed in seeds:
        with tempfile.TemporaryDirectory(prefix="readme_figures_") as tmp:
          start = time.perf_counter()
          print(f"running{'' if seed is None else f' (seed {seed})'}: {command}", flush=True)
          output = run(command, pathlib.Path(tmp), seed, group[0]["minutes"])
          print(f"  {time.perf_counter() - start:.0f} s", flush=True)
          per_seed[seed] = {f["id"]: read(f["read"], pathlib.Path(tmp), output) for f in group}
    except (RuntimeError, ValueError, KeyError, OSError, subprocess.TimeoutExpired) as e:
      errors.update({f["id"]: f"{type(e).__name__}: {e}" for f in group})
      continue
    for figure in group:
      values = {s: v[figure["id"]] for s, v in per_seed.items()}
      measured[figure["id"]] = values[None] if seeds == (None,) else {
        "median": statistics.median(values.values()), "worst": max(values.values()),
        "per_seed": {str(s): v for s, v in values.items()}}
  return measured, errors


def moved(figure: dict, got) -> str | None:
  """Why a measured value departs from the record beyond its noise, or None."""
  recorded = figure.get("value")
  if recorded is None:
    return "no recorded value (run --record)"
  noise = figure["tolerance"]
  pairs = ([(recorded["median"], got["median"]), (recorded["worst"], got["worst"])]
           if isinstance(recorded, dict) else
           list(zip(recorded, got)) if isinstance(recorded, list) and isinstance(got, list) else
           [(recorded, got)])
  for want, value in pairs:
    low, high = (want if isinstance(want, list) else (want, want))
    bound = max(noise.get("abs", 0.0), noise.get("rel", 0.0) * abs(high))
    if max(low - value, value - high) > bound:
      return f"recorded {want}, measured {value:.6g} (noise {bound:.3g})"
  return None


def this_machine() -> str:
  model = ""
  cpuinfo = pathlib.Path("/proc/cpuinfo")
  if cpuinfo.exists():
    model = next((line.split(":", 1)[1].strip() for line in cpuinfo.read_text().splitlines()
                  if line.startswith("model name")), "")
  load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
  return (f"{os.cpu_count()}-core {model or platform.processor() or platform.machine()}, "
          f"load {load:.1f}")  # a speed figure on a loaded machine is an upper bound


# The data the methods' settings were chosen on (README.md, "Methods and what they measure":
# optimise's on 7 of the 21 FT3D pairs, the KITTI frame and the synthetic val pairs;
# benchmarks/REAL_SWEEPS.md: --lidar's on the real labelled Argoverse 2 pair), as README labels
# name them: (how the label starts, words naming such data). An error figure there is a tuned one.
TUNED_ON = (("optimise", ("KITTI 000002", "real FT3D", "the 7 FT3D pairs", "synthetic_things val",
                          "synthetic_lidar val")),
            ("three-way EPE", ("the real labelled Argoverse 2 pair",)))


def tuned_problems(record: dict) -> list[str]:
  """A figure on data its settings were chosen on says so: its record's `tuned` (where they were
  chosen), and its label (README.md's block) or text saying "tuned"; TUNED_ON's figures (a time
  aside) must have `tuned`."""
  problems = []
  for f in record["figures"]:
    label = f.get("label", "")
    on_tuned = "seconds" not in label and any(
      label.startswith(start) and any(w in label for w in words) for start, words in TUNED_ON)
    if on_tuned and not f.get("tuned"):
      problems.append(f"{f['id']}: on data its settings were chosen on ({label!r}): record where "
                      "in its `tuned` and say \"tuned\" in its label")
    texts = f.get("text", label)
    if f.get("tuned") and not all(
        "tuned" in t and "nobody tuned" not in t and "never tuned" not in t
        for t in (texts if isinstance(texts, list) else [texts])):
      problems.append(f"{f['id']}: a tuned figure ({f['tuned']}) whose "
                      f"{'text' if 'text' in f else 'label'} does not say \"tuned\"")
  return problems


def docs_problems(record: dict, root: pathlib.Path) -> list[str]:
  """The docs against the record: README.md's block as --write makes it, every other figure's
  text (holding its recorded value) in its file, whitespace aside, and the tuned figures marked
  (tuned_problems)."""
  problems = tuned_problems(record)
  readme = (root / "README.md").read_text()
  if block_of(readme) != render(record):
    problems.append("README.md: its figures block is not what --write makes")
  for figure in record["figures"]:
    path = root / figure["file"]
    if not path.exists():
      problems.append(f"{figure['id']}: no file {figure['file']}")
      continue
    if "text" not in figure:
      continue  # README.md's block
    doc = " ".join(path.read_text().split())
    texts = figure["text"] if isinstance(figure["text"], list) else [figure["text"]]
    for text in texts:
      if " ".join(text.split()) not in doc:
        problems.append(f"{figure['id']}: {figure['file']} no longer says {text!r}")
      elif figure.get("value") is not None and shown(figure) not in text:
        problems.append(f"{figure['id']}: {text!r} does not hold its value {shown(figure)}")
  return problems


def block_of(readme: str) -> str | None:
  if BEGIN not in readme or END not in readme:
    return None
  return readme.split(BEGIN, 1)[1].split(END, 1)[0].strip("\n")


def script(command: str | None) -> str:
  """The tool a command runs, for the table (its flags are the record's)."""
  if command is None:
    return "none"
  found = re.search(r"benchmarks[/.]\w+(\.py)?|\S*real_sweeps_check\.py|evaluate\.py|train\.py|"
                    r"scripts/\w+\.sh \w+|jaxflow\.\w+|pytest", command)
  return found.group(0).replace("../shared/tools/", "") if found else shlex.split(command)[0]


def rerun_cell(figure: dict) -> str:
  tool = f"`{script(figure.get('command'))}`"
  if figure.get("command") is None:
    return "no command (the record says why)"
  if figure.get("device") == "gpu":
    return f"{tool} on a GPU"
  if figure["minutes"] > MAX_MINUTES or figure.get("read") is None:
    return f"{tool}, {figure['minutes']} min, not by --check"
  return f"{tool}, {figure['minutes']} min"


def row(f: dict) -> str:
  """One figure of README.md's block: what, value, pairs (and seeds), machine, how to rerun."""
  value = shown(f) + (f" {f['unit']}" if f.get("unit") and f.get("value") is not None else "")
  seeds = f.get("seeds")
  pairs = f"{f.get('pairs', '-')}" + (f" a seed, seeds {seeds[0]}-{seeds[-1]}" if seeds else "")
  return (f"| {f['label']} | {value}{' (stale)' if f.get('stale') else ''} | {pairs} | "
          f"{f.get('machine') or '-'}, {f.get('measured') or '-'} | {rerun_cell(f)} |")


def render(record: dict) -> str:
  """README.md's figures block: a table per section of the README's figures."""
  lines = []
  for section in record["sections"]:
    rows = [f for f in record["figures"]
            if f["file"] == "README.md" and f.get("section") == section["id"]]
    if rows:
      lines += ["", f"**{section['title']}**", "", *HEADER, *map(row, rows)]
  if any(f.get("stale") and f.get("section") for f in record["figures"]):
    lines += ["", *STALE_NOTE]
  return "\n".join(lines).strip("\n")


def write(record: dict, root: pathlib.Path):
  path = root / "README.md"
  readme = path.read_text()
  if block_of(readme) is None:
    raise SystemExit(f"{path}: no {BEGIN} ... {END} block")
  head, rest = readme.split(BEGIN, 1)
  path.write_text(f"{head}{BEGIN}\n{render(record)}\n{END}{rest.split(END, 1)[1]}")


def listing(record: dict, max_minutes: float):
  """One entry a figure; then what --check costs (each command once)."""
  commands = {}
  for f in record["figures"]:
    why = runnable(f, max_minutes, named=False)
    seeds = f" x seeds {f['seeds']}" if f.get("seeds") else ""
    print(f"{f['id']}  [{f['file']}]  {shown(f)}{' (stale)' if f.get('stale') else ''}  "
          f"{f.get('minutes', '-')} min{seeds}  "
          f"{'rerun by --check' if why is None else why.split(':')[0]}\n"
          f"    {f.get('command') or f.get('why')}")
    if why is None:
      commands[f["command"]] = f["minutes"]
  print(f"\n--check: {len(commands)} commands, ~{sum(commands.values()):.0f} min on 2 cores "
        f"(--max-minutes {max_minutes:g})")


def check(record: dict, chosen: list[dict], measured: dict, errors: dict,
          root: pathlib.Path) -> list[str]:
  """The figures that moved or failed and the docs' problems, each one line; prints every
  comparison."""
  failed = [f"{name}: not measured: {why}" for name, why in errors.items()]
  if measured:
    print(f"\nthis machine: {this_machine()} (a speed figure measured under load reads high)")
  for f in chosen:
    if f["id"] in measured:
      why = moved(f, measured[f["id"]])
      print(f"{f['id']}: " + (f"ok (recorded {shown(f)}, measured "
                              f"{json.dumps(measured[f['id']])})" if why is None else
                              f"MOVED: {why}"))
      if why is not None:
        failed.append(f"{f['id']} ({f['file']}): {why}")
  return failed + docs_problems(record, root)


def record_values(record: dict, measured: dict):
  """Writes the measured values into the record (the machine and date with them)."""
  today, machine = time.strftime("%Y-%m-%d"), this_machine()
  for f in record["figures"]:
    if f["id"] in measured:
      value = measured[f["id"]]
      f["value"] = ({k: v if k == "per_seed" else round(v, 6) for k, v in value.items()}
                    if isinstance(value, dict) else
                    [round(v, 6) for v in value] if isinstance(value, list) else round(value, 6))
      f["measured"], f["machine"] = today, machine
      f.pop("stale", None)


def main(argv=None):
  parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  mode = parser.add_mutually_exclusive_group(required=True)
  for name in ("list", "check", "record", "write"):
    mode.add_argument(f"--{name}", action="store_true")
  parser.add_argument("--only", default=None, help="figure ids, comma-separated")
  parser.add_argument("--max-minutes", type=float, default=MAX_MINUTES,
                      help="--check reruns commands estimated at this or less")
  parser.add_argument("--figures", type=pathlib.Path, default=RECORD, help="the record")
  parser.add_argument("--root", type=pathlib.Path, default=ROOT, help="where README.md is")
  args = parser.parse_args(argv)
  record = load(args.figures)
  if args.list:
    return listing(record, args.max_minutes)
  if args.write:
    return write(record, args.root)
  only = set(args.only.split(",")) if args.only else None
  unknown = (only or set()) - {f["id"] for f in record["figures"]}
  if unknown:
    raise SystemExit(f"unknown figure ids: {', '.join(sorted(unknown))} (--list names them)")
  chosen = [f for f in record["figures"] if only is None or f["id"] in only]
  skipped = {f["id"]: runnable(f, args.max_minutes, only is not None) for f in chosen}
  for name, why in skipped.items():
    if why is not None:
      print(f"{name}: {why}")
  measured, errors = measure([f for f in chosen if skipped[f["id"]] is None])
  if args.record:
    record_values(record, measured)
    save(record, args.figures)
    write(record, args.root)  # the block follows the record; other docs are written by hand
    print(f"recorded {len(measured)} figures in {args.figures}, README.md's block written")
    for problem in docs_problems(record, args.root):
      print(f"to mend by hand: {problem}")
    if errors:
      sys.exit("not measured:\n" + "\n".join(f"{k}: {v}" for k, v in errors.items()))
    return None
  failed = check(record, chosen, measured, errors, args.root)
  if failed:
    print("\nFAILED:\n" + "\n".join(failed))
    sys.exit(1)
  print(f"\n{len(measured)} figures rerun, none moved; the docs agree with the record")
  return None


if __name__ == "__main__":
  main()
