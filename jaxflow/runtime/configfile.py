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

PACKAGE_CONFIGS = pathlib.Path(__file__).absolute().parent.parent / "configs"


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


def _setting_value(text, current, flag: str, nullable: bool):
  """`text` (a command line's string, or a value from Python) as the type of `current` (or None,
  where the field may be none)."""
  if not isinstance(text, str) or isinstance(current, str):
    value = text
  else:
    try:
      value = ast.literal_eval(text)
    except (ValueError, SyntaxError):
      value = text  # a bare word: a string field's value, refused below for any other type
  if value is None:
    ok = nullable
  elif isinstance(current, bool) or isinstance(value, bool):
    ok = isinstance(value, bool) and (current is None or isinstance(current, bool))
  elif isinstance(current, float):
    ok = isinstance(value, (int, float))
    value = float(value) if isinstance(value, int) else value
  elif current is None:
    ok = isinstance(value, (int, float, str))
  else:
    ok = isinstance(value, type(current))
  if not ok:
    kind = "None or " * nullable + type(current).__name__
    raise ConfigError(f"{flag}: {text!r} is not {kind}, as its default {current!r}")
  return value


def replace_settings(settings, assignments: dict, prefix: str):
  """A copy of a settings dataclass with `assignments` {dotted field: value} applied at any depth
  (strings are parsed as Python literals of the field's type; None where a field may be none).
  A name that is not a field, a value of another type, or one its dataclass refuses is a
  ConfigError naming `prefix.field` and, for a wrong name, the fields there are."""

  def put(obj, parts, value, flag):
    names = [f.name for f in dataclasses.fields(obj)]
    if parts[0] not in names:
      near = difflib.get_close_matches(parts[0], names, 3)
      raise ConfigError(f"{flag}: no field {parts[0]!r} in {type(obj).__name__} (fields: "
                        f"{', '.join(near or names)})")
    current = getattr(obj, parts[0])
    nullable = "None" in str(next(f.type for f in dataclasses.fields(obj) if f.name == parts[0]))
    if len(parts) > 1:
      if not dataclasses.is_dataclass(current):
        raise ConfigError(f"{flag}: {parts[0]!r} has no fields (it is {current!r})")
      new = put(current, parts[1:], value, flag)
    elif dataclasses.is_dataclass(current):
      if not (nullable and value in (None, "None")):
        raise ConfigError(f"{flag}: {parts[0]!r} is a block of settings: set its fields "
                          f"({flag}.FIELD=V)" + (", or None to leave the stage out" * nullable))
      new = None
    else:
      new = _setting_value(value, current, flag, nullable)
    try:
      return dataclasses.replace(obj, **{parts[0]: new})
    except (ValueError, TypeError) as e:
      raise ConfigError(f"{flag}: {e}") from None

  for path, value in assignments.items():
    settings = put(settings, path.split("."), value, f"{prefix}.{path}")
  return settings
