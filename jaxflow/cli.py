"""Shared command-line wrapper: a user's mistake is one line on stderr and exit code 2.

    from jaxflow import cli
    cli.run(main)              # absl: checks the config flags, parses, then main(argv)
    cli.guard(main, args)      # any other parser: calls main(args) with the same error handling
    cli.call(predict.run, ["pc1.npy", "pc2.npy", "--out", "f.npy"])  # a command in this process

`jaxflow.errors.JaxflowError` (bad file, argument, checkpoint, non-finite training), absl flag
errors, a config file that does not load and a `--config.FIELD` that names no field print
`error: <message>` and exit with 2, without a traceback; anything else is a bug and keeps its
traceback. `--print_config` prints the config (overrides applied) with its fields' comments.
`--help` (`-h`) prints the tool's summary and usage, its flags, then the rest of its description,
and exits with 0 (also into a closed pipe, `--help | head`). Flags are spelled with underscores
(absl's convention); the old hyphenated spellings and renamed flags are refused with the new name
(`RENAMED`).

The options predict and evaluate.py share mean the same in both (`define_run_flags`).
"""

import logging as pylogging
import os
import sys
from pathlib import Path
from typing import Any, Callable

from absl import app, flags, logging
from ml_collections import config_flags

from jaxflow.runtime import configfile, determinism, host_memory, orbax_reports
from jaxflow.errors import ConfigError, JaxflowError

EXIT_USER_ERROR = 2
# The settings evaluate.py and predict use when no --config is given (8192 points, 32 iterations).
EVAL_CONFIG = f"{Path(__file__).absolute().parent / 'configs' / 'default.py'}:eval"
# Old spellings -> the flag that replaced them (every tool refuses the old one, naming the new).
RENAMED = {"save-flows": "save_flows", "max-points": "max_points", "corr-chunk": "corr_chunk",
           "max-range": "max_range", "num-processes": "num_processes",
           "process-id": "process_id", "print-config": "print_config",
           "config.eval.test_time": "--method optimise (config.eval.test_time was removed)",
           "sweep": "method.lidar"}


def fail(message: str):
  """Prints `error: message` as one line on stderr and exits with code 2."""
  print("error: " + " ".join(str(message).split()), file=sys.stderr)
  sys.exit(EXIT_USER_ERROR)


def guard(main: Callable[..., Any], *args, **kwargs):
  """main(*args, **kwargs), with a JaxflowError turned into one line and exit code 2."""
  orbax_reports.drop_closed_loop_reports()
  try:
    return main(*args, **kwargs)
  except JaxflowError as e:
    fail(str(e))


def positionals(argv, switches) -> list[str]:
  """argv's positional arguments, before absl parses it: a flag but `switches` (--NAME, --noNAME)
  given without "=" takes the next argument (a switch left out only hides the one after it)."""
  found, args, takes_value = [], list(argv[1:]), False
  for i, arg in enumerate(args):
    if takes_value:
      takes_value = False
    elif arg == "--":
      return found + args[i + 1:]
    elif arg.startswith("-") and arg != "-":
      name = arg.lstrip("-")
      takes_value = "=" not in name and not {name, name.removeprefix("no")} & set(switches)
    else:
      found.append(arg)
  return found


def _write_and_exit(text: str):
  """Prints `text` to stdout and exits with 0; a reader that closed the pipe (`| head`) is fine."""
  try:
    sys.stdout.write(text)
    sys.stdout.flush()
  except BrokenPipeError:
    os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # no error at exit's flush
  sys.exit(0)


_METHOD_FIELDS = {}  # the command line's --method.NAME.FIELD=V: {(NAME, FIELD): V}
_DEFINED = set()  # the flags the running command defined (run), removed by `call`
_IN_PROCESS = []  # non-empty while `call` runs a command


