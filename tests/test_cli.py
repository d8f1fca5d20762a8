"""jaxflow.cli: a user's mistake is one line on stderr and exit code 2; a bug keeps its traceback."""

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

import numpy as np

from jaxflow import cli, evaluate, predict, train
from jaxflow.runtime import configfile
from jaxflow.configs import default
from jaxflow.data import read_points
from jaxflow.errors import CheckpointError
from jaxflow.network import checkpointing

import commands

REPO = Path(__file__).absolute().parent.parent
TRAIN_PY = commands.script("train.py")


def python(*args, script=None):
  """A real subprocess: for what needs a process of its own (each use says why)."""
  env = dict(os.environ, JAX_PLATFORMS="cpu",
             PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]))
  argv = [sys.executable, "-c", script] if script else [sys.executable, *args]
  return subprocess.run(argv, cwd=REPO, env=env, capture_output=True, text=True, timeout=1200)


def assert_one_line_error(proc, *needles):
  assert proc.returncode == 2, (proc.returncode, proc.stderr[-2000:])
  lines = proc.stderr.strip().splitlines()
  assert len(lines) == 1 and lines[0].startswith("error: "), proc.stderr[-2000:]
  for needle in needles:
    assert needle in lines[0]


def test_guard_prints_one_line_and_exits_2(capsys):
  def main(path):
    raise CheckpointError(f"{path}: truncated\nsecond line")

  with pytest.raises(SystemExit) as info:
    cli.guard(main, "/x/ckpt")
  assert info.value.code == 2
  assert capsys.readouterr().err == "error: /x/ckpt: truncated second line\n"


def test_guard_passes_results_and_bugs_through():
  assert cli.guard(lambda a, b=0: a + b, 1, b=2) == 3
  with pytest.raises(ZeroDivisionError):
    cli.guard(lambda: 1 / 0)


ABANDONED_READ = textwrap.dedent("""
  # An orbax read that failed beside the one raised, collected after its loop closed.
  import asyncio, gc
  from jaxflow import cli
  from jaxflow.errors import CheckpointError
  async def async_deserialize():
    raise ValueError("OUT_OF_RANGE: /x/ckpt/1/state")
  def main():
    loop = asyncio.new_event_loop()
    task = loop.create_task(async_deserialize())
    loop.run_until_complete(asyncio.sleep(0.01))
    loop.close()
    del task
    gc.collect()
    raise CheckpointError("/x/ckpt/1: cannot restore the train state")
  cli.guard(main)
""")


def test_abandoned_orbax_reads_add_nothing_after_the_one_line():
  # A subprocess: what the interpreter reports at garbage collection and exit is the subject.
  proc = python(script=ABANDONED_READ)
  assert_one_line_error(proc, "cannot restore the train state")
  # Other asyncio errors still reach the user.
  proc = python(script=ABANDONED_READ.replace("async_deserialize", "user_coroutine"))
  assert "Task exception was never retrieved" in proc.stderr and proc.returncode == 2


ABSL_MAIN = textwrap.dedent("""
  from absl import flags
  from jaxflow import cli
  from jaxflow.errors import ConfigError
  _N = flags.DEFINE_integer("n", 1, "a number")
  def main(argv):
    if _N.value < 0:
      raise ConfigError(f"--n must be >= 0, got {_N.value}")
    print("n =", _N.value)
  cli.run(main)
""")


def test_run_with_absl_flags():
  # Subprocesses (no jax imported: 0.3 s each): a script's own module-level absl flag, as a user
  # writes one, is defined once a process.
  proc = python(script=ABSL_MAIN + "\n")
  assert proc.returncode == 0 and proc.stdout == "n = 1\n"
  assert_one_line_error(python("-c", ABSL_MAIN, "--n=-3"), "--n must be >= 0, got -3")
  assert_one_line_error(python("-c", ABSL_MAIN, "--n=abc"), "abc")  # a flag parsing error


@pytest.mark.slow
def train_py(*args):
  """`python train.py ARGS` in the repository, run in this process (tests/commands.py)."""
  return commands.run(train.run, *args, cwd=REPO, prog=TRAIN_PY)


