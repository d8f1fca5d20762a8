"""Config files on the command line: load `FILE.py[:ARG]`, check `--config.FIELD` names, describe.

    config = load("configs/default.py:smoke")       # ConfigError if the file does not load
    argv = check_argv(argv, "config")               # ConfigError naming a field that does not exist
    print(describe(config, "configs/default.py"))   # field = value  # the field's comment

A `configs/NAME.py` that does not exist in the working directory is the package's own
(jaxflow/configs/NAME.py), so the documented commands work from any folder after `pip install`.
"""

import ast
import dataclasses
import difflib
import importlib.util
import inspect
import io
import pathlib
import re
import tokenize

import ml_collections

from jaxflow.errors import ConfigError

PACKAGE_CONFIGS = pathlib.Path(__file__).absolute().parent / "configs"


def resolve(spec: str) -> str:
  """`spec` with a missing `configs/...` path replaced by the package's file of that name."""
  path, sep, arg = spec.partition(":")
  parts = pathlib.PurePath(path).parts
  if not pathlib.Path(path).exists() and len(parts) == 2 and parts[0] == "configs":
    packaged = PACKAGE_CONFIGS / parts[1]
    if packaged.exists():
      return f"{packaged}{sep}{arg}"
  return spec


def load(spec: str, flag: str = "config", given: str | None = None) -> ml_collections.ConfigDict:
  """get_config(ARG) of the file FILE.py of `spec` = "FILE.py[:ARG]"; any failure is a ConfigError
  (naming `given`, the spec as the user wrote it, when the path was resolved)."""
  path, sep, arg = spec.partition(":")
  try:
    module_spec = importlib.util.spec_from_file_location(f"{flag}_config", path)
    if module_spec is None:
      raise OSError(f"not a Python file: {path}")
    module = importlib.util.module_from_spec(module_spec)
    module_spec.loader.exec_module(module)
    return module.get_config(*([arg] if sep else []))
  except Exception as e:  # pylint: disable=broad-except  # a user's file: any error is theirs
    raise ConfigError(
      f"--{flag}={given or spec}: cannot load the config file: {type(e).__name__}: {e}") from None


def field_paths(config, prefix: str = "") -> list[str]:
  """Every leaf field of a ConfigDict as a dotted path, in order."""
  paths = []
  for key, value in config.items():
    if isinstance(value, ml_collections.ConfigDict):
      paths += field_paths(value, f"{prefix}{key}.")
    else:
      paths.append(prefix + key)
  return paths


def _has_field(config, path: str) -> bool:
  node = config
  for part in path.split("."):
    if not isinstance(node, ml_collections.ConfigDict) or part not in node:
      return False
    node = node[part]
  return True


def _flag_value(argv: list[str], flag: str) -> tuple[int, str | None]:
  """(index in argv of the value of --flag, the value); (-1, None) when not given."""
  for i, arg in enumerate(argv):
    if arg in (f"--{flag}", f"-{flag}") and i + 1 < len(argv):
      return i + 1, argv[i + 1]
    for dashes in ("--", "-"):
      if arg.startswith(f"{dashes}{flag}="):
        return i, arg.split("=", 1)[1]
  return -1, None


def check_argv(argv: list[str], flag: str, default: str | None = None) -> list[str]:
  """argv with --flag's `configs/...` path resolved (`resolve`), after checking that the file loads
  and that every `--flag.FIELD` names a field of its config; ConfigError otherwise."""
  argv = list(argv)
  index, spec = _flag_value(argv, flag)
  given = spec
  if spec is None:
    spec = default
  elif resolve(spec) != spec:
    resolved = resolve(spec)
    argv[index] = resolved if argv[index] == spec else f"{argv[index].split('=')[0]}={resolved}"
    spec = resolved
  overrides = [a for a in argv if a.lstrip("-").split("=")[0].startswith(f"{flag}.")
               or a.lstrip("-").split("=")[0].startswith(f"no{flag}.")]
  if spec is None or not overrides and index < 0:
    return argv  # nothing given: absl reports a missing required flag itself
  config = load(spec, flag, given)
  known = field_paths(config)
  for arg in overrides:
    path = arg.lstrip("-").split("=")[0].split(".", 1)[1]
    if "[" in path or _has_field(config, path):
      continue
    close = difflib.get_close_matches(path, known, n=1, cutoff=0.6)
    hint = f"; did you mean {close[0]}?" if close else ""
    raise ConfigError(f"unknown config field '{path}' in {arg}{hint}")
  return argv


