"""The docs say what the code does: every command of README.md and docs/*.md runs at toy size (or
is listed below with the reason it cannot), and the Python blocks run as written."""

import contextlib
import io
import re
import shlex
import sys
from pathlib import Path

import numpy as np
import pytest

import commands

ROOT = Path(__file__).absolute().parent.parent
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
TOOLS = r"(python3?|jaxflow-\w+|pip|bash|srun|tensorboard)\b"

# Documented commands that cannot run at toy size here, by a part of the command: the reason.
NOT_RUN = {
  "pip install": "installs packages (tests/test_install.py installs the package into a fresh venv)",
  "pip download": "downloads wheels from the package index",
  "-m pytest": "the test suite itself",
  "srun ": "needs a SLURM allocation (tests/test_distributed.py runs two processes)",
  "scripts/gpu_round.sh": "a GPU round: minutes on an accelerator",
  "jaxflow.import_pvraft PVRAFT.pth": "needs PV-RAFT's weights (tests/test_pvraft_fidelity.py "
                                      "imports the reference fixture's)",
  "jaxflow.data.convert --dataset opensf:": "needs Argoverse 2 logs (tests/test_data_opensf.py "
                                            "converts a made-up log)",
  "-m av2.evaluation.scene_flow.eval": "av2's own evaluator on a submission (tests/test_submission.py "
                                       "runs it on a fixture's export)",
  "--submission": "needs Argoverse 2 labels (tests/test_submission.py exports and scores a fixture)",
}
# Commands checked with --print_config only (the config file, its argument and every
# --config.FIELD are loaded; nothing is trained or evaluated): they train the paper-size models or
# need real data (FT3D, KITTI) or a checkpoint of another model, or several hosts.
CONFIG_ONLY = ("configs/ft3d", "configs/paper.py", "configs/ablation.py", "configs/pvraft.py",
               "configs/kitti_eval.py", "configs/argoverse_eval.py", "--coordinator")
# Toy overrides (all of them existing flags or config fields of the documented commands).
TRAIN_TOY = {"train.num_steps": "2", "train.log_every": "1", "train.checkpoint_every": "2",
             "train.batch_size": "2", "train.num_iters": "1", "data.num_points": "64",
             "data.dataset": "synthetic_lidar:4", "eval.dataset": "synthetic_lidar:2",
             "eval.num_points": "64", "eval.num_iters": "1", "eval.batch_size": "2"}
RUN_TOY = ["--iters", "1", "--max_points", "64", "--steps", "2"]  # predict, nsfp, evaluate.py


def documented_commands(path: Path) -> list[tuple[int, str]]:
  """(line, command) of every shell command of a markdown file: lines of indented code blocks and
  of ```bash / ``` blocks that start with a tool, continuation lines joined, comments dropped."""
  found, fence, pending = [], None, None
  for number, line in enumerate(path.read_text().splitlines(), 1):
    if line.startswith("```"):
      fence = None if fence is not None else line[3:].strip()
      continue
    in_block = (fence in ("", "bash", "sh", "shell")) or (fence is None and line.startswith("    "))
    text = line.strip()
    if pending is not None:
      pending = (pending[0], pending[1] + " " + text.rstrip("\\").strip())
      if not text.endswith("\\"):
        found.append(pending)
        pending = None
      continue
    if in_block and re.match(TOOLS, text):
      command = re.sub(r"\s+#\s.*$", "", text)
      if command.endswith("\\"):
        pending = (number, command.rstrip("\\").strip())
      else:
        found.append((number, command))
  return [(n, c) for n, c in found]


def every_command() -> list[tuple[str, str]]:
  """("FILE:LINE", one command) of every doc; `a && b` gives both."""
  return [(f"{path.name}:{number}", part.strip()) for path in DOCS
          for number, command in documented_commands(path) for part in command.split("&&")]


def plan(command: str) -> tuple[str, str]:
  """(how, why): "skip" (NOT_RUN), "config" (--print_config only) or "run" (toy size)."""
  for part, reason in NOT_RUN.items():
    if part in command:
      return "skip", reason
  if any(part in command for part in CONFIG_ONLY):
    return "config", "the paper-size model, real data or several hosts"
  return "run", "toy size"


def test_every_documented_command_is_run_or_listed_with_a_reason():
  commands = every_command()
  assert len(commands) > 30  # the parser finds the docs' commands
  tools = {shlex.split(c)[0] for _, c in commands}
  assert tools <= {"python", "python3", "bash", "srun"}, tools
  plans = {(where, c): plan(c)[0] for where, c in commands}
  assert set(plans.values()) == {"skip", "config", "run"}
  # Every command that runs has a rule below (predict, nsfp, evaluate.py, train.py).
  for where, command in commands:
    if plans[(where, command)] == "run":
      assert toy_args(command, Path("/t"), Path("/t/ck")) is not None, (where, command)