def take_method_fields(argv: list[str]) -> list[str]:
  """argv without its --method.NAME.FIELD=V arguments, which are kept for `method_fields` (those
  of an earlier call are dropped)."""
  _METHOD_FIELDS.clear()
  kept, positional = [], False
  for arg in argv:
    if arg == "--":
      positional = True
    if positional or not arg.startswith("--method."):
      kept.append(arg)
      continue
    name, eq, value = arg[2:].partition("=")
    parts = name.split(".")
    if not eq or len(parts) < 3 or not all(parts):
      fail(f"{arg}: a method's setting is --method.METHOD.FIELD=VALUE, e.g. "
           "--method.optimise.descent.steps=300 (--print_config lists the fields)")
    _METHOD_FIELDS[(parts[1], ".".join(parts[2:]))] = value
  return kept


def method_fields(method: str, also: tuple = ()) -> dict:
  """{field: value} of the command line's --method.METHOD.FIELD=V (a ConfigError when they name
  a method other than `method` and `also`: predict --lidar --method X takes lidar's and X's)."""
  other = sorted({m for m, _ in _METHOD_FIELDS if m != method and m not in also})
  if other:
    raise ConfigError(f"--method.{other[0]}.* sets the {other[0]} method's settings, but the "
                      f"method is {method} (--method {other[0]} to run it)")
  return {field: value for (m, field), value in _METHOD_FIELDS.items() if m == method}


def check_renamed(argv: list[str], renamed: dict[str, str]):
  """fail() naming the new flag when argv spells a renamed or hyphenated one."""
  for arg in argv[1:]:
    if arg == "--":
      return
    name = arg.lstrip("-").split("=", 1)[0]
    if not arg.startswith("--"):
      continue
    for old, new in renamed.items():
      if name == old or name.startswith(old + "."):
        new = new if new.startswith("--") else "--" + new
        if " " not in new:  # a field of a renamed block: the same field of the new one
          new += name[len(old):]
        fail(f"--{name} is now {new}")


def requested_model_fields(config_flag) -> list[str]:
  """The `config.model` fields a user asked for on a command line (`config_flag`: the absl flag of
  a config file): those given as `--config.model.FIELD=...` and, with an explicit config file, every
  field of its model except the runtime ones, which stay the checkpoint's unless given."""
  from jaxflow.network.model_fields import RUNTIME_MODEL_FIELDS  # pylint: disable=import-outside-toplevel

  given = {k.split(".", 1)[1] for k in config_flags.get_override_values(config_flag)
           if k.startswith("model.")}
  if config_flag.present:
    given |= {k for k in config_flag.value.model.keys() if k not in RUNTIME_MODEL_FIELDS}
  return sorted(given)


def define_process_flags():
  """--coordinator, --num_processes and --process_id of train.py and evaluate.py (read by
  `distributed.initialize_from_flags`; defined here, without jax, so that --print_config and --help
  answer before jax loads)."""
  flags.DEFINE_string(
    "coordinator", None, "HOST:PORT of process 0, for a run over many processes (hosts or GPUs).")
  flags.DEFINE_integer("num_processes", None, "Number of processes in the run.")
  flags.DEFINE_integer("process_id", None, "This process's index, 0 .. N-1.")


def define_run_flags(default_method: str):
  """The flags predict and evaluate.py share, with one meaning in both: --method, --steps,
  --objective, --iters, --max_points, --full, --corr_chunk, --seed, --save_flows."""
  from jaxflow.methods import registry  # pylint: disable=import-outside-toplevel

  flags.DEFINE_enum("method", default_method, list(registry.METHODS), "; ".join(
    f"{name}: {m.summary}" for name, m in registry.REGISTRY.items())
    + f" (docs/methods.md). Default {default_method}.")
  flags.DEFINE_integer("steps", None, "Cap the optimisation steps of nsfp / optimise.")
  flags.DEFINE_enum("objective", None, ["exact", "grid"], "--method nsfp: NSFP's objective, exact "
                    "(default: two-way Chamfer, k-d tree every step) or grid (one-way distance "
                    "grids: faster, less accurate).")
  flags.DEFINE_integer("iters", None, "Flow iterations of the network (default: "
                       "config.eval.num_iters, 32; for optimise's starting flow 8).")
  flags.DEFINE_integer("max_points", None, "Clouds above this size are sampled to it (default: "
                       "config.eval.num_points, 8192; 0: whole clouds).")
  flags.DEFINE_bool("full", False, "Whole clouds (--max_points 0), the correlation and kNN built "
                    "config.model.corr_chunk rows at a time (--corr_chunk; memory linear in the "
                    "points).")
  flags.DEFINE_integer("corr_chunk", None, "pc1 rows of the correlation and kNN built at a time "
                       "(--full): sets config.model.corr_chunk (default: the checkpoint's; 0: as many as "
                       "the clouds' sizes and the device's memory allow, jaxflow.geometry.ops).")
  flags.DEFINE_integer("seed", None, "Seed of the point sampling (default: config.eval.seed, 0).")
  flags.DEFINE_string("save_flows", None, "Write the flow of every pair into this folder, one "
                      "NAME.npy per pair, NAME made from the pair (jaxflow.evaluation.export).")