def _comments(path) -> dict[str, tuple[str, str]]:
  """{dotted target after its root name: (inline comment, comment block above)} of a config file's
  attribute assignments (`config.train.lr = 1e-3  # Adam.` gives "train.lr": ("Adam.", ""))."""
  source = pathlib.Path(path).read_text()
  lines = source.splitlines()
  inline = {}
  for token in tokenize.generate_tokens(io.StringIO(source).readline):
    if token.type == tokenize.COMMENT and lines[token.start[0] - 1].strip() != token.string:
      inline[token.start[0]] = token.string.lstrip("# ").strip()
  found = {}
  for node in ast.walk(ast.parse(source)):
    if not (isinstance(node, ast.Assign) and len(node.targets) == 1):
      continue
    names, target = [], node.targets[0]
    while isinstance(target, ast.Attribute):
      names.insert(0, target.attr)
      target = target.value
    if not names or not isinstance(target, ast.Name):
      continue
    above, row = [], node.lineno - 2
    while row >= 0 and lines[row].strip().startswith("#"):
      above.insert(0, lines[row].strip().lstrip("# ").strip())
      row -= 1
    found.setdefault(".".join(names), (inline.get(node.lineno, ""), " ".join(above)))
  return found


def comment_of(field: str, comments: list[dict]) -> str:
  """The inline comment of the field's assignment (exact path, then shorter suffixes: `m.knn` in
  model_config() is "model.knn"), else the comment block above it; "" when there is none."""
  suffixes = [".".join(field.split(".")[i:]) for i in range(field.count(".") + 1)]
  for kind in (0, 1):
    for table in comments:
      for suffix in suffixes:
        if table.get(suffix, ("", ""))[kind]:
          return table[suffix][kind]
  return ""


def describe(config, path=None, flag: str = "config") -> str:
  """The config as `flag.field = value  # comment` lines (comments from `path`, then the package's
  configs/default.py and configs/paper.py, the base where every field is defined)."""
  sources = [p for p in (path, PACKAGE_CONFIGS / "default.py", PACKAGE_CONFIGS / "paper.py")
             if p and pathlib.Path(p).exists()]
  comments = [_comments(p) for p in sources]
  lines = []
  for field in field_paths(config):
    value = config
    for part in field.split("."):
      value = value[part]
    note = comment_of(field, comments)
    lines.append(f"{flag}.{field} = {value!r}" + (f"  # {note}" if note else ""))
  return "\n".join(lines)


def _field_comments(cls) -> dict[str, str]:
  """{field: its comment} of a dataclass: the comment after the field, else the comment lines
  right above it."""
  comments, above = {}, []
  for line in inspect.getsource(cls).splitlines():
    text = line.strip()
    if text.startswith("#"):
      above.append(text.lstrip("# "))
      continue
    field = re.match(r"(\w+)\s*:[^#]*?(?:#\s*(.*))?$", text)
    if field and not text.startswith(("def ", "class ", "@")):
      note = field.group(2) or " ".join(above)
      if note:
        comments.setdefault(field.group(1), note)
    above = []
  return comments


def describe_settings(settings, prefix: str) -> str:
  """A settings dataclass (nested ones included) as `prefix.field = value  # comment` lines."""
  lines = []

  def walk(obj, path):
    comments = _field_comments(type(obj))
    for f in dataclasses.fields(obj):
      value = getattr(obj, f.name)
      if dataclasses.is_dataclass(value):
        walk(value, f"{path}.{f.name}")
      else:
        note = comments.get(f.name)
        lines.append(f"{path}.{f.name} = {value!r}" + (f"  # {note}" if note else ""))

  walk(settings, prefix)
  return "\n".join(lines)
