"""Training: the two-stage loop with jitted steps, held-out evaluation and checkpoints
(`trainer`), its losses (`losses`), metrics log and stop signals (`run_log`) and TensorBoard
events (`events`). It imports jaxflow.evaluation and everything below it; only the commands
(jaxflow.train) import it.
"""