def run_methods() -> list[tuple[str, object]]:
  """[(name, settings)] of the methods a command line runs (jaxflow.methods.registry): --method's,
  with --steps, --iters, --objective and its --method.NAME.FIELD=V. Predict's --lidar (or --method
  lidar) is the raw-sweep method, listed first, with --max_range its max_range and, as its
  `method`, --method's (default: the tool's own), listed second with those flags, and `start` when
  --method is given: the method runs on a camera's view, and on a sweep as a start when named."""
  from jaxflow.methods import registry  # pylint: disable=import-outside-toplevel

  given = flags.FLAGS
  name = given.method
  lidar = "lidar" in given and (given.lidar or registry.get(name).raw_sweeps)
  if not lidar:
    if "max_range" in given and given.max_range is not None:
      raise ConfigError("--max_range sets the lidar method's max_range: it needs --lidar")
    return [(name, registry.settings(name, given.steps, given.iters, given.objective,
                                     method_fields(name)))]
  raw = next(m for m, chosen in registry.REGISTRY.items() if chosen.raw_sweeps)
  nested = given["method"].default if name == raw else name
  fields = {"method": nested, "start": name != raw and bool(given["method"].present),
            **({} if given.max_range is None else {"max_range": given.max_range})}
  names = {raw, nested, *(m for m, _ in _METHOD_FIELDS)}  # method.lidar.method may name another
  chosen = registry.settings(raw, fields={**fields, **method_fields(raw, tuple(names))})
  if chosen.method is None:
    return [(raw, chosen)]
  registry.nested(chosen.method)
  return [(raw, chosen), (chosen.method, registry.settings(
    chosen.method, given.steps, given.iters, given.objective,
    method_fields(chosen.method, (raw, nested))))]


def run_settings(config):
  """config with the shared flags applied (config.eval.num_iters / num_points / seed,
  config.model.corr_chunk), and the model fields asked for (requested_model_fields)."""
  given = flags.FLAGS
  for name in ("iters", "max_points", "steps", "corr_chunk", "seed"):
    if given[name].value is not None and given[name].value < 0:
      raise ConfigError(f"--{name} must be >= 0, got {given[name].value}")
  if given.iters == 0:
    raise ConfigError("--iters must be >= 1, got 0")
  if given.full and given.max_points:
    raise ConfigError(f"--full uses whole clouds: drop --max_points {given.max_points}")
  config = config.copy_and_resolve_references()
  model_fields = requested_model_fields(given["config"])
  with config.unlocked():
    if given.iters is not None:
      config.eval.num_iters = given.iters
    if given.max_points is not None:
      config.eval.num_points = given.max_points
    if given.full:
      config.eval.num_points = 0
    if given.seed is not None:
      config.eval.seed = given.seed
    if given.corr_chunk is not None:  # the model config is its one home
      config.model.corr_chunk = given.corr_chunk
      model_fields = sorted({*model_fields, "corr_chunk"})
  return config, model_fields


def _print_help(description: str | None, full: bool):
  """The description's summary and usage lines, the flags, then the rest of the description."""
  paragraphs = (description or "").strip().split("\n\n")
  usage = next((i + 1 for i, p in enumerate(paragraphs) if p.startswith("    ")), 1)
  head, rest = "\n\n".join(paragraphs[:usage]), "\n\n".join(paragraphs[usage:])
  flags_help = flags.FLAGS.get_help() if full else flags.FLAGS.main_module_help()
  _write_and_exit(f"{head}\n\nFlags ({'all' if full else '--helpfull: all of them'}):\n"
                  f"{flags_help}\n" + (f"\n{rest}\n" if rest else ""))


