r"""Neural Scene Flow Prior (Li, Kooi Pontes, Lucey, NeurIPS 2021) on your point files: no training,
no checkpoint. The same command as `python -m jaxflow.predict --method nsfp`, with every flag of
jaxflow.predict (--lidar, --render, --max_points, --save_flows, ...); --method defaults to nsfp.

    python -m jaxflow.nsfp PC1 PC2 --out FLOW.npy [--objective exact|grid] [--steps 5000]
        [--max_points 8192] [--seed 0] [--lidar] [--render VIEW.png]

A coordinate MLP (8 x 128, ReLU) maps each pc1 point to its flow; it and a backward MLP (the cycle
term) are optimised from scratch with Adam on the truncated Chamfer distance, up to 5000 steps with
early stopping, and the flow of the lowest loss is returned (jaxflow.refine.optimiser.NSFP, the
`nsfp` method of jaxflow.methods.registry). --objective exact (default): NSFP's two-way Chamfer,
nearest points by k-d tree every step; grid: the one-way terms read from distance grids (faster,
less accurate on FT3D). From Python: `jaxflow.inference.predict_flow(pc1, pc2, method="nsfp",
objective="grid")`.

It takes minutes (~170 ms a step at 8192 points on a 2-core CPU, up to 5000 steps): a bar shows
the steps on a terminal; with stderr in a log file, a run expected to take over 30 s writes its
expected time (an estimate, from the pace of its first steps) and a line every 10% of its steps.
"""

from jaxflow import predict


def run():
  """`python -m jaxflow.nsfp`: jaxflow.predict with --method nsfp by default."""
  predict.run(default_method="nsfp", description=__doc__)


if __name__ == "__main__":
  run()
