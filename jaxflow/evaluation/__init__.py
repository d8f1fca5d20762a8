"""Evaluation: the paper's metrics and OpenSceneFlow's three-way reading (`metrics`), the
official Argoverse 2 readings (`av2_eval`), the evaluation loop over a dataset (`evaluator`), its
tables and pictures (`reporting`, `tables`), flow files (`export`) and the AV2 challenge's
submission (`submission`). It imports jaxflow.methods, jaxflow.network, jaxflow.data,
jaxflow.viz, jaxflow.geometry and the shared helpers; never jaxflow.training.
"""