def test_train_py_user_errors_are_one_line(tmp_path):
  assert_one_line_error(
    train_py("--config", "configs/default.py:smoke", "--workdir", tmp_path,
             "--config.data.dataset=nosuchformat:/x"),
    "nosuchformat",
  )
  assert_one_line_error(
    train_py("--config", "configs/nosuch.py", "--workdir", tmp_path), "nosuch.py"
  )
  assert_one_line_error(
    train_py("--config", "configs/default.py:smoke", "--workdir", tmp_path,
             "--config.train.stage=3"),
    "config.train.stage must be 1 or 2",
  )
  assert_one_line_error(
    train_py("--config", "configs/default.py:smoke", "--workdir", tmp_path,
             "--config.train.nosuch=3"),
    "unknown config field 'train.nosuch' in --config.train.nosuch=3",
  )
  assert_one_line_error(
    train_py("--config", "configs/default.py:bogus", "--workdir", tmp_path), "bogus"
  )


def test_near_miss_field_is_named_with_its_flag_and_a_suggestion(tmp_path):
  proc = train_py("--config", "configs/default.py:smoke", "--workdir", tmp_path,
                  "--config.train.batchsize=4")
  assert_one_line_error(proc)
  assert proc.stderr == ("error: unknown config field 'train.batchsize' in "
                         "--config.train.batchsize=4; did you mean train.batch_size?\n")
  proc = commands.run(evaluate.run, "--config.model.knnn", "3", cwd=REPO)  # default config; "FLAG V"
  assert proc.stderr == ("error: unknown config field 'model.knnn' in --config.model.knnn; "
                         "did you mean model.knn?\n")


def _leaves(d, prefix=""):
  """Flattened fields of a ConfigDict, written independently of configfile.field_paths."""
  out = {}
  for k, v in d.to_dict().items() if prefix == "" else d.items():
    if isinstance(v, dict):
      out.update(_leaves(v, f"{prefix}{k}."))
    else:
      out[prefix + k] = v
  return out


def test_print_config_lists_every_field_with_its_comment():
  proc = train_py("--config", "configs/default.py:smoke", "--print_config",
                  "--config.train.lr=0.5")
  assert proc.returncode == 0, proc.stderr[-2000:]
  lines = proc.stdout.splitlines()
  expected = _leaves(default.get_config("smoke"))
  expected["train.lr"] = 0.5
  assert len(lines) == len(expected)
  for field, value in expected.items():
    (line,) = [l for l in lines if l.startswith(f"config.{field} = ")]
    assert line.split("  # ")[0] == f"config.{field} = {value!r}"
  assert "config.train.lr = 0.5  # Adam (paper 4.1)." in lines
  # A model field's comment comes from model_config() (`m.knn = 32  # ...`).
  assert "config.model.knn = 8  # neighbours of each point in its own cloud" in proc.stdout


def test_print_config_lists_the_methods_settings_as_they_would_run():
  """predict / evaluate.py --print_config: the chosen method's settings (every stage, nested),
  --steps and --objective applied, with the dataclasses' comments; none for the network alone."""
  runs = {m: commands.run(predict.run, "--print_config", "--method", m, *extra, cwd=REPO)
          for m, extra
          in (("optimise", ["--steps", "30", "--method.optimise.bodies.inlier=0.1",
                            "--method.optimise.clusters.search=device"]),
              ("nsfp", ["--objective", "grid", "--method.nsfp.width=64"]), ("network", []))}
  runs["evaluate"] = commands.run(evaluate.run, "--print_config", "--steps", "7", cwd=REPO,
                                  prog=commands.script("evaluate.py"))
  assert all(p.returncode == 0 for p in runs.values()), {m: p.stderr[-500:] for m, p in runs.items()}
  lines = runs["optimise"].stdout.splitlines()
  assert "method.optimise.descent.steps = 30  # at most" in lines
  assert "method.optimise.rigid_steps = 30" in lines and "method.optimise.polish.steps = 30  # at most" in lines
  assert any(l.startswith("method.optimise.bodies.inlier = 0.1  # metres") for l in lines)
  assert "method.optimise.clusters.search = 'device'" in [l.split("  #")[0] for l in lines]
  assert "method.optimise.bodies.trials = 150  # RANSAC samples a hypothesis" in lines
  assert "method.nsfp.objective = 'grid'" in runs["nsfp"].stdout.splitlines()
  assert "method.nsfp.width = 64" in [l.split("  #")[0] for l in runs["nsfp"].stdout.splitlines()]
  assert "method." not in runs["network"].stdout and "config.eval." in runs["network"].stdout
  assert "method.network" not in runs["evaluate"].stdout  # evaluate.py's default: the network
  proc = commands.run(predict.run, "--print_config", "--method", "optimise", "--objective", "grid")
  assert_one_line_error(proc, "--objective", "--method nsfp")


