r"""Trains a jaxflow model and evaluates it: `python -m jaxflow.train` (jaxflow/train.py) as a script.

    python train.py --config configs/default.py --workdir runs/default [--config.FIELD=VALUE ...]
"""

from jaxflow import train

if __name__ == "__main__":
  train.run()
