"""Errors that a user can act on: each names the file or argument and what is wrong.

The command-line tools print these as one line and exit with code 2 (see `jaxflow.cli`);
anything else is a bug and keeps its traceback.
"""


class JaxflowError(Exception):
  """Base class of the errors a user can fix (bad file, bad argument, bad checkpoint)."""


class DataError(JaxflowError):
  """A data file is missing, unreadable or malformed."""

  def __init__(self, path, problem: str):
    self.path = str(path)
    self.problem = problem
    super().__init__(f"{self.path}: {problem}")

  def __reduce__(self):  # survives pickling between loader processes with path and problem
    return (type(self), (self.path, self.problem))


class CheckpointError(JaxflowError):
  """A checkpoint is missing, incomplete or does not match the model."""


class ConfigError(JaxflowError):
  """A config field or command-line argument is invalid."""


class NonFiniteError(JaxflowError):
  """Training produced a non-finite loss or gradient."""