def test_print_config_and_help_of_train_py_answer_without_loading_jax():
  # Subprocesses: whether a fresh process imports jax is the subject.
  for flag in ("--print_config", "--help"):
    proc = python(script=textwrap.dedent(f"""
      import atexit, sys
      atexit.register(lambda: print("jax loaded:", "jax" in sys.modules, file=sys.stderr))
      sys.argv = ["train.py", "--config", "configs/default.py", "{flag}"]
      from jaxflow import train
      train.run()
    """))
    assert proc.returncode == 0 and "jax loaded: False" in proc.stderr, proc.stderr[-2000:]


def test_predict_says_a_missing_or_empty_point_file_without_loading_jax(tmp_path):
  """The console script and `python -m`: a wrong point file is said before jax loads (5791fe8
  imported jax and the methods first, ~3 s on a CPU), as the in-process command says it."""
  (tmp_path / "empty.npy").touch()
  (tmp_path / "pc.npy").write_bytes(b"x")
  cases = [(["--max_points", "64", f"{tmp_path}/pc.npy", f"{tmp_path}/no.npy"],
            f"{tmp_path}/no.npy: missing file"),
           (["--lidar", str(tmp_path), f"{tmp_path}/pc.npy", "--out", "f.npy"],
            f"{tmp_path}: not a regular file"),
           (["--out", "f.npy", "--", f"{tmp_path}/empty.npy", "b.npy"],
            f"{tmp_path}/empty.npy: empty file")]
  for argv, error in cases:
    proc = python(script=textwrap.dedent(f"""
      import atexit, sys
      atexit.register(lambda: print("jax loaded:", "jax" in sys.modules, file=sys.stderr))
      sys.argv = ["jaxflow-predict", *{argv!r}]
      from jaxflow import predict
      predict.run()
    """))
    *said, loaded = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and loaded == "jax loaded: False", proc.stderr[-2000:]
    assert said == [f"error: {error}"], said
    assert commands.run(predict.run, *argv, cwd=tmp_path).stderr.strip() == said[0]
  assert cli.positionals(["p", "--out", "o.npy", "a", "--nolidar", "b", "--up=z", "-v", "1", "c",
                          "--", "--d"], ("lidar",)) == ["a", "b", "c", "--d"]


def test_configs_path_falls_back_to_the_package(tmp_path, monkeypatch):
  monkeypatch.chdir(tmp_path)  # no configs/ here: the package's
  assert configfile.resolve("configs/default.py:smoke") == (
    f"{configfile.PACKAGE_CONFIGS / 'default.py'}:smoke")
  (tmp_path / "configs").mkdir()
  (tmp_path / "configs" / "default.py").write_text("")
  assert configfile.resolve("configs/default.py") == "configs/default.py"  # a user's own wins


def test_train_says_where_it_wrote(tmp_path):
  (tmp_path / "checkpoints").mkdir()
  for name in ("config.json", "metrics.jsonl", "eval.json"):
    (tmp_path / name).write_text("{}")
  lines = train.written(tmp_path).splitlines()
  assert [l.split()[0] for l in lines] == [str(tmp_path / n) for n in
                                           ("checkpoints", "config.json", "metrics.jsonl",
                                            "eval.json")]


@pytest.mark.slow
def test_predict_text_output_small_cloud_and_size_warning(tmp_path):
  if not checkpointing.SHIPPED_CHECKPOINT.exists():
    pytest.skip("no shipped checkpoint in this tree")
  rng = np.random.default_rng(0)
  np.save(tmp_path / "small.npy", rng.uniform(-5, 5, (100, 3)).astype(np.float32))
  np.save(tmp_path / "big.npy", rng.uniform(-5, 5, (50_000, 3)).astype(np.float32))
  assert_one_line_error(  # refused before any work: no .npy bytes under another name
    commands.run(predict.run, tmp_path / "small.npy", tmp_path / "big.npy", "--out",
                 tmp_path / "flow.dat"),
    "flow.dat: unknown file type '.dat'; use one of .npy, .txt, .csv")
  proc = commands.run(predict.run, tmp_path / "small.npy", tmp_path / "big.npy", "--out",
                      tmp_path / "flow.txt", "--iters", "1")
  assert proc.returncode == 0, proc.stderr[-2000:]
  assert "PC1: all 100 points used; PC2: sampled to 8192 of 50000 points;" in proc.stderr
  assert "warning: PC1 has 100 points and PC2 50000 (500x)" in proc.stderr
  flow = np.loadtxt(tmp_path / "flow.txt")  # text, x y z per line
  assert flow.shape == (100, 3) and np.isfinite(flow).all()