def _parse_flags(argv: list[str], config_names=(),
                 host_memory_default=host_memory.RELEASE) -> list[str]:
  try:
    argv = flags.FLAGS(argv)
  except flags.Error as e:
    fail(str(e))
  if flags.FLAGS.deterministic:  # before anything starts jax's backend (jaxflow.runtime.determinism)
    try:
      determinism.enable()
    except ConfigError as e:
      fail(str(e))
  if not flags.FLAGS["verbosity"].present:  # orbax and jax log every step of a save at INFO
    logging.set_verbosity(logging.WARNING)
  if flags.FLAGS.print_config:
    text = []
    for name in config_names:
      path = config_flags.get_config_filename(flags.FLAGS[name])
      text.append(configfile.describe(flags.FLAGS[name].value, path.split(":")[0], name) + "\n")
    if "method" in flags.FLAGS:  # predict, evaluate.py: the methods' settings as they would run
      from jaxflow.methods import registry  # pylint: disable=import-outside-toplevel
      try:
        text += [registry.describe_settings(name, chosen) + "\n"
                 for name, chosen in run_methods() if chosen is not None]
      except ConfigError as e:
        fail(str(e))
    _write_and_exit("".join(text))
  from jaxflow.runtime import compile_cache  # pylint: disable=import-outside-toplevel  (jax: not for --help)
  if _IN_PROCESS and flags.FLAGS.host_memory is None:
    host_memory_default = host_memory.RELEASE  # malloc's settings are the caller's (cli.call)
  try:  # before jax starts its threads, before anything compiles
    notes = [host_memory.keep(flags.FLAGS.host_memory, host_memory_default),
             compile_cache.enable(flags.FLAGS.compilation_cache)]
  except ValueError as e:
    fail(str(e))
  for note in filter(None, notes):
    print(f"note: {note}", file=sys.stderr)
  return argv


def run(main: Callable[[list], Any], define_flags: Callable[[], Any] | None = None,
        config_files: dict[str, str | None] | None = None, renamed: dict[str, str] | None = None,
        description: str | None = None, host_memory_default: str = host_memory.RELEASE):
  """absl's `app.run(main)` with `guard`; flag and config errors also become one line and exit 2.

  `config_files` maps each config-file flag that `define_flags` defines to its default file (or
  None): the file and every `--NAME.FIELD` of the command line are checked before absl sees them
  (ml_collections loads a default file, overrides applied, as soon as its flag is defined). --help
  shows main's module docstring and the flags `define_flags` defines (exit 0); `renamed`: more old
  flag names -> new ones than RENAMED. `host_memory_default`: whether malloc keeps freed memory
  when neither --host_memory nor $JAXFLOW_HOST_MEMORY says (jaxflow.runtime.host_memory).
  """
  config_files = config_files or {}
  _DEFINED.clear()  # (cli.call removes these afterwards)
  check_renamed(sys.argv, {**RENAMED, **(renamed or {})})
  sys.argv = take_method_fields(sys.argv)
  try:
    for name, default in config_files.items():
      sys.argv = configfile.check_argv(sys.argv, name, default)
  except ConfigError as e:
    fail(str(e))
  before = set(flags.FLAGS)
  try:
    if define_flags is not None:
      define_flags()
  finally:  # (also when a config default fails to load: cli.call removes what was defined)
    _DEFINED.update(set(flags.FLAGS) - before)
  if _METHOD_FIELDS and "method" not in flags.FLAGS:
    fail(f"--method.{'.'.join(next(iter(_METHOD_FIELDS)))}: this command has no --method")
  flags.DEFINE_bool("print_config", False, "Print the config (with the overrides given) field by "
                    "field, with each field's comment, and exit.")
  flags.DEFINE_bool("deterministic", False, "Run-to-run identical results on a GPU too (XLA's "
                    "deterministic GPU ops; slower). The CPU is deterministic already "
                    "(docs/methods.md, Determinism).")
  flags.DEFINE_string("compilation_cache", None, "Folder of JAX's persistent compilation cache: a "
                      "second run reads back what the first compiled (default: "
                      "$JAXFLOW_COMPILATION_CACHE, else ~/.cache/jaxflow/xla; 'off': none; "
                      "jaxflow.runtime.compile_cache).")
  flags.DEFINE_enum("host_memory", None, list(host_memory.CHOICES), "keep: malloc keeps the memory a "
                    "compiled program frees for its next call (no fresh page faults; the process "
                    "holds what it took); release: malloc as it is. Default: "
                    f"$JAXFLOW_HOST_MEMORY, else {host_memory_default} (jaxflow.runtime.host_memory).")
  _DEFINED.update(set(flags.FLAGS) - before)
  for name in sorted(set(flags.FLAGS) - before):  # --help shows sys.argv[0]'s key flags
    if "." not in name:  # the config's fields: --print_config lists them
      flags.FLAGS.register_key_flag_for_module(sys.argv[0], flags.FLAGS[name])
  help_asked = [a for a in sys.argv[1:] if a in ("--help", "-h", "--helpshort", "-?", "--helpfull")]
  if help_asked:
    _print_help(description or sys.modules[main.__module__].__doc__,
                full=help_asked[0] == "--helpfull")
  app.run(lambda argv: guard(main, argv),
          flags_parser=lambda argv: _parse_flags(argv, list(config_files), host_memory_default))


