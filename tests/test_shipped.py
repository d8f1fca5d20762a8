"""configs/shipped.py is the config of the shipped checkpoint: its model, data and training fields
are the ones the checkpoint stored (config.json and the step folder's own copy)."""

import json

import pytest

from jaxflow.configs import shipped
from jaxflow.network import checkpointing
from jaxflow.network.model_fields import ADDED_MODEL_FIELDS

SECTIONS = ("seed", "model", "data", "train")  # what made the parameters
# Fields added after the checkpoint was written, with the value that reproduces how it ran.
ADDED = {"model": ADDED_MODEL_FIELDS, "train": {"resume_with_new_recipe": False}}
EVAL_FIELDS = ("dataset", "split", "num_points", "num_iters", "batch_size", "seed", "every")


@pytest.fixture(scope="module")
def stored():
  if not checkpointing.SHIPPED_CHECKPOINT.exists():
    pytest.skip("no shipped checkpoint in this tree")
  readable = json.loads((checkpointing.SHIPPED_CHECKPOINT / "config.json").read_text())
  ckpts, _, config = checkpointing.open_checkpoint(checkpointing.SHIPPED_CHECKPOINT)
  ckpts.close()
  return readable, checkpointing.config_to_dict(config)


def test_shipped_config_is_the_checkpoints_own(stored):
  ours = checkpointing.config_to_dict(shipped.get_config())
  readable, in_step = stored
  for theirs in (readable, in_step):
    for section in SECTIONS:
      if not isinstance(theirs[section], dict):
        assert ours[section] == theirs[section], section
        continue
      assert {k: ours[section].get(k) for k in theirs[section]} == theirs[section], section
      added = {k: v for k, v in ours[section].items() if k not in theirs[section]}
      assert added == {k: ADDED.get(section, {})[k] for k in added}, section
    for field in EVAL_FIELDS:  # the end-of-run check (test_time came later: off, not stored)
      assert ours["eval"][field] == theirs["eval"][field], field