def test_dropped_rows_message_counts_points(tmp_path):
  (tmp_path / "a.xyz").write_text("0 0 0\n1 0 0\nnan 0 0\n0 1 0\n0 0 inf\n1 1 1\n")
  with pytest.warns(UserWarning) as caught:
    points = read_points(tmp_path / "a.xyz")
  assert len(points) == 4
  assert [str(w.message) for w in caught] == [
    f"{tmp_path / 'a.xyz'}: dropped 2 of 6 points with a non-finite value"]


TOOLS = ("jaxflow.predict", "jaxflow.evaluate", "jaxflow.train", "jaxflow.nsfp", "jaxflow.summary",
         "jaxflow.import_pvraft", "jaxflow.data.convert")


def _popen(*args, stdout=subprocess.PIPE):
  """A real subprocess (the help's exit code into a closed pipe is what a shell sees)."""
  env = dict(os.environ, JAX_PLATFORMS="cpu",
             PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]))
  return subprocess.Popen([sys.executable, *map(str, args)], cwd=REPO, env=env, stdout=stdout,
                          stderr=subprocess.PIPE, text=True)


@pytest.mark.slow
def test_every_tool_has_a_help_that_exits_0_also_into_a_closed_pipe():
  helps = {t: _popen("-m", t, "--help") for t in TOOLS}
  helps.update({s: _popen(s, "--help") for s in ("evaluate.py", "train.py")})
  closed = {t: _popen("-m", t, "--helpfull" if t in TOOLS[:5] else "--help") for t in TOOLS}
  for p in closed.values():
    p.stdout.close()  # `| head` that has read nothing: every write of the help fails
  for tool, p in helps.items():
    out, err = p.communicate(timeout=240)
    assert p.returncode == 0, (tool, err[-2000:])
    assert "Traceback" not in err, (tool, err)
    paragraphs = out.strip().split("\n\n")
    if paragraphs[0].startswith("usage:"):  # argparse's tools: the usage, then the description
      paragraphs = paragraphs[1:]
    first = paragraphs[0].strip()
    assert len(first) > 20 and not first.startswith(("USAGE:", "Flags", "positional", "options")), (
      tool, first)
    if tool in ("jaxflow.evaluate", "jaxflow.train", "evaluate.py", "train.py"):
      for flag in ("--coordinator", "--num_processes", "--process_id"):
        assert flag in out, (tool, flag)
    if tool == "jaxflow.predict":  # usage and flags first, the long description after them
      assert out.index("python -m jaxflow.predict PC1 PC2") < out.index("Flags (") < out.index(
        "--out:") < out.index("Method (--method"), out[:3000]
    if tool in ("jaxflow.predict", "jaxflow.evaluate", "jaxflow.nsfp"):
      for flag in ("--method", "--iters", "--max_points", "--full", "--corr_chunk", "--seed",
                   "--save_flows", "--steps", "--objective"):  # the shared flags, in both tools
        assert flag in out, (tool, flag)
  for tool, p in closed.items():
    err = p.stderr.read()
    p.wait(timeout=240)
    assert p.returncode == 0 and "Traceback" not in err and "BrokenPipe" not in err, (tool, err)


def test_old_flag_spellings_are_refused_naming_the_new_one():
  cases = {("jaxflow.predict", "a.npy", "b.npy", "--save-flows", "d"): "--save-flows is now --save_flows",
           ("jaxflow.predict", "a.npy", "b.npy", "--corr-chunk=4"): "--corr-chunk is now --corr_chunk",
           ("jaxflow.predict", "a", "b", "--max-range", "9"): "--max-range is now --max_range",
           ("jaxflow.evaluate", "--render", "d"): "--render is now --render_dir",
           ("jaxflow.evaluate", "--max-points", "9"): "--max-points is now --max_points",
           ("jaxflow.train", "--config", "configs/default.py:smoke", "--workdir", "w",
            "--num-processes", "2"): "--num-processes is now --num_processes"}
  tools = {"jaxflow.predict": predict.run, "jaxflow.evaluate": evaluate.run, "jaxflow.train": train.run}
  for args in cases:
    done = commands.run(tools[args[0]], *args[1:], cwd=REPO)
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 2 and lines == [f"error: {cases[args]}"], (args, done.stderr)


