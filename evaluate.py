r"""Evaluates a checkpoint: `python -m jaxflow.evaluate` (jaxflow/evaluate.py) as a script.

    python evaluate.py --checkpoint runs/default --dataset synthetic_lidar:64 --split test
"""

from jaxflow import evaluate

if __name__ == "__main__":
  evaluate.run()