def _sweep(up: str, seed: int) -> np.ndarray:
  """A raw LiDAR-like sweep: ground, boxes (moved by 0.5 m in the second), far points."""
  rng = np.random.default_rng(0)
  ground = np.c_[rng.uniform(-25, 25, (400, 2)), rng.normal(-1.7, 0.02, 400)]
  boxes = np.concatenate([rng.uniform(0, 1, (80, 3)) * [3, 2, 1.6] + [x, y, -1.7]
                          for x, y in ((6, 2), (-8, 4), (3, -9))]) + [0.5 * seed, 0, 0]
  far = rng.uniform(-1, 1, (20, 3)) + [40, 5, 0]
  points = np.concatenate([ground, boxes, far]).astype(np.float32)
  return points[:, [0, 2, 1]] if up == "y" else points  # y up: the camera frame's axes


def _write_cloud(path: Path, points: np.ndarray):
  from jaxflow.evaluation import export  # pylint: disable=import-outside-toplevel
  if path.suffix == ".ply":
    export.write_ply(path, points)
  elif path.suffix == ".bin":
    np.c_[points, np.zeros(len(points), np.float32)].astype(np.float32).tofile(path)
  else:
    np.save(path, points)


def toy_args(command: str, cwd: Path, checkpoint: Path) -> list[str] | None:
  """The argv of a documented command at toy size (point files written into `cwd`), or None."""
  argv = shlex.split(command.replace("[", "").replace("]", ""))
  argv = [{"PC1": "pc1.ply", "PC2": "pc2.ply"}.get(a, a) for a in argv]  # as README.md's
  argv = _this_python(argv)
  if argv[1] in ("train.py", "evaluate.py"):
    argv[1] = str(ROOT / argv[1])
  tool = argv[2] if argv[1] == "-m" else Path(argv[1]).name
  if tool in ("jaxflow.predict", "jaxflow.nsfp"):
    lidar, up = "--lidar" in argv, argv[argv.index("--up") + 1] if "--up" in argv else "z"
    files = [a for a in argv[3:] if Path(a).suffix in (".npy", ".ply", ".bin")
             and argv[argv.index(a) - 1] not in ("--out",)]
    for i, name in enumerate(files):  # two, or a log's sweeps
      points = _sweep(up, i) if lidar else _sweep("y", i)[400:640]  # the cut part of a sweep
      if cwd.is_dir():
        _write_cloud(cwd / name, points)
    return argv + RUN_TOY
  if tool == "evaluate.py":
    out, skip = [], False
    for i, a in enumerate(argv):
      if skip:
        skip = False
        continue
      if a in ("--checkpoint", "--dataset") and i + 1 < len(argv):
        out += [a, str(checkpoint) if a == "--checkpoint" else "synthetic_lidar:2"]
        skip = True
      elif not a.startswith("--config.eval.num_points"):
        out.append(a)
    if "--checkpoint" not in out:
      out += ["--checkpoint", str(checkpoint)]
    return out + RUN_TOY
  if tool == "train.py":
    out = [a for a in argv if not any(a.startswith(f"--config.{k}=") for k in TRAIN_TOY)]
    i = out.index("--workdir")
    out[i + 1] = str(cwd / Path(out[i + 1]).name)
    return out + [f"--config.{k}={v}" for k, v in TRAIN_TOY.items()]
  return None


def _this_python(argv: list[str]) -> list[str]:
  """`python` / `python3` of a documented command as the interpreter running the tests (a venv
  that is not activated: PATH's python may lack the project's packages)."""
  return [sys.executable, *argv[1:]] if argv and argv[0] in ("python", "python3") else argv


def _run(argv, cwd) -> tuple[int, str, str]:
  """(exit code, stdout, stderr) of a documented command's toy argv, run in this process
  (tests/commands.py): the commands share one import of jax and their compiled programs. The
  command as a shell starts it (console scripts, `python -m`) is tests/test_install.py's and
  tests/test_cli.py's subject, not this file's."""
  from jaxflow import evaluate, nsfp, predict, train  # pylint: disable=import-outside-toplevel
  tool = argv[2] if argv[1] == "-m" else Path(argv[1]).name
  entry = {"jaxflow.predict": predict.run, "jaxflow.nsfp": nsfp.run, "evaluate.py": evaluate.run,
           "train.py": train.run}[tool]
  args = argv[3:] if argv[1] == "-m" else argv[2:]
  done = commands.run(entry, *args, cwd=cwd, prog=argv[1] if argv[1] != "-m" else None)
  return done.returncode, done.stdout, done.stderr


def _run_all(jobs: dict) -> dict:
  """{key: (returncode, stdout, stderr)} of {key: (argv, cwd)}, one after another."""
  return {k: _run(argv, cwd) for k, (argv, cwd) in jobs.items()}