def call(command: Callable[[], Any], argv: list[str], prog: str | None = None) -> int:
  """Runs a command's console-script function (`command`: predict.run, evaluate.run, train.run,
  ...) on `argv` (without the program name) in this process, as `python -m` would in its own, and
  returns its exit code: the compiled programs of earlier calls are reused (the tests' commands).

  What it prints goes to sys.stdout / sys.stderr as they are when called (redirect them to read
  it). A bug prints its traceback on stderr and gives 1, as a process would. Afterwards absl's flags
  are as before (the command's removed, the rest unparsed), and so are the logging handlers and
  JAX's compilation-cache settings; malloc is left as it is (--host_memory: a process's setting),
  and `--deterministic` needs a process of its own (XLA reads its flags once).
  """
  import traceback  # pylint: disable=import-outside-toplevel

  app.define_help_flags()  # once a process: theirs are not the command's to remove
  module = sys.modules[command.__module__]
  saved_argv, saved_handlers = sys.argv, list(pylogging.getLogger().handlers)
  saved_done = (app._run_init.done, app._register_and_parse_flags_with_usage.done)  # pylint: disable=protected-access
  saved_verbosity, was_parsed = logging.get_verbosity(), flags.FLAGS.is_parsed()
  saved_cache = _compile_cache().settings() if "jax" in sys.modules else None
  sys.argv = [prog or getattr(module, "__file__", None) or command.__module__, *map(str, argv)]
  _IN_PROCESS.append(True)
  try:
    command()
    code = 0
  except SystemExit as e:
    code = e.code if isinstance(e.code, int) else 0 if e.code is None else 1
    if not isinstance(e.code, (int, type(None))):
      print(e.code, file=sys.stderr)  # what the interpreter prints for sys.exit("text")
  except Exception:  # pylint: disable=broad-except  (a bug: the traceback, exit 1)
    traceback.print_exc()
    code = 1
  finally:
    _IN_PROCESS.pop()
    for name in sorted(set(flags.FLAGS)):  # the command's flags and its config's --NAME.FIELD
      if name in _DEFINED or name.split(".")[0] in _DEFINED:
        delattr(flags.FLAGS, name)
    _DEFINED.clear()
    _METHOD_FIELDS.clear()
    flags.FLAGS.unparse_flags()
    if was_parsed:
      flags.FLAGS.mark_as_parsed()
    app._run_init.done, app._register_and_parse_flags_with_usage.done = saved_done  # pylint: disable=protected-access
    logging.set_verbosity(saved_verbosity)
    pylogging.getLogger().handlers[:] = saved_handlers
    if saved_cache is not None:
      _compile_cache().restore(saved_cache)
    sys.argv = saved_argv
  return code


def _compile_cache():
  from jaxflow.runtime import compile_cache  # pylint: disable=import-outside-toplevel  (jax)
  return compile_cache