def test_method_settings_are_replaced_field_by_field_with_their_types_checked():
  """configfile.replace_settings, what --method.METHOD.FIELD=V and the API's method_fields use:
  nested fields, strings parsed as the field's type, None only where a field may be none, and a
  ConfigError naming the field for a wrong name, type or value."""
  from jaxflow.errors import ConfigError  # pylint: disable=import-outside-toplevel
  from jaxflow.methods import registry  # pylint: disable=import-outside-toplevel

  default = registry.settings("optimise")
  got = configfile.replace_settings(default, {"descent.steps": "300", "bodies.inlier": "0.1",
                                              "rigid_learning_rate": "1", "choose": "False",
                                              "start_iters": "None"}, "method.optimise")
  assert (got.descent.steps, got.bodies.inlier, got.rigid_learning_rate, got.choose,
          got.start_iters) == (300, 0.1, 1.0, False, None)
  assert isinstance(got.rigid_learning_rate, float) and got.polish == default.polish
  assert configfile.replace_settings(default, {"bodies": "None"}, "m").bodies is None
  assert registry.settings("optimise", steps=30, fields={"polish.steps": 3}).polish.steps == 3
  for fields, words in (({"descent.stepz": "3"}, ["method.optimise.descent.stepz", "steps"]),
                        ({"descent.steps": "0.5"}, ["descent.steps", "not int", "400"]),
                        ({"descent": "None"}, ["block of settings"]),
                        ({"descent.objective": "gird"}, ["descent.objective", "exact, grid"]),
                        ({"bodies.trials": "0"}, ["bodies.trials", ">= 1"]),
                        ({"choose": "1"}, ["not bool"]),
                        ({"start_iters.x": "1"}, ["has no fields"])):
    with pytest.raises(ConfigError) as e:
      registry.settings("optimise", fields=fields)
    assert all(w in str(e.value) for w in words), (fields, str(e.value))
  with pytest.raises(ConfigError, match="network has no --method.network"):
    registry.settings("network", fields={"steps": 3})


def test_commands_in_one_process_answer_as_separate_processes(tmp_path):
  """jaxflow.cli.call (tests/commands.py), what the tests run commands with: two calls in one
  process with different arguments (a config field set, then left at its file's value; another
  config; an error of each tool) answer exactly as two subprocesses, and absl's flags are left as
  found. Subprocesses here: they are the reference."""
  from absl import flags  # pylint: disable=import-outside-toplevel

  cases = [("train.py", "--config", "configs/default.py:smoke", "--print_config",
            "--config.train.lr=0.5", "--config.model.knn=4"),
           ("train.py", "--config", "configs/default.py:smoke", "--print_config"),
           ("train.py", "--config", "configs/default.py:eval", "--print_config", "--nodeterministic"),
           ("train.py", "--config", "configs/default.py:smoke", "--workdir", tmp_path,
            "--config.train.stage=3"),
           ("evaluate.py", "--print_config", "--steps", "7", "--method", "optimise"),
           ("evaluate.py", "--print_config"),
           ("evaluate.py", "--max-points", "9")]
  entries = {"train.py": train.run, "evaluate.py": evaluate.run}
  before = set(flags.FLAGS)
  in_process = [commands.run(entries[c[0]], *c[1:], cwd=REPO, prog=commands.script(c[0]))
                for c in cases]
  assert set(flags.FLAGS) == before and not flags.FLAGS.is_parsed()
  assert "config" not in flags.FLAGS and "method" not in flags.FLAGS
  for case, got in zip(cases, in_process):
    alone = python(*case)
    assert (got.returncode, got.stdout, got.stderr) == (
      alone.returncode, alone.stdout, alone.stderr), case
  # The cases differ where their arguments do (the state of one call does not reach the next).
  assert "config.train.lr = 0.5" in in_process[0].stdout
  assert "config.train.lr = 0.001" in in_process[1].stdout
  assert "config.model.knn = 4" in in_process[0].stdout and "config.model.knn = 8" in in_process[1].stdout
  assert "method.optimise.descent.steps = 7" in in_process[4].stdout
  assert "method." not in in_process[5].stdout
  assert in_process[3].returncode == 2 and in_process[6].returncode == 2