def _toy_key(command: str, checkpoint: Path) -> tuple:
  """A command at toy size up to the names of its files and its workdir: two documented commands
  of the same key run the same code (e.g. the main job in README.md and docs/training.md, whose
  step count the toy size replaces; one predict command on pc1.ply, another on frame1.ply)."""
  argv = toy_args(command, Path("CWD"), checkpoint)  # (no files written)
  return tuple("FILE" + Path(a).suffix if Path(a).suffix in (".npy", ".ply", ".bin", ".png",
                                                             ".html", ".json")
               else "WORKDIR" if i and argv[i - 1] == "--workdir" else a
               for i, a in enumerate(argv))


@pytest.mark.slow
def test_every_documented_command_runs_at_toy_size(tmp_path):
  documented = [(w, c) for w, c in every_command() if plan(c)[0] != "skip"]
  main_job = next(c for _, c in documented if plan(c)[0] == "run" and "train.py" in c)
  done = _run(toy_args(main_job, tmp_path, None), tmp_path)
  assert done[0] == 0, done[2][-2000:]  # its toy run is the checkpoint of the other commands
  argv = shlex.split(main_job)
  checkpoint = tmp_path / Path(argv[argv.index("--workdir") + 1]).name
  jobs = {(w, c): (_this_python(shlex.split(c.replace("[", "").replace("]", "")))
                   + ["--print_config"], ROOT) for w, c in documented if plan(c)[0] == "config"}
  seen = {_toy_key(main_job, checkpoint)}  # the main job ran above
  for i, (where, command) in enumerate(c for c in documented if plan(c[1])[0] == "run"):
    same = _toy_key(command, checkpoint)
    if same in seen:  # e.g. the main job in README.md and docs/training.md: run once
      continue
    seen.add(same)
    cwd = tmp_path / f"cmd{i}"
    cwd.mkdir()
    jobs[(where, command)] = (toy_args(command, cwd, checkpoint), cwd)
  failed = {k: r[2][-1500:] for k, r in _run_all(jobs).items() if r[0] != 0}
  assert failed == {}


# Python blocks of the docs, by file: what each is checked against (or why it is not run).
PYTHON_BLOCKS = {"README.md": 1, "network.md": 1, "users.md": 2}
NOT_RUN_BLOCKS = {("users.md", 1): "a fragment: pc1, pc2, flow, flow_gt and a run's metrics are the "
                                   "reader's (tests/test_viz.py draws each picture)"}


def python_blocks(path: Path) -> list[str]:
  return re.findall(r"```python\n(.*?)```", path.read_text(), flags=re.S)


def test_every_python_block_is_run_or_listed():
  assert {p.name: len(python_blocks(p)) for p in DOCS if python_blocks(p)} == PYTHON_BLOCKS


def _exec(block: str, name: str) -> str:
  printed = io.StringIO()
  with contextlib.redirect_stdout(printed):
    exec(compile(block, name, "exec"), {})  # pylint: disable=exec-used
  return printed.getvalue().strip()


@pytest.mark.slow
def test_network_doc_python_block_runs_as_written():
  (block,) = python_blocks(ROOT / "docs" / "network.md")
  assert _exec(block, "network.md") == "(1, 8, 256, 3) (1, 256, 3)"


@pytest.mark.slow
def test_readme_python_block_recovers_the_motion_with_the_commands_default():
  """predict_flow's default is the command's (optimise): the README's scene moved by (0.2, 0, 0.5)
  gives that flow (the network alone gave (0.25, 0.09, 0.20))."""
  from jaxflow import cli, inference  # pylint: disable=import-outside-toplevel
  from jaxflow.network import checkpointing
  if not checkpointing.SHIPPED_CHECKPOINT.exists():
    pytest.skip("no shipped checkpoint in this tree")
  assert inference.DEFAULT_METHOD == "optimise"
  (block,) = python_blocks(ROOT / "README.md")
  printed = _exec(block, "README.md")
  shape, mean = re.fullmatch(r"\((\d+), 3\) \[(.*)\]", printed).groups()
  assert shape == "2000"
  np.testing.assert_allclose(np.array(mean.split(), float), [0.2, 0.0, 0.5], atol=0.02)
  del cli


@pytest.mark.slow
def test_users_doc_python_block_runs_on_toy_files(tmp_path, monkeypatch):
  from jaxflow.network import checkpointing  # pylint: disable=import-outside-toplevel
  if not checkpointing.SHIPPED_CHECKPOINT.exists():
    pytest.skip("no shipped checkpoint in this tree")
  for i in (1, 2):
    _write_cloud(tmp_path / f"frame{i}.ply", _sweep("y", i - 1)[400:640])
  (tmp_path / "runs").mkdir()
  (tmp_path / "runs" / "my_run").symlink_to(checkpointing.SHIPPED_CHECKPOINT)
  monkeypatch.chdir(tmp_path)
  block = python_blocks(ROOT / "docs" / "users.md")[0]
  printed = _exec(block.replace("max_points=8192", "max_points=64"), "users.md")
  assert printed.startswith("(240, 3)") and (tmp_path / "frame1_moved.ply").exists()
